"""The constrained symplectic Euler and RATTLE steps and the guard's rate checks (ROS-free).

Measured figures quoted in the docstrings come from these very scenes (10-segment ponytail,
0.4 m, 0.1 kg; thin chain of ``test_stability``), at the default step 1/240 s unless stated.
"""
import dataclasses
import math
from itertools import pairwise

import numpy as np
import pytest
from scipy.linalg import lapack

from ponytail_ros.app.motions import reference_motion
from ponytail_ros.core import ChainSpec, Scene, SceneError, Simulator, SolverSpec, StillMotion
from ponytail_ros.core.reference import default_reference_dir, load_reference, reference_errors
from ponytail_ros.core.rotations import cross, quat_axis_x, quat_from_rotvec, quat_to_matrix
from ponytail_ros.core.state import half_vectors

from helpers import chain_sim, reference_ponytail, total_energy as energy
from oracle.integrators import free_rotation, rotation_kick
from oracle.solver import Dynamics
from oracle.stabilization import project_velocities

HEAD = (0.0, 0.0, 1.6)
STILL = StillMotion(HEAD)
SE = 'symplectic_euler'


def ponytail(n=10, **kw):
    return reference_ponytail(n, **kw)


def thin_chain(n=5):
    """Segments with I_axial = 1e-4 I_perp (as ``test_stability.thin_chain``)."""
    ip = (0.1 / n) * (0.4 / n) ** 2 / 12.0
    return ponytail(n, inertia=tuple((1e-4 * ip, ip, ip) for _ in range(n)),
                    rest_direction=(0.3, 0.0, -1.0))


def make_sim(chain, integrator=SE, dt=1 / 240, motion=STILL, **solver):
    return chain_sim(chain, motion, integrator, dt, **solver)



def spun(chain, spin, **kw):
    """``chain`` at rest, then every segment spun about its own axis at ``spin`` rad/s plus a
    small wobble, velocities consistent with the joints."""
    sim = make_sim(chain, **kw)
    st = sim.state.copy()
    st.w = spin * quat_axis_x(st.q) + np.array([0.5, 0.0, 0.3])
    anchor = sim.anchors(STILL.state_at(0.0))
    st.v = project_velocities(sim.model, anchor.velocity, st.w,
                              half_vectors(sim.model.length, st.q))
    sim.reset(STILL.state_at(0.0), 0.0, state=st)
    return sim


def energies(sim, duration, fps=60.0):
    """Energy after every call of ``1/fps`` s (J); asserts no reset and closed joints."""
    out = [energy(sim)]
    for k in range(1, int(round(duration * fps)) + 1):
        r = sim.advance_to(k / fps, STILL)
        assert r.reset_reason is None, r.reset_reason
        assert r.max_gap < 1e-12
        out.append(energy(sim))
    return np.array(out)


def releasable(chain):
    """E0 - E_rest of ``chain`` on the still head (J): the scale of energy errors."""
    rest = make_sim(dataclasses.replace(chain, rest_direction=None))
    return energy(make_sim(chain)) - energy(rest)


def axial_spin(sim):
    return np.sum(quat_axis_x(sim.state.q) * sim.state.w, axis=1)


# -- energy ------------------------------------------------------------------------------------
def test_symplectic_euler_energy_error_is_bounded_and_first_order():
    """Still head, no damping, the ponytail released at 45°, 5 s: the energy oscillates within
    ±1.4 % of the releasable energy at 1/240 s (0.62 % at 1/480, 0.30 % at 1/960: first order)
    and does not drift (mean over the last second within 0.1 % of the first second's)."""
    chain = ponytail(rest_direction=(math.sqrt(0.5), 0.0, -math.sqrt(0.5)))
    scale = releasable(chain)
    amplitude = {}
    for dt in (1 / 240, 1 / 960):
        e = energies(make_sim(chain, dt=dt), 5.0)
        e = (e - e[0]) / scale
        amplitude[dt] = np.max(np.abs(e))
        assert abs(e[-60:].mean() - e[:61].mean()) < 1e-3
    assert amplitude[1 / 240] < 0.02
    assert amplitude[1 / 960] < amplitude[1 / 240] / 3.0


