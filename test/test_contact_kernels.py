"""The compiled contacts and limits (``contact_stage`` and its modules) against the NumPy
implementation they replaced (``_oracle_collision``, ``_oracle_limits``), call by call.

Each scene is run with the compiled resolve; every call's inputs (the state after the
integrator step, the anchors, the colliders' pose, the step) are replayed through the oracle,
and the two results must agree to ``AGREE`` relative to the largest entry of each of x, q, v,
ω (or absolutely where that is below 1: m, unit quaternion, m/s, rad/s), with the same
numbers of contacts, limits and position passes. The scenes cover spheres (a rooted ponytail),
capsules (world and on a moving body), planes, friction, swing and twist limits on the first
and inner joints, several chains, a non-axisymmetric inertia and a run without projection.
"""
import numpy as np
import pytest

from ponytail_ros.app.motions import ShakeNodHead as ShakeMotion
from ponytail_ros.core import (
    ChainSpec,
    KinematicState,
    Scene,
    Simulator,
    StillMotion,
    broad_phase,
    collision,
    contact_model,
    limits,
    step,
)
from ponytail_ros.core.rotations import quat_from_rotvec, quat_multiply
from ponytail_ros.core.scene import ColliderSpec, SolverSpec
from ponytail_ros.core.state import half_vectors

import _oracle_collision
import _oracle_limits
from helpers import TwoBodies

DT = 1.0 / 240.0
AGREE = 1e-11   # relative; most scenes agree to ~1e-13. Friction on a nearly stuck contact
                # (slip ~1e-8 m/s) amplifies rounding: its direction is ill-conditioned.


def _ponytail(friction=0.4, **kw):
    R, r = 0.1, 0.01
    root = (R + r) * np.array([-np.cos(0.35), 0.0, np.sin(0.35)])
    chain = ChainSpec(n_segments=10, length=0.4, mass=0.1, radius=r, attach=tuple(root),
                      damping=2e-4, drag_linear=0.1, drag_quadratic=0.1, **kw)
    return Scene(chains=(chain,), colliders=(ColliderSpec.sphere(radius=R, friction=friction),))


def _floor_rope():
    chain = ChainSpec(n_segments=10, length=1.0, mass=0.2, radius=0.005, attach=(0, 0, 0),
                      rest_direction=(1, 0, 0), damping=2e-4, drag_linear=0.05)
    return Scene(chains=(chain,), colliders=(
        ColliderSpec.plane(point=(0, 0, -0.6), normal=(0, 0, 1), friction=0.5),))


def _obstacles(**solver):
    n = 12
    inertia = np.tile([2e-6, 4e-5, 6e-5], (n, 1)) if solver.pop('skew', False) else None
    chain = ChainSpec(n_segments=n, length=0.8, mass=0.1, radius=0.006, attach=(0, 0, 0),
                      rest_direction=(1, 0.3, 0), damping=1e-3,
                      inertia=None if inertia is None else tuple(map(tuple, inertia)))
    return Scene(chains=(chain,), solver=SolverSpec(**solver), colliders=(
        ColliderSpec.sphere(center=(0.3, 0.1, -0.25), radius=0.1, friction=0.3),
        ColliderSpec.capsule(center=(0.55, 0.0, -0.35), axis=(0, 1, 0.2), half_length=0.3,
                             radius=0.03),
        ColliderSpec.plane(point=(0, 0, -0.6), normal=(0, 0.1, 1), body=None, friction=0.6)))


