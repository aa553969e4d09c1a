"""Compiling the kernels a scene uses before its first step needs them, and saying so.

numba compiles a kernel at its first call, or loads it from its on-disk cache
(``kernel_cache``). Left to the first step, the compile (a minute or more on the first start
after an install) would stall a node's first tick, or a replay's, without a word. So the
kernels are compiled in stages (``STAGES``), each by running a small scene through it:

* ``free step``: the chains' own RK4 step (``step.advance_rk4``; also every scene's
  sub-steps), the anchor tracks and the per-tick queries (guard, published poses);
* ``other integrators``: the step of any integrator (``step.advance``: symplectic Euler,
  RATTLE);
* ``crowd lanes``: a crowd's step in SIMD lanes (``lanes.advance_lanes``);
* ``contact step``: the RK4 step with contacts and limits (``step_unilateral``), one chain at
  a time, and the depth and joint-angle queries;
* ``contact step (other integrators)``: the same with any integrator;
* ``crowd contacts``: the same with a crowd's chains in lanes;
* ``head fit``: the head pose's fit (``head_kernels``);
* ``markers``: the display markers' numbers.

``stages_for`` says which a scene uses: a scene without colliders or joint limits compiles
no contact stage, one of fewer than ``lanes.MIN_CHAINS`` equal chains no lanes, an RK4 scene
no other integrator (numba prunes the branches a scene does not take from the versions it
compiles: ``None`` arguments, ``step.chain_steps``).

Before compiling, one line says so, with an estimate from the stages whose kernels are not in
the cache; then each stage's progress: on a terminal (stderr a TTY) one line updated in
place, else a plain line per stage; at the end one line with the time taken. Loading a warm
cache says nothing.

Who calls: ``say_compiles(log)`` (node, replay) makes every ``Simulator`` built afterwards in
the process compile the stages its scene uses at its construction (``prepare``), said
through ``log``: a live change that adds colliders compiles the contact stage then, said too.
``report_compile(log)`` compiles every stage at once (the benches, the test suite,
``python -m ponytail_ros.core.compile``: a deploy-time step that fills the cache). A process
that calls neither compiles lazily, as numba does.

A cold cache is compiled on two cores when there are two: a child process compiles the
contact stage alone (``step_unilateral.compile_contact_stage``: the largest kernels, for the
types the contact step calls them with) while this one compiles the free step, the head fit,
the markers and the contact queries; then this one compiles the contact step's loop
(``advance_unilateral``), loading the contact stage from what the child wrote to the cache
(numba writes cache files atomically, so two processes may compile the same callee: the
later write wins, and both are the same code). A child that fails changes nothing but the
time: what it did not cache is compiled here.
``PONYTAIL_COMPILE_JOBS=1`` compiles in this process only (a shared or single-core machine);
the default is 2 where two cores are free. ``python -m ponytail_ros.bench.compile_cost``
measures cold and warm starts, per stage.
"""
import argparse
import os
import subprocess
import sys
import threading
import time

from . import kernel_cache

__all__ = ['STAGES', 'compile_kernels', 'prepare', 'report_compile', 'say_compiles',
           'say_if_cold', 'stages_for']

STAGES = ('free step', 'other integrators', 'crowd lanes', 'contact step',
          'contact step (other integrators)', 'crowd contacts', 'head fit', 'markers')
#: The stages compiled in the child process on two cores.
_CHILD_STAGES = ('contact step', 'contact step (other integrators)', 'crowd contacts')
#: Rough compile cost of each stage on one core of a small machine, s: for the estimate said
#: before compiling only (``bench.compile_cost`` measures them).
_ROUGH_SECONDS = {'free step': 20.0, 'other integrators': 25.0, 'crowd lanes': 35.0,
                  'contact step': 55.0, 'contact step (other integrators)': 15.0,
                  'crowd contacts': 35.0, 'head fit': 6.0, 'markers': 2.0}