@pytest.mark.parametrize('spin', [100.0, 1000.0])
def test_symplectic_euler_axial_spin_of_any_rate_costs_nothing(spin):
    """Thin segments (I_axial = 1e-4 I_perp) spinning about their axes at dt·Ω = 0.42 and 4.2:
    no reset, the axial spin conserved to rounding (measured 4e-14 relative), and the energy
    curve the same as without spin to 1e-4 of the releasable energy (measured 3e-6 at 100 rad/s,
    3e-5 at 1000 rad/s): the spin adds nothing to the first-order error of the swing."""
    chain = thin_chain()
    scale = releasable(chain)
    e_still = energies(spun(chain, 0.0), 2.0)
    sim = spun(chain, spin)
    s0 = axial_spin(sim)
    e_spin = energies(sim, 2.0)
    assert np.max(np.abs(axial_spin(sim) - s0)) < 1e-9 * spin
    assert np.max(np.abs((e_spin - e_spin[0]) - (e_still - e_still[0]))) < 1e-4 * scale


def test_symplectic_euler_non_axisymmetric_spin_is_stable():
    """Other inertias take Catto's implicit Newton step: thin, slightly flattened segments
    (I = (1e-4, 1, 1.1) I_perp) spinning at 300 rad/s (dt·Ω = 1.25) stay finite with joints
    closed and bounded energy. Measured: +5.8 % of the releasable energy at first, then the
    implicit Euler damping of the fast precession takes 97 % of it within 2 s (at 30 rad/s:
    +0.4 %, -3.9 %)."""
    n = 5
    ip = (0.1 / n) * (0.4 / n) ** 2 / 12.0
    chain = ponytail(n, inertia=tuple((1e-4 * ip, ip, 1.1 * ip) for _ in range(n)),
                     rest_direction=(0.3, 0.0, -1.0))
    sim = spun(chain, 300.0)
    assert not sim.axisymmetric
    e = energies(sim, 2.0)
    scale = releasable(chain)
    assert e.max() - e[0] < 0.1 * scale
    assert e[-1] < e[0]


# -- the rotation kick ---------------------------------------------------------------------
def _random_bodies(inertia, seed=0, n=64):
    rng = np.random.default_rng(seed)
    sc = Scene(chains=(ChainSpec(n_segments=n, inertia=tuple(map(tuple, inertia(rng, n)))),))
    dyn = Dynamics(Simulator(sc).model)
    q = quat_from_rotvec(rng.normal(size=(n, 3)) * 2.0)
    w = rng.normal(size=(n, 3)) * 50.0
    return dyn, q, w


def _kinetic(dyn, q, w):
    R = quat_to_matrix(q)
    wb = np.einsum('nji,nj->ni', R, w)
    return 0.5 * np.sum(dyn.model.inertia * wb * wb, axis=1)


def test_rotation_kick_axisymmetric_keeps_the_free_body_invariants():
    """No torque: the axial spin is unchanged and |ω⊥| kept (the implicit-midpoint precession
    is a rotation), so the kinetic energy is unchanged, at any step."""
    def inertia(rng, n):
        ia = rng.uniform(1e-8, 2e-4, n)
        ip = rng.uniform(1e-6, 1e-4, n)
        return np.stack([ia, ip, ip], axis=1)
    dyn, q, w = _random_bodies(inertia)
    assert dyn.axisymmetric
    e = quat_axis_x(q)
    for h in (1e-3, 1 / 60):
        w1 = rotation_kick(dyn, q, w, np.zeros_like(w), h)
        assert np.allclose(np.sum(w1 * e, axis=1), np.sum(w * e, axis=1), rtol=0, atol=1e-12)
        perp = lambda u: u - np.sum(u * e, axis=1, keepdims=True) * e  # noqa: E731
        assert np.allclose(np.linalg.norm(perp(w1), axis=1), np.linalg.norm(perp(w), axis=1),
                           rtol=1e-12)
        assert np.allclose(_kinetic(dyn, q, w1), _kinetic(dyn, q, w), rtol=1e-12)


def test_rotation_kick_general_inertia_is_catto_newton_step():
    """Other inertias: one Newton step of I(ω⁺ - ω) + h ω⁺ × Iω⁺ = hT (body frame) from ω.
    Its residual is second order in h, and it never adds kinetic energy to a free body here."""
    def inertia(rng, n):
        return rng.uniform(1e-6, 1e-4, (n, 3))
    dyn, q, w = _random_bodies(inertia)
    assert not dyn.axisymmetric
    I = dyn.model.inertia
    R = quat_to_matrix(q)
    residuals = []
    for h in (1e-4, 1e-5):
        w1 = rotation_kick(dyn, q, w, np.zeros_like(w), h)
        wb0, wb1 = (np.einsum('nji,nj->ni', R, u) for u in (w, w1))
        f = I * (wb1 - wb0) + h * cross(wb1, I * wb1)
        residuals.append(np.max(np.abs(f / (I * np.abs(wb0)).max(axis=1, keepdims=True))))
        assert np.all(_kinetic(dyn, q, w1) <= _kinetic(dyn, q, w) * (1 + 1e-12))
    assert residuals[1] < residuals[0] / 50.0          # O(h²): 100x for 10x smaller h