def _crowd():
    """Three chains on the shaken head: two collide with the head, the shoulder and a floor
    (one with limits), one does not collide but has limits. Frictionless: with several rows
    per chain a nearly stuck contact (slip ~1e-8 m/s) takes a friction impulse along its slip
    direction, which rounding-level differences in the velocities turn (an ill-conditioned
    direction in both implementations, not a difference between them)."""
    R = 0.1
    cols = (ColliderSpec.sphere(radius=R),
            ColliderSpec.capsule(center=(-0.05, 0.0, 1.32), axis=(0.0, 1.0, 0.0),
                                 half_length=0.2, radius=0.06, body=None),
            ColliderSpec.plane(point=(0.0, 0.0, 1.25), normal=(0.0, 0.0, 1.0), body=None))
    chains = (ChainSpec(n_segments=6, length=0.35, mass=0.06, radius=0.008,
                        attach=(-0.11, 0.0, 0.0), damping=2e-4, drag_linear=0.1),
              ChainSpec(n_segments=8, length=0.4, mass=0.08, radius=0.008,
                        attach=(-0.08, 0.07, 0.04), damping=2e-4, drag_linear=0.1,
                        swing_limit=0.5, twist_limit=0.25),
              ChainSpec(n_segments=5, length=0.3, mass=0.05, radius=0.008,
                        attach=(0.0, -0.11, 0.0), damping=2e-4, collide=False,
                        swing_limit=(0.3, 0.6, 0.6, 0.6, 0.6)))
    return Scene(chains=chains, colliders=cols)


def _limits_only():
    chain = ChainSpec(n_segments=10, length=0.4, mass=0.1, radius=0.01, attach=(-0.1, 0, 0),
                      damping=2e-4, drag_linear=0.1, drag_quadratic=0.1, swing_limit=0.3,
                      twist_limit=0.2)
    return Scene(chains=(chain,))


SCENES = {
    'sphere, rooted ponytail, friction': (_ponytail, ShakeMotion, 0.8),
    'sphere and limits': (lambda: _ponytail(swing_limit=0.6, twist_limit=0.3), ShakeMotion, 0.6),
    'floor, friction': (_floor_rope, lambda: StillMotion((0.0, 0.0, 0.0)), 1.2),
    'sphere, capsule, plane': (_obstacles, lambda: StillMotion((0.0, 0.0, 0.0)), 1.5),
    'non-axisymmetric inertia': (lambda: _obstacles(skew=True), lambda: StillMotion(), 1.0),
    'no projection': (lambda: _obstacles(projection=False), lambda: StillMotion(), 0.8),
    'swing and twist limits': (_limits_only, ShakeMotion, 0.8),
    'several chains': (_crowd, ShakeMotion, 0.8),
}


def _moving_shoulder():
    chain = ChainSpec(n_segments=8, length=0.5, mass=0.05, radius=0.005, attach=(0, 0, 0),
                      damping=2e-4, drag_linear=0.05)
    shoulder = ColliderSpec.capsule(center=(0, 0, 0), axis=(0, 1, 0), half_length=0.15,
                                    radius=0.04, body=1)
    return Scene(chains=(chain,), n_kinematic_bodies=2, colliders=(shoulder,))


SCENES['capsule on a moving body'] = (_moving_shoulder, TwoBodies, 1.5)


def _caged():
    """A short chain hanging in a cage of twelve small spheres (on the head), 1 mm clear of them:
    every collider is within the chain's reach, so the candidate rows (4 segments × 12
    colliders) overflow the row tables' usual room (``ROW_COLLIDERS`` per segment) and the
    step is resolved again with grown tables (``contact_model.grown``)."""
    chain = ChainSpec(n_segments=4, length=0.4, mass=0.05, radius=0.01, attach=(0, 0, 0),
                      damping=2e-4, drag_linear=0.05)
    cage = tuple(ColliderSpec.sphere(center=(0.036 * np.cos(a), 0.036 * np.sin(a), z),
                                     radius=0.025, friction=0.0)
                 for a, z in zip(np.linspace(0, 2 * np.pi, 12, endpoint=False),
                                 np.tile([-0.12, -0.2, -0.28], 4), strict=True))
    return Scene(chains=(chain,), colliders=cage)


SCENES['caged: the row tables grow'] = (_caged, ShakeMotion, 0.6)


def _swept():
    """The rooted ponytail among twenty world spheres in a row behind the head, one of them
    under the hanging chain: from ``SWEEP_COLLIDERS`` round colliders on, the broad phase
    tests only those near each chain along the row (``broad_phase.sweep_order``)."""
    scene = _ponytail()
    row = tuple(ColliderSpec.sphere(center=(-0.2, y, -0.32), radius=0.06, body=None,
                                    friction=0.3)
                for y in np.linspace(-1.9, 1.9, 20))
    return Scene(chains=scene.chains, colliders=scene.colliders + row)