#: Wall time (s) of each stage of the last compile in this process, in its order: what a
#: cold compile spends where (``bench.compile_cost``). On two cores a child stage is this
#: process's wait for the child beyond its own stages, then its load of the child's cache.
STAGE_SECONDS: dict = {}
#: This process's CPU time (s) of each stage of the last compile: on a shared machine the
#: steadier figure (one process: the compile's cost; two: the child's is not in it).
STAGE_CPU: dict = {}

# The child's part, run as ``python -c _CHILD <stage> ...``; it prints its cache misses.
_CHILD = 'from ponytail_ros.core.compile import _child; _child()'

_done: set = set()          # stages run in this process
_log = None                 # ``say_compiles``'s log (None: ``prepare`` does nothing)
_progress_on = True
_busy = False               # a compile under way (its warm-up scenes build Simulators)
_seconds = 0.0              # of every compile in this process
_compiled = False           # whether any of them compiled rather than loaded


# -- the stages' warm-up scenes ---------------------------------------------------------
def _warm_free():
    from .head import KinematicState, SwayYawMotion
    from .scene import ChainSpec, Scene, SolverSpec
    from .simulator import Simulator
    free = Simulator(Scene(chains=[ChainSpec(n_segments=2)],
                           solver=SolverSpec(integrator='rk4', dt=0.01)))
    still = KinematicState.still()
    free.advance_frame(0.02, still)
    free.advance_frame(0.04, still, head_prev=still)    # (a node's frames: frame_tables)
    free.segment_poses(free.t + 0.001)
    free.advance_to(free.t + 0.02, SwayYawMotion())     # (a motion's table: ``advance_to``)


def _crowd_scene(**kwargs):
    from . import lanes
    from .scene import ChainSpec, Scene, SolverSpec
    # Equal chains step in SIMD lanes (``lanes``; undamped: implicit damping would take the
    # general step).
    return Scene(chains=[ChainSpec(n_segments=2, damping=0.0)] * lanes.MIN_CHAINS,
                 solver=SolverSpec(integrator='rk4', dt=0.01), **kwargs)


def _far_floor():
    from .scene import ColliderSpec
    return ColliderSpec.plane(point=(0.0, 0.0, -10.0), normal=(0.0, 0.0, 1.0))


def _warm_other_integrators():
    from .head import KinematicState
    from .scene import ChainSpec, Scene, SolverSpec
    from .simulator import Simulator
    Simulator(Scene(chains=[ChainSpec(n_segments=2)],
                    solver=SolverSpec(integrator='symplectic_euler', dt=0.01))).advance_frame(
        0.02, KinematicState.still())


def _warm_crowd():
    from .head import KinematicState
    from .simulator import Simulator
    Simulator(_crowd_scene()).advance_frame(0.02, KinematicState.still())


def _bounded(integrator='rk4'):
    from .scene import ChainSpec, Scene, SolverSpec
    from .simulator import Simulator
    # A far floor (never touched) and a cone limit: the contacts-and-limits loop runs.
    return Simulator(Scene(chains=[ChainSpec(n_segments=2, swing_limit=1.0)],
                           colliders=[_far_floor()],
                           solver=SolverSpec(integrator=integrator, dt=0.01)))


def _warm_contacts(integrator='rk4'):
    from .head import KinematicState
    bounded = _bounded(integrator)
    bounded.advance_frame(0.02, KinematicState.still())
    bounded.contact_depths()
    bounded.joint_angles()


def _warm_contacts_other_integrators():
    _warm_contacts('symplectic_euler')


def _warm_contact_queries():
    # The contact stages' kernels outside the step: here while the child compiles the step's.
    bounded = _bounded()
    bounded.contact_depths()
    bounded.joint_angles()
    bounded._contact_workspace(bounded.unilateral.static_pose)


def _warm_contact_stage():
    # The contact stage alone (the child's part: ``step_unilateral.compile_contact_stage``).
    _bounded()._compile_contact_stage()