def test_free_rotation_is_the_exact_torque_free_flow():
    """Axisymmetric segments: the angular momentum (world) and the kinetic energy are kept, and
    one step of h equals two of h/2 (a flow, not an approximation), at any spin."""
    def inertia(rng, n):
        ia = rng.uniform(1e-8, 2e-4, n)
        ip = rng.uniform(1e-6, 1e-4, n)
        return np.stack([ia, ip, ip], axis=1)
    dyn, q, w = _random_bodies(inertia)
    x, v = np.zeros_like(w), np.zeros_like(w)

    def momentum(q, w):
        R = quat_to_matrix(q)
        wb = np.einsum('nji,nj->ni', R, w)
        return np.einsum('nij,nj->ni', R, dyn.model.inertia * wb)
    for h in (1e-3, 1 / 60):
        _, q1, w1 = free_rotation(dyn, x, q, v, w, h)
        _, qa, wa = free_rotation(dyn, x, q, v, w, h / 2)
        _, q2, w2 = free_rotation(dyn, x, qa, v, wa, h / 2)
        assert np.allclose(momentum(q1, w1), momentum(q, w), rtol=1e-12, atol=1e-15)
        assert np.allclose(_kinetic(dyn, q1, w1), _kinetic(dyn, q, w), rtol=1e-12)
        assert np.allclose(w2, w1, rtol=0, atol=1e-9 * np.abs(w).max())
        assert np.allclose(quat_to_matrix(q2), quat_to_matrix(q1), rtol=0, atol=1e-9)


# -- the step ----------------------------------------------------------------------------------
@pytest.mark.parametrize('integrator, damping', [(SE, 0.0), ('rattle', 1e-3)])
def test_step_leaves_joints_and_velocities_closed_with_one_factorisation_per_step(
        monkeypatch, integrator, damping):
    """Symplectic Euler and RATTLE, moving head, 1 s: positions closed to rounding, velocities
    tangent to the joints (the RATTLE projection), and A factorised once per step (the
    projection's factor is the next step's): two solves, one factorisation."""
    calls = []
    real = lapack.dpbtrf
    monkeypatch.setattr(lapack, 'dpbtrf', lambda *a, **k: calls.append(1) or real(*a, **k))
    motion = reference_motion()
    sim = make_sim(ponytail(damping=damping), integrator, motion=motion)
    r = sim.advance_to(1.0, motion)
    assert r.steps == 240 and r.reset_reason is None
    assert len(calls) <= r.steps + 1
    m, st = sim.model, sim.state
    h = half_vectors(m.length, st.q)
    anchor = sim._last_anchor[1]
    c_dot = m.parent_side(anchor.velocity, st.v + cross(st.w, h)) - (st.v - cross(st.w, h))
    assert np.max(np.abs(c_dot)) < 1e-12
    assert np.max(sim.joint_gaps()) < 1e-12


REF_DIR = default_reference_dir()


@pytest.mark.skipif(not REF_DIR.is_dir(), reason=f'reference data not found in {REF_DIR}')
@pytest.mark.parametrize('name, bound_240, bound_1000', [
    ('N5_moving_hanging', 2e-2, 1e-3), ('N10_moving_hanging_damped', 2e-2, 5e-3)])
def test_symplectic_euler_accuracy_against_the_reference(name, bound_240, bound_1000):
    """Largest distance of any joint point to the shared reduced-coordinate reference over 3 s
    of the moving head. Measured: N5 1.1e-2 m at 1/240 s, 2.9e-4 m at 1/1000 s; N10 damped
    1.1e-2 and 2.6e-3 m (the unconstrained v += h a, ω += h α before: 8.4e-2, 2.3e-2 m and
    0.20, 1.9e-2 m)."""
    ref = load_reference(REF_DIR / f'ponytail_{name}.json')
    errors = [reference_errors(ref, SolverSpec(integrator=SE, dt=dt,
                                               max_steps_per_call=10**6)).max()
              for dt in (1 / 240, 1 / 1000)]
    assert errors[0] < bound_240
    assert errors[1] < bound_1000