SCENES['many spheres: the broad phase sweeps'] = (_swept, ShakeMotion, 0.6)


def test_the_swept_scene_takes_the_sweep():
    """The premise of the swept scene: more round colliders than ``SWEEP_COLLIDERS``."""
    scene = _swept()
    assert len(scene.colliders) >= broad_phase.SWEEP_COLLIDERS


def test_the_caged_chain_overflows_the_usual_row_tables():
    """The premise of the caged scene: every collider is within the chain's reach of its
    anchor (so the broad phase keeps every pair), and the candidate rows, segments × colliders,
    exceed the usual tables (segments × ``ROW_COLLIDERS``): its steps take the grown path."""
    scene = _caged()
    chain = scene.chains[0]
    reach = chain.length + chain.radius
    for col in scene.colliders:
        assert np.linalg.norm(np.asarray(col.center)) - col.radius < reach
    assert len(scene.colliders) > contact_model.ROW_COLLIDERS


def _per_step(sim):
    """Make ``sim`` take every step through ``Unilateral.resolve`` (the per-step path it uses
    for sub-stepped steps) instead of its compiled step loop, so that calls can be recorded;
    ``test_the_compiled_loop_equals_the_per_step_path`` shows both give the same state."""
    sim._call_unilateral = lambda *args, **kw: (step.SUBSTEPS, 0)


@pytest.mark.parametrize('name', ['sphere and limits', 'capsule on a moving body',
                                  'swing and twist limits', 'several chains',
                                  'caged: the row tables grow'])
def test_the_compiled_loop_equals_the_per_step_path(name):
    """The compiled step loop with contacts and limits inside
    (``step_unilateral.advance_unilateral``, its contact workspace kept across the calls)
    gives bit for bit the state of the per-step path (compiled step, then ``resolve`` from
    Python, a fresh workspace per call), so the oracle comparison below, made on the per-step
    path, covers it."""
    make_scene, make_motion, seconds = SCENES[name]
    motion = make_motion()
    sims = [Simulator(make_scene(), motion), Simulator(make_scene(), motion)]
    _per_step(sims[1])
    for k in range(1, int(round(seconds / DT)) + 1):
        for sim in sims:
            assert sim.advance_to(k * DT, motion).reset_reason is None
    for a, b in zip((sims[0].state.x, sims[0].state.q, sims[0].state.v, sims[0].state.w),
                    (sims[1].state.x, sims[1].state.q, sims[1].state.v, sims[1].state.w),
                    strict=True):
        assert np.array_equal(a, b)
    assert sims[0].unilateral.last == sims[1].unilateral.last


def _recorded_calls(scene, motion, seconds):
    """Run ``scene``; return every resolve call's inputs (copied) and compiled outputs."""
    sim = Simulator(scene, motion)
    _per_step(sim)
    uni = sim.unilateral
    compiled = uni.resolve
    calls = []

    def record(x, q, v, w, anchor, pose, project=True, dt=None):
        args = [a.copy() for a in (x, q, v, w)]
        out = compiled(x, q, v, w, anchor, pose, project, dt)
        calls.append((args, anchor, pose, project, dt, [o.copy() for o in out],
                      dict(uni.last), sim.model.q_rest.copy()))
        return out

    uni.resolve = record
    for k in range(1, int(round(seconds / DT)) + 1):
        report = sim.advance_to(k * DT, motion)
        assert report.reset_reason is None
    return sim, calls