def _warm_crowd_contact_stage():
    from .simulator import Simulator
    Simulator(_crowd_scene(colliders=[_far_floor()]))._compile_contact_stage()


def _warm_crowd_contacts():
    from .head import KinematicState
    from .simulator import Simulator
    Simulator(_crowd_scene(colliders=[_far_floor()])).advance_frame(0.02,
                                                                    KinematicState.still())


def _warm_head():
    from .head_estimation import HeadEstimator, HeadEstimatorBank
    head = HeadEstimator()
    for t in (0.0, 0.01, 0.02):
        head.add(t, (t, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    head.state_at(0.015)
    head.prefetch((0.012, 0.017))   # (a tick's instants in one call: fits_at)
    _ = head.sample_period          # compiles median_interval
    bank = HeadEstimatorBank([HeadEstimator(), head])   # (a node with frames)
    bank.states_at(0.015)
    bank.add_poses(1, 0.02, [(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)], [False])
    bank.longest_sample_period([1])


def _warm_markers():
    import numpy as np

    from . import marker_kernels
    i0, none = np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64)
    k, unit = np.zeros(4), np.array([[0.0, 0.0, 0.0, 1.0]])
    # One segment: joint rows 0 (its origin) and 1 (the tip), capsule row 1, identity row 0.
    marker_kernels.chain_numbers(np.zeros((1, 3)), unit, np.ones(1), i0, i0, i0 + 1, i0 + 1, i0,
                                 True, k, k, k, k, np.empty((2, 7)), np.empty((2, 3)))
    # One sphere fixed in body 0.
    marker_kernels.collider_numbers(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), i0, i0,
                                    np.zeros((1, 3)), unit, i0, none, none, np.zeros(0),
                                    np.empty((1, 7)), np.empty((0, 3)),
                                    np.empty(1, dtype=np.bool_))


#: A child stage's part in the child (the rest is run here when the child is done; here,
#: while waiting for it, the contact queries: ``_warm_contact_queries``).
_CHILD_WARM = {'contact step': _warm_contact_stage,
               'contact step (other integrators)': _warm_contact_stage,
               'crowd contacts': _warm_crowd_contact_stage}

_WARM = {'free step': _warm_free, 'other integrators': _warm_other_integrators,
         'crowd lanes': _warm_crowd, 'contact step': _warm_contacts,
         'contact step (other integrators)': _warm_contacts_other_integrators,
         'crowd contacts': _warm_crowd_contacts, 'head fit': _warm_head,
         'markers': _warm_markers}


# -- what is compiled, what is cached ---------------------------------------------------
def _unilateral_is(in_lanes, constrained):
    """A signature test of ``advance_unilateral``: its ``in_lanes`` and ``constrained``
    arguments' types."""
    return lambda sig: (str(sig[24]), str(sig[26])) == (in_lanes, constrained)


def _stage_kernels(stage):
    """``(kernel, signature test or None)`` of the kernels ``stage`` compiles."""
    from . import (
        contact_model,
        head_kernels,
        lanes,
        limit_kernels,
        marker_kernels,
        state_kernels,
        step,
        step_unilateral,
    )
    uni = step_unilateral.advance_unilateral
    kernels = {
        'free step': [step.advance_rk4, state_kernels.guard_measures,
                      state_kernels.segment_poses, head_kernels.track_table,
                      head_kernels.point_kinematics, head_kernels.frame_tables,
                      head_kernels.sinusoid_table],
        'other integrators': [step.advance],
        'crowd lanes': [lanes.advance_lanes],
        'contact step': [(uni, _unilateral_is('none', 'none')),
                         contact_model.resolve_workspace, limit_kernels.joint_angles],
        'contact step (other integrators)': [(uni, _unilateral_is('none', 'bool'))],
        'crowd contacts': [(uni, _unilateral_is('bool', 'none'))],
        'head fit': [head_kernels.loess_fit, head_kernels.states_fit, head_kernels.fit_time,
                     head_kernels.add_samples, head_kernels.longest_median_interval,
                     head_kernels.median_interval, head_kernels.fits_at],
        'markers': [marker_kernels.chain_numbers, marker_kernels.collider_numbers],
    }[stage]
    return [k if isinstance(k, tuple) else (k, None) for k in kernels]


