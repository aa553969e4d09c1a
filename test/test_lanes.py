"""The crowd step in SIMD lanes (``core.lanes``) against the general compiled step: the same
results bit for bit (``np.array_equal``) on x, q, v, ω and f_c, for crowds of several sizes
(a multiple of ``LANES``, one block exactly, a partial last block) with chains that differ
(each on its own head with its own phase, its own length, mass, radius, damping, drag), each
supported term on; a crowd with skulls and joint limits through the contact step loop; and
scenes the lanes do not cover fall back to the general step."""
import dataclasses

import numpy as np
import pytest

from ponytail_ros.app.motions import crowd_motion
from ponytail_ros.core import lanes, step as compiled
from ponytail_ros.core.head import point_table
from ponytail_ros.core.scene import ChainSpec, ColliderSpec, Scene, SolverSpec
from ponytail_ros.core.simulator import Simulator

L = lanes.LANES
DT = 1e-3


def _crowd(n_chains, n_segments=6, seed=0, damping=0.0, drag=(0.0, 0.0), stiffness=0.0,
           wind=(0.0, 0.0, 0.0), integrator='rk4', projection=True, damping_method='explicit',
           gravity=(0.0, 0.0, -9.81), inertia=None):
    """``n_chains`` different chains of ``n_segments``, chain k on head k (``crowd_motion``)."""
    rng = np.random.default_rng(seed)
    chains = tuple(ChainSpec(
        name=f'c{k}', n_segments=n_segments, length=rng.uniform(0.2, 0.6),
        mass=rng.uniform(0.05, 0.2), radius=rng.uniform(0.005, 0.015), anchor_body=k,
        attach=tuple(rng.uniform(-0.1, 0.1, 3)), damping=damping * rng.uniform(0.5, 1.5),
        drag_linear=drag[0] * rng.uniform(0.5, 1.5), drag_quadratic=drag[1],
        stiffness=stiffness, inertia=inertia) for k in range(n_chains))
    solver = SolverSpec(integrator=integrator, dt=DT, projection=projection,
                        damping_method=damping_method)
    return Scene(chains=chains, n_kinematic_bodies=n_chains, gravity=gravity, wind=wind,
                 solver=solver)


def _kernel_inputs(scene, n_steps, t0=0.3, external=False, seed=1):
    """A simulator on the scene's crowd motion, run to ``t0`` (so the chains swing), its
    ``StepModel``, the anchor table of the next ``n_steps`` steps and the state."""
    motion = crowd_motion(len(scene.chains))
    sim = Simulator(scene, motion, 0.0)
    sim.advance_to(t0, motion)
    if external:
        rng = np.random.default_rng(seed)
        sim.set_external(0.01 * rng.standard_normal((sim.model.n, 3)),
                         1e-4 * rng.standard_normal((sim.model.n, 3)))
    m = sim.model
    A = sim._table(point_table(motion.states_at(sim._stage_times(n_steps)), m.anchor_body,
                               m.attach))
    return sim, sim._step_model(), A


def _run(kernel, sim, M, A, n_steps):
    st = sim.state
    x, q, v, w = (np.array(a, dtype=float) for a in (st.x, st.q, st.v, st.w))
    ext_F, ext_T = sim._external_arrays()
    f_c = np.zeros((sim.model.n, 3))
    status = kernel(M, A, n_steps, DT, x, q, v, w, ext_F, ext_T, f_c)
    return status, (x, q, v, w, f_c)


def _assert_identical(scene, n_steps=40, external=False):
    sim, M, A = _kernel_inputs(scene, n_steps, external=external)
    assert lanes.crowd_layout(sim.model) is not None and lanes.supports(M)
    s0, general = _run(compiled.advance, sim, M, A, n_steps)
    s1, lane = _run(lanes.advance_lanes, sim, M, A, n_steps)
    assert s0 == s1 == compiled.OK
    for name, a, b in zip(('x', 'q', 'v', 'w', 'f_c'), general, lane, strict=True):
        assert np.array_equal(a, b), name
    # The chains really differ (else a mix-up of lanes would go unseen).
    x = general[0].reshape(len(scene.chains), -1, 3)
    assert not np.array_equal(x[0], x[-1])


@pytest.mark.parametrize('n_chains', sorted({L, 2 * L, 2 * L + 3, L + 1, 5 * L + 2}))
def test_gravity_and_gyroscopic_bit_identical(n_chains):
    _assert_identical(_crowd(n_chains))


def test_explicit_damping_bit_identical():
    scene = _crowd(L + 2, damping=2e-5)
    assert lanes.supports(Simulator(scene)._step_model())
    _assert_identical(scene)


def test_drag_and_wind_bit_identical():
    _assert_identical(_crowd(L + 2, drag=(0.05, 0.2), wind=(1.0, -0.5, 0.2)))


def test_external_forces_bit_identical():
    _assert_identical(_crowd(L + 2), external=True)


def test_without_projection_and_gravity_bit_identical():
    _assert_identical(_crowd(L + 2, projection=False), n_steps=20)
    _assert_identical(_crowd(L + 2, gravity=(0.0, 0.0, 0.0), damping=1e-5), n_steps=20)


@pytest.mark.parametrize('damping', [0.0, 2e-5])
def test_bending_stiffness_bit_identical(damping):
    """Bending stiffness alone and summed with joint damping into one joint torque (the
    general step's order)."""
    scene = _crowd(L + 2, stiffness=2e-3, damping=damping)
    assert Simulator(scene)._step_model().stiffness_on
    _assert_identical(scene)