@pytest.mark.parametrize('name', list(SCENES))
def test_compiled_resolve_matches_the_numpy_oracle(name):
    make_scene, make_motion, seconds = SCENES[name]
    sim, calls = _recorded_calls(make_scene(), make_motion(), seconds)
    oracle = _oracle_collision.Unilateral(sim.model, sim.dt)
    worst = 0.0
    active = passes = 0
    for args, anchor, pose, project, dt, out, last, q_rest in calls:
        sim.model.q_rest[:] = q_rest
        ref = oracle.resolve(*args, anchor, pose, project, dt)
        for a, b in zip(out, ref, strict=True):
            worst = max(worst, float(np.max(np.abs(a - b))) / max(1.0, float(np.max(np.abs(b)))))
        assert last == oracle.last
        active += last['contacts'] + last['limits']
        passes += last['position_passes']
    assert worst < AGREE, f'compiled and NumPy resolve differ by {worst:.3g}'
    assert active > 50 and passes > 5            # the scene did exercise contacts/limits


@pytest.mark.parametrize('name', ['sphere and limits', 'several chains', 'floor, friction'])
def test_rows_and_detection_match_the_oracle(name):
    """Candidate rows (contacts and limits) and the reported depths, on recorded states."""
    make_scene, make_motion, seconds = SCENES[name]
    sim, calls = _recorded_calls(make_scene(), make_motion(), 0.5 * seconds)
    m = sim.model
    oracle = _oracle_collision.Unilateral(m, sim.dt)
    if m.has_colliders:
        det = collision._Detector(m, collision.Colliders(m))
        det_ref = _oracle_collision._Detector(m, _oracle_collision.Colliders(m))
    compared = 0
    for args, anchor, pose, _project, dt, _, _, q_rest in calls[::5]:
        m.q_rest[:] = q_rest
        sim.unilateral.dt = oracle.dt = dt
        got, ref = sim.unilateral.rows(*args, anchor, pose), oracle.rows(*args, anchor, pose)
        assert (got is None) == (ref is None)
        if got is None:
            continue
        compared += 1
        for key in ref:
            assert np.allclose(got[key], ref[key], rtol=0.0, atol=AGREE), key
        if m.has_colliders:
            h = half_vectors(m.length, args[1])
            for report in (False, True):
                d_got = det.detect(args[0], h, anchor.position, pose, report)
                d_ref = det_ref.detect(args[0], h, anchor.position, pose, report)
                for a, b in zip(d_got, d_ref, strict=True):
                    assert np.allclose(a, b, rtol=0.0, atol=AGREE)
    assert compared > 5


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_limit_kernels_match_the_oracle(seed):
    """Angles, limit rows and the exact projection on random far-from-rest poses of two
    chains (one on a turning head body, one with a rest direction)."""
    scene = Scene(chains=(ChainSpec(n_segments=7, swing_limit=0.4, twist_limit=0.25,
                                    rest_direction=(0.3, 0.2, -1.0)),
                          ChainSpec(n_segments=5, swing_limit=(0.2, 0.5, 0.5, 0.5, 0.5),
                                    attach=(0.1, 0.0, 0.0))), gravity=(0, 0, 0))
    head = KinematicState.still((0.0, 0.0, 1.0), (0.1, -0.2, 0.3, 0.927))
    head.orientation /= np.linalg.norm(head.orientation)
    head.angular_velocity[:] = (0.4, -0.3, 0.8)
    sim = Simulator(scene, head)
    m, anchor = sim.model, sim.anchors(head)
    rng = np.random.default_rng(seed)
    q = quat_multiply(quat_from_rotvec(rng.normal(size=(m.n, 3)) * 1.1), sim.state.q)
    w = rng.normal(size=(m.n, 3)) * 2.0
    for a, b in zip(limits.joint_angles(m, q, anchor.orientation),
                    _oracle_limits.joint_angles(m, q, anchor.orientation), strict=True):
        assert np.max(np.abs(a - b)) < AGREE

    def every(gap, sep):
        return np.ones(gap.shape, bool)
    got = limits.limit_rows(m, q, w, anchor, every)
    ref = _oracle_limits.limit_rows(m, q, w, anchor, every)
    for key in ref:
        assert np.allclose(got[key], ref[key], rtol=0.0, atol=AGREE), key
    got = limits.project_limits(m, q, anchor.orientation)
    ref = _oracle_limits.project_limits(m, q, anchor.orientation)
    assert got is not None and np.max(np.abs(got - ref)) < AGREE
    assert limits.project_limits(m, got, anchor.orientation, 1e-9) is None