def _kernels():
    return [k for s in STAGES for k, _ in _stage_kernels(s)]


def _misses():
    """Cache misses of this process's kernels so far: how many numba compiled."""
    return sum(sum(k.stats.cache_misses.values()) for k in set(_kernels()))


def _cached(kernel, signature=None):
    """Whether numba's cache holds a compiled version of ``kernel`` (one whose signature
    passes the test ``signature``) that its index accepts (its source unchanged); True if
    that cannot be told."""
    if getattr(kernel._cache, 'cache_path', True) is None:
        return False                        # no cache (``kernel_cache.CACHE_WARNING``)
    try:
        index = kernel._cache._cache_file._load_index()
    except Exception:
        return True
    return any(signature is None or signature(key[0]) for key in index)


def _stage_misses_here():
    """Whether this process compiled the contact stage itself (after the child compiled
    it: the child's types were not the contact step's)."""
    from .contact_stage import resolve_chains_into
    return sum(resolve_chains_into.stats.cache_misses.values()) > 0


def _missing(stage):
    """Whether some kernel of ``stage`` is not in the cache (it will compile)."""
    return not all(_cached(k, s) for k, s in _stage_kernels(stage))


def stages_for(scene):
    """The stages (``STAGES``, in order) a ``Simulator`` of ``scene`` runs, with the head fit
    and the markers of a node or replay: contacts only with colliders or joint limits, lanes
    only for a crowd that ``lanes`` steps, the other integrators only for a scene using
    one."""
    from .simulator import Simulator
    _guard = _busy_set(True)
    try:
        sim = Simulator(scene)              # (only arrays: no kernel runs while _busy)
    finally:
        _busy_set(_guard)
    return _stages_of(sim)


def _stages_of(sim):
    from . import lanes, step
    M = sim._step_model()
    crowd = sim._crowd is not None and lanes.supports(M)
    rk4 = M.integrator == step.RK4
    contact = sim.unilateral is not None
    need = {'free step', 'head fit', 'markers'}
    if crowd:
        need.add('crowd lanes')
    if not rk4:
        need.add('other integrators')
    if contact:
        need.add('crowd contacts' if crowd else
                 'contact step' if rk4 else 'contact step (other integrators)')
    return tuple(s for s in STAGES if s in need)


def _busy_set(value):
    global _busy
    old, _busy = _busy, value
    return old


# -- running the stages -----------------------------------------------------------------
def _cores():
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _jobs():
    """Processes for a cold compile: ``PONYTAIL_COMPILE_JOBS`` (1 or 2), else 2 where two
    cores are free."""
    text = os.environ.get('PONYTAIL_COMPILE_JOBS', '').strip()
    if not text:
        return min(2, _cores())
    if text not in ('1', '2'):
        raise ValueError(f'PONYTAIL_COMPILE_JOBS = {text!r} is not allowed: must be 1 or 2 '
                         '(processes compiling a cold kernel cache)')
    return int(text)


def _child():
    """The child's part of a cold compile (the stages named in its arguments); prints its
    cache misses."""
    from .contact_stage import resolve_chains_into
    for stage in sys.argv[1:]:
        _CHILD_WARM[stage]()
    print(_misses() + sum(resolve_chains_into.stats.cache_misses.values()), flush=True)