def test_symplectic_euler_without_projection_still_steps():
    """``projection=False``: the velocity form of C̈ = 0 (no position correction): the joints
    drift slowly, the chain stays finite."""
    sim = make_sim(ponytail(damping=2e-4), motion=reference_motion(), projection=False,
                   guard_max_gap=10.0)
    r = sim.advance_to(2.0, reference_motion())
    assert r.reset_reason is None and sim.state.is_finite()
    assert 1e-9 < r.max_gap < 0.1


# -- RATTLE ------------------------------------------------------------------------------------
def _end_positions(chain, integrator, dt, motion, duration=1.0, **solver):
    sim = make_sim(chain, integrator, dt, motion, **solver)
    r = sim.advance_to(duration, motion)
    assert r.reset_reason is None, r.reset_reason
    return sim.state.x.copy()


@pytest.mark.parametrize('case', ['release', 'moving head, damping and drag'])
def test_rattle_is_second_order(case):
    """Joint positions after 1 s against RK4 at 1/4000 s (itself ~1e-9 m off): the error
    falls 4x per halving of the step (1/480 → 1/1920 s; symplectic Euler: 2.0x). With explicit
    damping and drag too: the velocity-dependent forces of the second half kick are taken at
    the extrapolated end velocity (taken at u½ instead, the step was first order in them:
    2.1x). With a turning head the segments spin about their own axes: the drift's exact
    free rotation keeps the order (a drift with ω⊥ held and the gyroscopic precession in the
    kicks fell to 2.3x at 1/7680 s, ``test_rattle_is_second_order_with_axial_spin``)."""
    if case == 'release':
        chain = ponytail(5, rest_direction=(math.sqrt(0.5), 0.0, -math.sqrt(0.5)))
        motion, solver = STILL, {}
    else:
        chain, motion = ponytail(5, damping=2e-4, drag_linear=0.05), reference_motion()
        solver = dict(damping_method='explicit')
    ref = _end_positions(chain, 'rk4', 1 / 4000, motion, **solver)
    errors = [np.max(np.linalg.norm(
        _end_positions(chain, 'rattle', 1 / hz, motion, **solver) - ref, axis=1))
        for hz in (480, 960, 1920)]
    assert errors[0] < 1e-4
    for coarse, fine in pairwise(errors):
        assert 3.5 < coarse / fine < 4.6


def test_rattle_is_second_order_with_axial_spin():
    """The 10-segment ponytail hanging from a head that yaws at up to π rad/s (segments spin
    about their own axes with it), 0.25 s: self-convergence 4x per halving down to 1/15360 s
    (measured 4.0x; with the gyroscopic precession split into the kicks instead: 2.3x)."""
    from ponytail_ros.app.motions import SinusoidHead
    motion = SinusoidHead(p0=HEAD, amplitude=(0.0, 0.0, 0.0), frequency=(0.0, 0.0, 0.0),
                          yaw_amplitude=0.5, yaw_frequency=1.0)
    x = {hz: _end_positions(ponytail(), 'rattle', 1 / hz, motion, duration=0.25)
         for hz in (3840, 7680, 15360)}
    coarse = np.max(np.linalg.norm(x[3840] - x[7680], axis=1))
    fine = np.max(np.linalg.norm(x[7680] - x[15360], axis=1))
    assert 3.5 < coarse / fine < 4.6


def test_rattle_energy_error_is_bounded_and_second_order():
    """The ponytail released at 45° (as the symplectic Euler test above), 5 s: the energy never
    rises above its start (RATTLE's projection only takes energy out), its error is at most
    0.5 % of the releasable energy at 1/240 s (measured 0.28 %; symplectic Euler 1.4 %) and falls
    faster than 10x from 1/240 to 1/960 s (measured 41x; first order: 4x)."""
    chain = ponytail(rest_direction=(math.sqrt(0.5), 0.0, -math.sqrt(0.5)))
    scale = releasable(chain)
    amplitude = {}
    for dt in (1 / 240, 1 / 960):
        e = energies(make_sim(chain, 'rattle', dt), 5.0)
        e = (e - e[0]) / scale
        assert e.max() <= 1e-12
        amplitude[dt] = np.max(np.abs(e))
    assert amplitude[1 / 240] < 5e-3
    assert amplitude[1 / 960] < amplitude[1 / 240] / 10.0