@pytest.mark.parametrize('name', ['sphere and limits', 'floor, friction'])
def test_one_row_solve_is_the_general_solve_bit_for_bit(name):
    """``solve_rows_into`` with its workspace's scratch takes a call of one row (most steps
    of a ponytail on its skull) without the general path's grouping and dense problems
    (``_solve_one_row``); it gives the impulse and the velocity change of the general path
    (``solve_rows``, whose empty scratch always takes it) bit for bit: every candidate row of
    recorded states (contacts; limits, which also move the parent), as a normal row and as
    a friction row, with closing and separating rates, added onto non-zero velocities."""
    from ponytail_ros.core import contact_impulses, contact_joints, contact_model
    make_scene, make_motion, seconds = SCENES[name]
    sim, calls = _recorded_calls(make_scene(), make_motion(), 0.5 * seconds)
    m, uni = sim.model, sim.unilateral
    n = m.n
    rng = np.random.default_rng(0)
    sc = contact_model.solve_scratch(1, 1, n, m.n_chains)
    compared = pushed = parents = 0
    for args, anchor, pose, _project, dt, _, _, q_rest in calls[::7]:
        m.q_rest[:] = q_rest
        uni.dt = dt
        rows = uni.rows(*args, anchor, pose)
        if rows is None:
            continue
        R, I = collision._rows_arrays(rows)
        h, inv_I = np.empty((n, 3)), np.empty((n, 3, 3))
        C, Lo = np.empty((n, 3, 3)), np.empty((n, 3, 3))
        assert contact_joints.joint_factors(np.ascontiguousarray(args[1]), uni.model_args, h,
                                           inv_I, C, Lo)
        v0, w0 = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
        for r in range(R.shape[0]):
            for friction in (False, True):
                b = np.array([rng.normal() * 0.1])
                bound = np.array([abs(rng.normal()) * 0.01]) if friction else np.zeros(0)
                dv, dw = v0.copy(), w0.copy()
                lam = contact_impulses.solve_rows(R[r:r + 1], I[r:r + 1], b, bound, h, inv_I, C,
                                                  Lo, uni.model_args, dv, dw)
                v, w, one = v0.copy(), w0.copy(), np.full(1, np.nan)
                contact_impulses.solve_rows_into(R[r:r + 1], I[r:r + 1], b, bound, h, inv_I, C, Lo,
                                                 uni.model_args, v, w, one, sc)
                assert np.array_equal(one, lam)
                assert np.array_equal(v, dv) and np.array_equal(w, dw)
                compared += 1
                pushed += lam[0] > 0.0
                parents += I[r, 1] >= 0
    assert compared > 50 and pushed > 10
    assert parents > 0 or not m.has_limits


@pytest.mark.parametrize('k, seed', [(2, 0), (5, 1), (9, 2), (14, 3)])
def test_small_lcp_is_exact_and_matches_the_oracle(k, seed):
    """The compiled LCP on random positive definite W (some rows pulling, some pushing):
    λ ≥ 0, slack ≥ 0 and λ·slack = 0 to rounding for the regularised W + REG·diag(W) it
    solves; λ agrees with the NumPy principal pivoting; the Lawson–Hanson fall-back gives the
    same λ."""
    from ponytail_ros.core import small_solves as K
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(k, k + 2))
    W = A @ A.T / k
    b = rng.normal(size=k)
    lam = K.lcp(W, b)
    slack = (W + K.REG * np.diag(np.diag(W))) @ lam + b
    assert np.any(lam > 0.0) and np.any(lam == 0.0)
    assert np.all(lam >= 0.0) and np.all(slack >= -1e-12 * np.abs(b).max())
    assert np.all(np.abs(lam * slack) < 1e-12 * (1 + lam @ lam))
    assert np.max(np.abs(lam - _oracle_collision._lcp(W, b))) < 1e-9 * (1 + np.abs(lam).max())
    d = 1.0 / np.sqrt(np.diag(W))
    Ws = W * d[:, None] * d[None, :] + K.REG * np.eye(k)
    assert np.max(np.abs(K.nnls_quadratic(Ws, b * d) * d - lam)) < 1e-9 * (1 + np.abs(lam).max())