class _Progress:
    """Each stage's progress: one line rewritten in place on a terminal (a ticker thread
    updates its seconds), else a plain line per stage through ``log``."""

    def __init__(self, log, count, estimate, tty):
        self.log, self.count, self.estimate, self.tty = log, count, estimate, tty
        self.k, self.name, self.t0 = 0, '', time.perf_counter()
        self._stop = threading.Event()
        self._thread = None
        if tty:
            self._thread = threading.Thread(target=self._tick, daemon=True)
            self._thread.start()

    def _line(self):
        return (f'\rponytail_ros: compiling [{self.k}/{self.count}] {self.name:<32} '
                f'{time.perf_counter() - self.t0:4.0f} s of about {self.estimate:.0f} s ')

    def _tick(self):
        while not self._stop.wait(0.5):
            sys.stderr.write(self._line())
            sys.stderr.flush()

    def start(self, name):
        self.k += 1
        self.name = name
        self._stage_t0 = time.perf_counter()
        if self.tty:
            sys.stderr.write(self._line())
            sys.stderr.flush()

    def done(self):
        if not self.tty:
            self.log(f'ponytail_ros: [{self.k}/{self.count}] compiled {self.name} in '
                     f'{time.perf_counter() - self._stage_t0:.1f} s')

    def close(self):
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            sys.stderr.write('\r' + ' ' * 79 + '\r')
            sys.stderr.flush()


def _estimate(missing, jobs):
    here = sum(_ROUGH_SECONDS[s] for s in missing if jobs == 1 or s not in _CHILD_STAGES)
    child = sum(_ROUGH_SECONDS[s] for s in missing if jobs > 1 and s in _CHILD_STAGES)
    return max(here, child)


def _say(msg):
    print(msg, file=sys.stderr, flush=True)


def _announce(missing, jobs, log, progress):
    """The line said before compiling ``missing``; returns its ``_Progress``."""
    where = kernel_cache.cache_location()
    estimate = _estimate(missing, jobs)
    when = ' once after install' if where else ''
    cache = f'cache: {where}' if where else 'no cache: at every start'
    log(f'ponytail_ros: compiling the simulation kernels{when}, about {estimate:.0f} s '
        f'({", ".join(missing)}; {cache})...')
    return _Progress(log, len(missing), estimate, progress and sys.stderr.isatty())


