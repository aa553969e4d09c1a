"""Compiling the kernels once per process, before the first step needs them, and saying so.

numba compiles a kernel at its first call, or loads it from its on-disk cache
(``kernel_cache``). Left to the first step, the compile (tens of seconds on the first start
after an install) would stall a node's first tick, or a replay's, without a word. The entry
points (node, replay, demo, bench, the test suite) call ``report_compile`` at start instead:
it runs a small scene through every kernel of the step -- the free step, a crowd's step in
lanes, the step with contacts and limits, the depth and joint-angle queries, the head's pose
fit, the guard and the published poses -- and says in one line when that compiled rather than
loaded.
"""
import sys
import time

__all__ = ['compile_kernels', 'report_compile']

_result = None


def _warm_up():
    from . import contact_kernels, head_kernels, lanes, state_kernels, step, step_unilateral
    from .head import KinematicState
    from .head_estimation import HeadEstimator, HeadEstimatorBank
    from .scene import ChainSpec, ColliderSpec, Scene, SolverSpec
    from .simulator import Simulator
    free = Simulator(Scene(chains=[ChainSpec(n_segments=2)],
                           solver=SolverSpec(integrator='rk4', dt=0.01)))
    free.advance_frame(0.02, KinematicState.still())
    free.segment_poses(free.t + 0.001)
    # A crowd: equal chains step in SIMD lanes (``lanes``; undamped: implicit damping would
    # take the general step).
    crowd = Simulator(Scene(chains=[ChainSpec(n_segments=2, damping=0.0)] * lanes.MIN_CHAINS,
                            solver=SolverSpec(integrator='rk4', dt=0.01)))
    crowd.advance_frame(0.02, KinematicState.still())
    # A far floor (never touched) and a cone limit: the contacts-and-limits loop runs.
    bounded = Simulator(Scene(chains=[ChainSpec(n_segments=2, swing_limit=1.0)],
                              colliders=[ColliderSpec.plane(point=(0.0, 0.0, -10.0),
                                                            normal=(0.0, 0.0, 1.0))],
                              solver=SolverSpec(integrator='rk4', dt=0.01)))
    bounded.advance_frame(0.02, KinematicState.still())
    bounded.contact_depths()
    bounded.joint_angles()
    head = HeadEstimator()
    for t in (0.0, 0.01, 0.02):
        head.add(t, (t, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    head.state_at(0.015)
    _ = head.sample_period          # compiles median_interval
    bank = HeadEstimatorBank([HeadEstimator(), head])   # (a node with frames)
    bank.states_at(0.015)
    bank.add_poses(1, 0.02, [(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)], [False])
    bank.longest_sample_period([1])
    return sum(sum(k.stats.cache_misses.values()) for k in (
        step.advance, step_unilateral.advance_unilateral, contact_kernels.resolve_workspace,
        lanes.advance_lanes,
        head_kernels.loess_fit, head_kernels.states_fit, head_kernels.fit_time,
        head_kernels.add_samples, head_kernels.longest_median_interval, head_kernels.track_table,
        head_kernels.point_kinematics, head_kernels.median_interval, state_kernels.guard_measures,
        state_kernels.segment_poses))


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