def test_collider_pose_matches_the_oracle():
    """Colliders on two moving bodies and in the world: the compiled pose (world geometry,
    body motion, the speed bound) equals the NumPy one."""
    from ponytail_ros.core.head import AnchorKinematics
    scene = Scene(chains=(ChainSpec(n_segments=3),), n_kinematic_bodies=2, colliders=(
        ColliderSpec.sphere(center=(0.01, 0.02, 0.03), radius=0.1, body=0),
        ColliderSpec.capsule(center=(0.1, 0, 0), axis=(0, 1, 0.3), half_length=0.2,
                             radius=0.03, body=1),
        ColliderSpec.capsule(center=(0, 0, 1.3), axis=(1, 0, 0), half_length=0.1,
                             radius=0.05, body=None),
        ColliderSpec.plane(point=(0, 0, 0.2), normal=(0.1, 0, 1), body=1),
        ColliderSpec.plane(point=(0, 0, 0), normal=(0, 0, 1), body=None)))
    sim = Simulator(scene, KinematicState.still(np.zeros((2, 3))))
    rng = np.random.default_rng(5)
    q = rng.normal(size=(2, 4))
    bodies = AnchorKinematics(rng.normal(size=(2, 3)), rng.normal(size=(2, 3)),
                              rng.normal(size=(2, 3)), q / np.linalg.norm(q, axis=1)[:, None],
                              rng.normal(size=(2, 3)))
    got = collision.Colliders(sim.model).pose(bodies)
    ref = _oracle_collision.Colliders(sim.model).pose(bodies)
    for field in ('a0', 'd2', 'normal', 'origin', 'velocity', 'omega', 'speed'):
        assert np.max(np.abs(getattr(got, field) - getattr(ref, field))) < AGREE, field
    assert np.all(got.speed[[2, 4]] == 0.0) and np.all(got.speed[[0, 1, 3]] > 0.0)


_LEAK_CHECK = """
import gc
import sys
import numpy as np
sys.path.insert(0, {test_dir!r})
from numba.core.runtime import rtsys
import test_contact_kernels as T
from ponytail_ros.core import Simulator
out = []
for name in ('sphere and limits', 'several chains', 'caged: the row tables grow'):
    make_scene, make_motion, _ = T.SCENES[name]
    motion = make_motion()
    sim = Simulator(make_scene(), motion)
    sim.advance_to(0.05, motion)
    # The previous scene's simulator is garbage in reference cycles: collected now, not by a
    # collection that happens to run inside the window (its arrays would count as freed there).
    gc.collect()
    gc.disable()
    s0 = rtsys.get_allocation_stats()
    for k in range(1, 41):
        sim.advance_to(0.05 + k / 120, motion)
    s1 = rtsys.get_allocation_stats()
    gc.enable()
    out.append((s1.mi_alloc - s0.mi_alloc, s1.mi_free - s0.mi_free))
print(out)
"""


def test_compiled_steps_free_every_array_they_allocate():
    """The kernels that borrow (``_nrt=False``: no reference counting) must not upset numba's
    counts: over 40 ticks of contact scenes (the grown-tables path included), every array the
    compiled calls allocate is freed, and no other (the cyclic collector is held off during the
    count: it freed a previous scene's arrays inside the window once, 29 frees more than
    allocations). numba counts allocations only when started with
    ``NUMBA_NRT_STATS=1``, hence a process of its own."""
    import ast
    import os
    import subprocess
    import sys
    test_dir = os.path.dirname(os.path.abspath(__file__))
    env = dict(os.environ, NUMBA_NRT_STATS='1')
    res = subprocess.run([sys.executable, '-c', _LEAK_CHECK.format(test_dir=test_dir)],
                         env=env, capture_output=True, text=True, check=True)
    counts = ast.literal_eval(res.stdout.strip().splitlines()[-1])
    for allocated, freed in counts:
        assert allocated > 100          # the calls did allocate (workspaces, row scratch)
        assert freed == allocated