def _start_child(stages):
    """The child process compiling ``stages`` (None if there are none or it cannot start)."""
    if not stages:
        return None
    try:
        return subprocess.Popen([sys.executable, '-c', _CHILD, *stages],
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    except OSError:
        return None


def _wait_child(child):
    """The child's cache misses, once it is done."""
    out = child.communicate()[0]
    return int(out.strip()) if out.strip().isdigit() else 0


def _run(stages, log, progress):
    """Run ``stages`` (not yet run in this process), compiling what is missing from the
    cache, said through ``log`` (None: nothing said). Returns ``(seconds, compiled)``."""
    global _busy
    stages = [s for s in STAGES if s in stages and s not in _done]
    if not stages:
        return 0.0, False
    t_start = time.perf_counter()
    missing = [s for s in stages if _missing(s)]
    jobs = _jobs() if kernel_cache.cache_location() is not None else 1
    bar = _announce(missing, jobs, log, progress) if missing and log is not None else None
    child = _start_child([s for s in missing if s in _CHILD_STAGES] if jobs > 1 else [])
    to_child = child.args[3:] if child is not None else []
    misses0, child_misses = _misses(), 0
    _busy = True
    try:
        # This process's stages first, the child's (waited for, then loaded) last.
        for stage in ([s for s in stages if s not in to_child] + to_child):
            t0, c0 = time.perf_counter(), time.process_time()
            said = bar is not None and stage in missing
            if said:
                bar.start(stage + (' (second process)' if stage in to_child else ''))
            if stage in to_child and child.returncode is None:
                _warm_contact_queries()
                child_misses = _wait_child(child)
            _WARM[stage]()
            if stage in to_child and child_misses and _stage_misses_here() and log is not None:
                log('ponytail_ros: warning: the contact stage compiled in both processes '
                    '(step_unilateral.compile_contact_stage no longer builds the types '
                    'advance_unilateral calls it with): the cold compile took longer')
            _done.add(stage)
            STAGE_SECONDS[stage] = time.perf_counter() - t0
            STAGE_CPU[stage] = time.process_time() - c0
            if said:
                bar.done()
    finally:
        _busy = False
        if child is not None and child.returncode is None:
            child.kill()
            child.wait()
        if bar is not None:
            bar.close()
    seconds = time.perf_counter() - t_start
    compiled = _misses() - misses0 + child_misses > 0
    if compiled and log is not None:
        log(f'ponytail_ros: compiled the simulation kernels in {seconds:.1f} s'
            + (' (once after install; later starts load them from the cache)'
               if kernel_cache.cache_location() else ''))
    return seconds, compiled


def compile_kernels(stages=STAGES, log=None, progress=True):
    """Compile (or load from numba's cache) the kernels of ``stages`` not yet run in this
    process; returns ``(seconds, compiled)`` of every compile in the process so far,
    ``compiled`` True when numba had to compile (the first start after an install or an
    upgrade) rather than load its cache. ``log``: where to say it (None: nothing said)."""
    global _seconds, _compiled
    STAGE_SECONDS.clear()
    STAGE_CPU.clear()
    seconds, compiled = _run(stages, log, progress)
    _seconds += seconds
    _compiled = _compiled or compiled
    return _seconds, _compiled


def say_if_cold(log=None):
    """Say at once, through ``log`` (default stderr), that the kernels will compile before
    the first step when the cache is cold (``kernel_cache.is_cold``), with an estimate for a
    scene with colliders: what a command says first, before the seconds its imports take
    (this module and ``kernel_cache`` import neither numba nor the kernels). The stages,
    the estimate for the scene and the progress follow once the scene is known. Returns
    whether it said so."""
    if not kernel_cache.is_cold():
        return False
    where = kernel_cache.cache_location()
    estimate = _estimate(['free step', 'contact step', 'head fit', 'markers'], _jobs())
    (log or _say)(f'ponytail_ros: the simulation kernels compile before the first step, about '
                  f'{estimate:.0f} s' + (f', once after install (cache: {where})' if where
                                         else ', at every start (no cache)'))
    return True


def say_compiles(log=None, progress=True):
    """From now on every ``Simulator`` built in this process compiles the stages its scene
    uses at its construction (``prepare``), said through ``log`` (a callable taking a line;
    default stderr); ``progress``: a progress line on a terminal."""
    global _log, _progress_on
    _log = log or _say
    _progress_on = progress


def report_compile(log=None, progress=True):
    """Compile every stage (``compile_kernels``), saying so through ``log`` (a callable,
    default stderr) when it compiled; later ``Simulator``s say theirs likewise
    (``say_compiles``)."""
    say_compiles(log, progress)
    return compile_kernels(STAGES, _log, progress)


def prepare(sim):
    """The stages ``Simulator`` ``sim`` uses, compiled (or loaded) and said if
    ``say_compiles`` was called; else nothing (numba compiles at the first call)."""
    if _log is None or _busy:
        return
    stages = [s for s in _stages_of(sim) if s not in _done]
    if stages:
        compile_kernels(stages, _log, _progress_on)


def main(argv=None):
    p = argparse.ArgumentParser(
        prog='python -m ponytail_ros.core.compile',
        description='Compile the simulation kernels into numba\'s cache (a deploy step: run '
                    'it once after install, as the user the node runs as, so that the first '
                    'start loads them).')
    p.add_argument('--stages', default=','.join(STAGES),
                   help='comma-separated stages (default: all: %(default)s)')
    args = p.parse_args(argv)
    stages = [s.strip() for s in args.stages.split(',') if s.strip()]
    bad = [s for s in stages if s not in STAGES]
    if bad:
        p.error(f'--stages: {", ".join(bad)} not among {", ".join(STAGES)}')
    say_compiles()
    seconds, compiled = compile_kernels(stages, _log)
    where = kernel_cache.cache_location()
    print(f'ponytail_ros: kernels {"compiled" if compiled else "already cached"} '
          f'({seconds:.1f} s); cache: {where or "none"}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