def test_all_terms_sixteen_segments_bit_identical():
    _assert_identical(_crowd(3 * L + 1, n_segments=16, damping=1e-5, drag=(0.02, 0.1),
                             stiffness=1e-3, wind=(0.5, 0.0, 0.0)), external=True)


def test_failed_joint_solve_reports_the_same_status():
    """A non-positive-definite A (here: a negative mass of one chain) fails in both."""
    sim, M, A = _kernel_inputs(_crowd(L + 1), 5)
    inv_mass = M.inv_mass.copy()
    inv_mass[sim.model.chain_start[2]:sim.model.chain_end[2]] *= -1.0
    M = M._replace(inv_mass=inv_mass)
    assert _run(compiled.advance, sim, M, A, 5)[0] == compiled.JOINT_SOLVE_FAILED
    assert _run(lanes.advance_lanes, sim, M, A, 5)[0] == compiled.JOINT_SOLVE_FAILED


def test_no_steps_leaves_f_c_alone():
    sim, M, A = _kernel_inputs(_crowd(L), 1)
    status, (x, q, v, w, f_c) = _run(lanes.advance_lanes, sim, M, A, 0)
    assert status == compiled.OK and not f_c.any() and np.array_equal(x, sim.state.x)


def _simulate(scene, force_general, t_end=0.1):
    motion = crowd_motion(len(scene.chains))
    sim = Simulator(scene, motion, 0.0)
    if force_general:
        sim._crowd = None
    reports = [sim.advance_to(t, motion) for t in np.arange(1, 13) * (t_end / 12)]
    rollout = sim.rollout(t_end + np.arange(1, 4) * 0.01, motion)
    return sim, reports, rollout


def _assert_simulations_identical(scene):
    """``scene`` simulated with the lanes (the simulator's choice, checked) and chain by chain:
    the same state, rollout, joint forces, steps and contact counts, bit for bit, no reset.
    Returns the lanes' simulator."""
    sim = Simulator(scene, crowd_motion(len(scene.chains)), 0.0)
    assert sim._kernel(sim._step_model()).kernel is lanes.advance_lanes
    a, reports_a, roll_a = _simulate(scene, False)
    b, reports_b, roll_b = _simulate(scene, True)
    for name in ('x', 'q', 'v', 'w'):
        assert np.array_equal(getattr(a.state, name), getattr(b.state, name)), name
        assert np.array_equal(getattr(roll_a, name), getattr(roll_b, name)), name
    assert np.array_equal(a.constraint_forces, b.constraint_forces)
    assert [r.steps for r in reports_a] == [r.steps for r in reports_b]
    assert (a.unilateral is None) == (b.unilateral is None)
    if a.unilateral is not None:
        assert a.unilateral.last == b.unilateral.last
    assert all(r.reset_reason is None for r in reports_a + roll_a.reports)
    return a


def test_simulator_dispatches_crowds_to_the_lanes():
    _assert_simulations_identical(_crowd(L + 3, damping=1e-5))


def _skulls_and_limits(scene, swing_limit=0.6):
    """``scene`` with a skull on every head that its chain hangs against, and swing limits."""
    chains = tuple(dataclasses.replace(c, attach=(-0.1, 0.0, 0.03), swing_limit=swing_limit,
                                       collide=True)
                   for c in scene.chains)
    skulls = tuple(ColliderSpec.sphere(radius=0.09, body=k, friction=0.3)
                   for k in range(len(chains)))
    return dataclasses.replace(scene, chains=chains, colliders=skulls)


@pytest.mark.parametrize('n_chains', [L + 3, 2 * L])
def test_crowd_with_colliders_and_limits_steps_in_lanes_bit_identical(n_chains):
    """The contact step loop takes the chains' steps in the lanes between its contact stages:
    the same state, joint forces, contacts and limits, bit for bit, as chain by chain."""
    a = _assert_simulations_identical(_skulls_and_limits(
        _crowd(n_chains, damping=1e-5, stiffness=1e-3, drag=(0.02, 0.1))))
    # The skulls really act: chains rest on them at the end.
    assert a.unilateral.last['contacts'] > 0


@pytest.mark.parametrize('kind', ['implicit_damping', 'symplectic_euler',
                                  'non_axisymmetric', 'few_chains', 'mixed_lengths'])
def test_unsupported_scenes_fall_back(kind):
    kw = {}
    n_chains = L + 1
    if kind == 'implicit_damping':
        kw = dict(damping=1e-4, damping_method='implicit')
    elif kind == 'symplectic_euler':
        kw = dict(integrator='symplectic_euler')
    elif kind == 'non_axisymmetric':
        kw = dict(inertia=[[1e-6, 2e-5, 3e-5]] * 6)
    elif kind == 'few_chains':
        n_chains = lanes.MIN_CHAINS - 1
    scene = _crowd(n_chains, **kw)
    if kind == 'mixed_lengths':
        chains = list(scene.chains)
        chains[-1] = ChainSpec(n_segments=5, anchor_body=len(chains) - 1)
        scene = Scene(chains=tuple(chains), n_kinematic_bodies=len(chains),
                      solver=scene.solver)
    sim = Simulator(scene, crowd_motion(n_chains), 0.0)
    assert sim._kernel(sim._step_model()).kernel is (
        compiled.advance_rk4 if scene.solver.integrator == 'rk4' else compiled.advance)
    a, _, roll_a = _simulate(scene, False, t_end=0.03)
    b, _, roll_b = _simulate(scene, True, t_end=0.03)
    for name in ('x', 'q', 'v', 'w'):
        assert np.array_equal(getattr(a.state, name), getattr(b.state, name)), name