@pytest.mark.parametrize('spin', [100.0, 1000.0])
def test_rattle_axial_spin_of_any_rate_costs_nothing(spin):
    """RATTLE shares symplectic Euler's rotation kick and drift: thin segments spinning about
    their axes at dt·Ω = 0.42 and 4.2 keep their axial spin to rounding and their energy curve
    equals the one without spin to 1e-4 of the releasable energy."""
    chain = thin_chain()
    scale = releasable(chain)
    e_still = energies(spun(chain, 0.0, integrator='rattle'), 2.0)
    sim = spun(chain, spin, integrator='rattle')
    s0 = axial_spin(sim)
    e_spin = energies(sim, 2.0)
    assert np.max(np.abs(axial_spin(sim) - s0)) < 1e-9 * spin
    assert np.max(np.abs((e_spin - e_spin[0]) - (e_still - e_still[0]))) < 1e-4 * scale


def test_rattle_needs_projection():
    with pytest.raises(SceneError) as err:
        SolverSpec(integrator='rattle', projection=False).validate()
    assert err.value.field == 'solver.projection'
    assert "integrator 'rattle'" in str(err.value)


# -- the guard -----------------------------------------------------------------------------
def test_guard_max_step_angle_is_validated():
    with pytest.raises(SceneError) as err:
        SolverSpec(guard_max_step_angle=0.0).validate()
    assert err.value.field == 'solver.guard_max_step_angle' and '(0.0, 100.0]' in str(err.value)
    with pytest.raises(SceneError):
        SolverSpec(guard_max_step_angle=float('inf')).validate()
    assert SolverSpec().guard_max_step_angle == 2.5


@pytest.mark.parametrize('integrator', ['rk4', SE, 'rattle'])
def test_guard_reports_a_solver_failure(integrator):
    """A joint solve that fails (a non-finite orientation makes a pivot of J M⁻¹ Jᵀ
    non-positive, as a blow-up would) resets the chain to rest and says why."""
    sim = make_sim(ponytail(), integrator)
    st = sim.state.copy()
    st.q[3] = np.nan
    sim.reset(STILL.state_at(sim.t), sim.t, state=st)
    r = sim.advance_to(0.1, STILL)
    assert r.reset_reason == 'solver failure: J M⁻¹ Jᵀ is not positive definite'
    assert sim.state.is_finite() and np.max(sim.joint_gaps()) < 1e-12


def _set_rates(sim, w):
    """Give ``sim`` the angular velocities ``w`` (rad/s), linear ones consistent with the
    joints."""
    st = sim.state.copy()
    st.w = np.asarray(w, dtype=float)
    anchor = sim.anchors(STILL.state_at(sim.t))
    st.v = project_velocities(sim.model, anchor.velocity, st.w,
                              half_vectors(sim.model.length, st.q))
    sim.reset(STILL.state_at(sim.t), sim.t, state=st)


@pytest.mark.parametrize('integrator', ['rk4', SE])
def test_guard_catches_a_joint_turning_too_fast_per_step(integrator):
    """The guard's view of a state (a call with no step due): the second segment swinging at
    700 rad/s relative to the first (2.92 rad per 1/240 s step), tip speed 14 m/s, below
    guard_max_speed: reset. 550 rad/s (2.29 rad) passes."""
    for rate, caught in ((700.0, True), (550.0, False)):
        sim = make_sim(ponytail(2), integrator)
        w = np.zeros((2, 3))
        w[1] = (0.0, rate, 0.0)
        _set_rates(sim, w)
        reason = sim.advance_to(sim.t, STILL).reset_reason
        if caught:
            assert reason.startswith('joint angular speed 700 rad/s: 2.92 rad per step')
        else:
            assert reason is None


def test_guard_spares_symplectic_euler_an_axial_spin_but_not_rk4():
    """300 rad/s about each thin segment's own axis at 1/240 s: symplectic Euler follows any
    axial spin (test above), so the guard leaves it out; RK4's gyroscopic precession needs
    dt·Ω ≲ 1 (here 1.25 > guard_max_step_angle / 2.5): reset at once."""
    chain = thin_chain()
    reasons = {}
    for integrator in (SE, 'rattle', 'rk4'):
        sim = make_sim(chain, integrator)
        _set_rates(sim, 300.0 * quat_axis_x(sim.state.q))
        reasons[integrator] = sim.advance_to(sim.t, STILL).reset_reason
    assert reasons[SE] is None and reasons['rattle'] is None
    assert reasons['rk4'].startswith('gyroscopic precession at 300 rad/s')
