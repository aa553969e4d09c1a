"""Compiling the kernels once per process, before the first step needs them, and saying so.

numba compiles a kernel at its first call, or loads it from its on-disk cache
(``kernel_cache``). Left to the first step, the compile (minutes on the first start after an
install) would stall a node's first tick, or a replay's, without a word. The entry points
(node, replay, demo, bench, the test suite) call ``report_compile`` at start instead: it runs
small scenes through every kernel of the step -- the free step, a crowd's step in lanes, the
step with contacts and limits, the depth and joint-angle queries, the head's pose fit, the
guard, the published poses and the markers' numbers -- and says in one line when that
compiled rather than loaded.

A cold cache is compiled on two cores when there are two: the step with contacts and limits
(the largest kernel, about half of the compile) in a child process, the rest here at the same
time; then every kernel is run here once more, loading what the child wrote to the cache
(numba writes cache files atomically, so two processes may compile the same callee: the
later write wins, and both are the same code). A child that fails changes nothing but the
time: what it did not cache is compiled here. ``PONYTAIL_COMPILE_JOBS=1`` compiles in this
process only (a shared or single-core machine); the default is 2 where two cores are free.
``python -m ponytail_ros.bench.compile_cost`` measures both ways from a cold cache.
"""
import os
import subprocess
import sys
import time

__all__ = ['compile_kernels', 'report_compile']

_result = None

#: Wall time (s) of each part of the last ``_warm_up`` in this process, in its order: what a
#: cold compile spends where (``bench.compile_cost``). Two cores: ``contact step`` is this
#: process's wait for the child beyond its own parts, then its load of the child's cache.
STAGE_SECONDS: dict = {}

# The child's part (``_warm_contacts``), run as ``python -c _CHILD``; it prints its cache
# misses.
_CHILD = 'from ponytail_ros.core.compile import _child; _child()'


def _warm_free():
    from .head import KinematicState
    from .scene import ChainSpec, Scene, SolverSpec
    from .simulator import Simulator
    free = Simulator(Scene(chains=[ChainSpec(n_segments=2)],
                           solver=SolverSpec(integrator='rk4', dt=0.01)))
    still = KinematicState.still()
    free.advance_frame(0.02, still)
    free.advance_frame(0.04, still, head_prev=still)    # (a node's frames: frame_tables)
    free.segment_poses(free.t + 0.001)


def _warm_crowd():
    from . import lanes
    from .head import KinematicState
    from .scene import ChainSpec, Scene, SolverSpec
    from .simulator import Simulator
    # A crowd: equal chains step in SIMD lanes (``lanes``; undamped: implicit damping would
    # take the general step).
    crowd = Simulator(Scene(chains=[ChainSpec(n_segments=2, damping=0.0)] * lanes.MIN_CHAINS,
                            solver=SolverSpec(integrator='rk4', dt=0.01)))
    crowd.advance_frame(0.02, KinematicState.still())


def _warm_contacts():
    from .head import KinematicState
    from .scene import ChainSpec, ColliderSpec, Scene, SolverSpec
    from .simulator import Simulator
    # A far floor (never touched) and a cone limit: the contacts-and-limits loop runs.
    bounded = Simulator(Scene(chains=[ChainSpec(n_segments=2, swing_limit=1.0)],
                              colliders=[ColliderSpec.plane(point=(0.0, 0.0, -10.0),
                                                            normal=(0.0, 0.0, 1.0))],
                              solver=SolverSpec(integrator='rk4', dt=0.01)))
    bounded.advance_frame(0.02, KinematicState.still())
    bounded.contact_depths()
    bounded.joint_angles()


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


def _kernels():
    from . import (contact_kernels, head_kernels, lanes, marker_kernels, state_kernels, step,
                   step_unilateral)
    return (step.advance, step_unilateral.advance_unilateral, contact_kernels.resolve_workspace,
            lanes.advance_lanes,
            head_kernels.loess_fit, head_kernels.states_fit, head_kernels.fit_time,
            head_kernels.add_samples, head_kernels.longest_median_interval,
            head_kernels.track_table, head_kernels.point_kinematics, head_kernels.frame_tables,
            head_kernels.median_interval, head_kernels.fits_at, marker_kernels.chain_numbers,
            marker_kernels.collider_numbers, state_kernels.guard_measures,
            state_kernels.segment_poses)


def _misses():
    """Cache misses of this process's kernels so far: how many numba compiled."""
    return sum(sum(k.stats.cache_misses.values()) for k in _kernels())


def _cached(kernel):
    """Whether numba's cache holds a compiled version of ``kernel`` that its index accepts
    (its source unchanged); True if that cannot be told (then nothing is started for it)."""
    try:
        return bool(kernel._cache._cache_file._load_index())
    except Exception:
        return True


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
    """The child's part of a cold compile; prints its cache misses."""
    _warm_contacts()
    print(_misses(), flush=True)


def _warm_up():
    """Run every kernel once; returns the cache misses (of this process and its child)."""
    from . import step_unilateral
    STAGE_SECONDS.clear()
    child = None
    if _jobs() > 1 and not _cached(step_unilateral.advance_unilateral):
        try:
            child = subprocess.Popen([sys.executable, '-c', _CHILD], stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, text=True)
        except OSError:
            child = None
    try:
        for name, part in (('free step', _warm_free), ('crowd lanes', _warm_crowd),
                           ('head fit', _warm_head), ('markers', _warm_markers)):
            t0 = time.perf_counter()
            part()
            STAGE_SECONDS[name] = time.perf_counter() - t0
    except BaseException:
        if child is not None:
            child.kill()
            child.wait()
        raise
    t0 = time.perf_counter()
    out = child.communicate()[0] if child is not None else ''
    child_misses = int(out.strip()) if out.strip().isdigit() else 0
    _warm_contacts()                # loads the child's cache (compiles what it did not)
    STAGE_SECONDS['contact step'] = time.perf_counter() - t0
    return _misses() + child_misses


def compile_kernels():
    """Compile the kernels (or load them from numba's cache), once per process; returns
    ``(seconds, compiled)``, ``compiled`` True when numba had to compile (the first start
    after an install or an upgrade) rather than load its cache."""
    global _result
    if _result is None:
        t0 = time.perf_counter()
        misses = _warm_up()
        _result = (time.perf_counter() - t0, misses > 0)
    return _result


def report_compile(log=None):
    """``compile_kernels``, saying so in one line (``log``: a callable, default stderr) when
    it compiled in this process."""
    first = _result is None
    seconds, compiled = compile_kernels()
    if compiled and first:
        msg = (f'ponytail_ros: compiled the simulation step in {seconds:.1f} s (once after '
               'install; later starts load it from the cache)')
        (log or (lambda m: print(m, file=sys.stderr, flush=True)))(msg)
    return seconds, compiled
