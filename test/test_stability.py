"""Numerical stability of the chain core at the extremes (ROS-free).

What is checked, for every extreme (step 1e-5 .. 1/15 s; 1 .. 1000 segments; neighbouring mass
ratios 1e-3 .. 1e3; thin, fast-spinning segments; head accelerations to 1e4 m/s² and spins of
50 rad/s; teleports; an hour at 120 Hz under ``-m soak``):

- after every call the state is finite and every joint gap is below ``guard_max_gap``;
- where the setting is within the solver's reach: no reset, joints closed to rounding, and on a
  still head with no damping the energy does not grow (RK4 is mildly dissipative);
- where it is not (the "known limits" below): the guard detects the blow-up, resets the chain
  to rest on the current head pose and says why (``StepReport.reset_reason``), and the setting
  that fixes it runs clean.

The guard (``Simulator._guard``) resets on a non-finite state, a failed joint solve ('solver
failure: ...'), a speed over ``guard_max_speed``, a joint turning more than
``guard_max_step_angle`` (2.5 rad) per step, for RK4 also a spinning segment's gyroscopic
precession beyond 1 rad per step, and a gap over ``guard_max_gap``.

Known limits (each has a test that the guard catches it and one that the fix works). A
physical mode of rate ω is within RK4's reach for dt·ω ≲ 1-2.8 (stability ends at 2.8 on the
imaginary axis; nonlinear whips fail earlier), symplectic Euler's for dt·ω < 2 (it is a
constrained SHAKE/RATTLE-type step: beyond its reach it mostly dissipates instead of blowing up):
  1. the reference ponytail on the moving head at dt ≥ 1/60 s -> dt ≤ 1/120 s (MuJoCo's RK4
     fails there too);
  2. stiff links: a link of mass m and length l under tension T is a pendulum of ω² ≈ 3T/(m l):
     1000 segments of 4 cm (10 kg hanging from the top link) at 1/240 s -> 1/2000 s; neighbour
     mass ratios of 1e2-1e3 -> 1/960 s (RK4); symplectic Euler stays bounded at 1/240 s but
     loses ~half the energy in 2 s (accurate at 1/3840 s);
  3. violent heads: 1e4 m/s² (T ≈ m_chain·a ≈ 1000 N) -> 1/8000 s (±1 m at 16 Hz, whose whip
     spins segments faster: 1/32000 s); a head spun up to 50 rad/s whirls segments at ~900 rad/s
     -> 1/3840 s with RK4; symplectic Euler never blows up there but needs ~1/16000 s to be
     accurate;
  4. a thin segment spinning about its own axis at Ω: RK4 integrates the gyroscopic term
     explicitly and reaches dt·Ω ≈ 1 (300 rad/s at 1/240 s fails; the guard's precession check
     resets it at once) -> dt ≤ 1/(4Ω); symplectic Euler carries the axial spin exactly at any
     Ω. Its energy still oscillates by its first-order ±dt·Ω₁/2 (Ω₁ the chain's slowest mode):
     ±1.2 % of the releasable energy at 1/240 s, just over the 1 % asked of the thin chain
     (xfail, strict) -> 1/480 s, or ``integrator='rattle'`` (its 2nd-order form, same
     rotation kick: the energy never rises above its start there, even at 1000 rad/s);
  5. a head that jumps within one 60 Hz frame (the quintic anchor track then accelerates at
     ~2000 m/s² per 0.1 m): RK4 is reset from 0.05 m; symplectic Euler follows 0.2 m and is
     reset from 0.5 m; a deliberate teleport should call ``reset``.
Core defects found earlier and fixed: symplectic Euler gained energy on a still head without
damping (+24 % in 5 s at 1/240 s; now bounded, ±1.4 %), and the guard was blind to a spurious
spin-up below ``guard_max_speed`` (energy x400, no reset; now reset at the first call).
"""
import dataclasses
import math
import os
import time
import warnings
from itertools import pairwise

import numpy as np
import pytest

from ponytail_ros.app.motions import SinusoidHead, SpinHead, reference_motion
from ponytail_ros.core import (
    ChainSpec,
    ChainState,
    KinematicState,
    Scene,
    SceneError,
    Simulator,
    SolverSpec,
    StillMotion,
)
from ponytail_ros.core.rotations import quat_axis_x, quat_from_rotvec
from ponytail_ros.core.state import half_vectors

from helpers import chain_sim, reference_ponytail, total_energy as energy
from oracle.stabilization import project_velocities

hypothesis = pytest.importorskip('hypothesis')
from hypothesis import HealthCheck, given, settings, strategies as st  # noqa: E402

HEAD = (0.0, 0.0, 1.6)
STILL = StillMotion(HEAD)
RK4, SE, RATTLE = 'rk4', 'symplectic_euler', 'rattle'


# -- helpers ------------------------------------------------------------------------------------
ponytail = reference_ponytail


def make_sim(chain, motion=STILL, integrator=RK4, dt=1 / 240, gravity=(0.0, 0.0, -9.81), **solver):
    return chain_sim(chain, motion, integrator, dt, gravity=gravity, **solver)



def tilted(angle_deg):
    a = math.radians(angle_deg)
    return (math.sin(a), 0.0, -math.cos(a))


def releasable(chain, **kw):
    """E0 - E_rest of ``chain`` on the still head (J): the scale of energy errors."""
    e0 = energy(make_sim(chain, **kw))
    rest = dataclasses.replace(chain, rest_direction=None)
    return e0 - energy(make_sim(rest, **kw))


class Run:
    """Advance ``sim`` in calls of ``1/fps`` s and check the invariants after every call."""

    def __init__(self, sim, motion, duration, fps=60.0, frames=False):
        self.reports, self.energies, self.times = [], [energy(sim)], [sim.t]
        self.reset_states = []          # (t, state, joint gaps) right after each reset
        gmax = sim.scene.solver.guard_max_gap
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', RuntimeWarning)     # a blow-up is the guard's job
            for k in range(1, int(round(duration * fps)) + 1):
                t = k / fps
                r = (sim.advance_frame(t, motion.state_at(t)) if frames
                     else sim.advance_to(t, motion))
                assert sim.state.is_finite(), f'non-finite state after the call at t={t}'
                assert r.max_gap <= gmax, f'gap {r.max_gap} > guard_max_gap at t={t}'
                assert np.all(np.isfinite(sim.joint_gaps()))
                self.reports.append(r)
                if r.reset_reason:
                    self.reset_states.append((sim.t, sim.state.copy(), sim.joint_gaps()))
                self.energies.append(energy(sim))
                self.times.append(sim.t)
        self.energies = np.array(self.energies)
        self.resets = [(self.times[i + 1], r.reset_reason) for i, r in enumerate(self.reports)
                       if r.reset_reason]
        self.max_gap = max(r.max_gap for r in self.reports)
        self.sim = sim

    def growth(self, scale):
        """Largest rise of the energy above its initial value, relative to ``scale``."""
        return float(np.max(self.energies - self.energies[0]) / scale)


def assert_reset_to_rest(run, motion):
    """Right after each reset the chain is at rest on the head: finite, joints closed, in the
    scene's rest pose and moving rigidly with the head (what a fresh simulator starts in)."""
    assert run.reset_states
    for t, state, gaps in run.reset_states:
        assert state.is_finite()
        assert np.max(gaps) < 1e-9
        fresh = Simulator(run.sim.scene, motion.state_at(t), t)
        assert np.allclose(state.x, fresh.state.x, atol=1e-9)
        assert np.allclose(state.v, fresh.state.v, atol=1e-9)
        assert np.allclose(state.w, fresh.state.w, atol=1e-9)


# -- step size ----------------------------------------------------------------------------------
@pytest.mark.parametrize('integrator', [RK4, SE])
@pytest.mark.parametrize('dt, duration', [(1e-5, 0.02), (1e-4, 0.2), (1e-3, 1.0), (1 / 240, 3.0),
                                          (1 / 120, 3.0)])
def test_step_sizes_within_reach_run_clean_on_the_moving_head(integrator, dt, duration):
    sim = make_sim(ponytail(), reference_motion(), integrator, dt)
    run = Run(sim, reference_motion(), duration)
    assert not run.resets
    assert run.max_gap < 1e-12


@pytest.mark.parametrize('integrator', [RK4, SE])
@pytest.mark.parametrize('dt', [1 / 60, 1 / 30, 1 / 15])
def test_steps_too_large_for_the_moving_head_are_caught_by_the_guard(integrator, dt):
    """Known limit 1 (MuJoCo's RK4 goes unstable at 1/60 s on this scene too)."""
    motion = reference_motion()
    sim = make_sim(ponytail(), motion, integrator, dt)
    run = Run(sim, motion, 3.0)
    assert run.resets, 'expected the guard to catch the blow-up'
    reasons = ('non-finite', 'solver failure', 'speed', 'gap', 'precession')
    assert all(any(r in why for r in reasons) for _, why in run.resets)
    assert sim.total_resets == len(run.resets)


@pytest.mark.parametrize('dt', [1e-5, 1e-3, 1 / 240, 1 / 120])
def test_rk4_energy_does_not_grow_on_a_still_head(dt):
    """No damping: RK4 + projection loses a little energy; gains stay at rounding/truncation.

    Bound: the truncation error of RK4 per unit time is O(dt⁴); measured growth at 1/240 s is
    ~2e-6 of the releasable energy over 5 s, so 1e-4 is a 50x margin and far below any
    visible gain (and 1e-9 at tiny steps where the error is rounding only).
    """
    chain = ponytail(rest_direction=tilted(45))
    duration = {1e-5: 0.03, 1e-3: 2.0}.get(dt, 5.0)
    run = Run(make_sim(chain, dt=dt), STILL, duration)
    assert not run.resets
    bound = 1e-9 if dt <= 1e-4 else 1e-4
    assert run.growth(releasable(chain)) < bound


def test_symplectic_euler_energy_does_not_grow():
    """Regression: the unconstrained symplectic Euler (v += h a, ω += h α, then a rigid velocity
    rebuild) gained +24 % in 5 s at 1/240 s here. The constrained step's energy error is a
    bounded first-order oscillation: measured ±1.4 % (max +1.2 %), no drift."""
    chain = ponytail(rest_direction=tilted(45))
    run = Run(make_sim(chain, integrator=SE), STILL, 5.0)
    assert not run.resets
    assert run.growth(releasable(chain)) < 0.05


# -- joint damping ------------------------------------------------------------------------------
_FIELDS = SolverSpec.__dataclass_fields__
EXPLICIT_DAMPING = (dict(damping_method='explicit') if 'damping_method' in _FIELDS else
                    dict(implicit_damping=False) if 'implicit_damping' in _FIELDS else None)


def test_damped_reference_ponytail_runs_clean_at_the_default_step():
    """The shared reference's damped ponytail (c = 1e-4 N·m·s/rad) on the moving head.

    Joint damping about a thin segment's own axis is stiff (rate ~ 4c/I_axial = 800/s here):
    explicit damping needs dt < 2.8 I_axial/(4c) = 1/287 s with RK4 (1/400 s with symplectic
    Euler) and blew up at 1/240 s in 0.11 s; the core now switches to implicit damping there
    (``damping_method='auto'``).
    """
    motion = reference_motion()
    for integrator in (RK4, SE):
        run = Run(make_sim(ponytail(damping=1e-4), motion, integrator), motion, 2.0)
        assert not run.resets, integrator
        assert run.max_gap < 1e-12


@pytest.mark.skipif(EXPLICIT_DAMPING is None, reason='SolverSpec cannot force explicit damping')
def test_explicit_damping_beyond_its_limit_is_caught():
    motion = reference_motion()
    run = Run(make_sim(ponytail(damping=1e-4), motion, RK4, **EXPLICIT_DAMPING), motion, 1.0)
    assert run.resets
    assert_reset_to_rest(run, motion)
    fixed = Run(make_sim(ponytail(damping=1e-4), motion, RK4, 1 / 300, **EXPLICIT_DAMPING),
                motion, 1.0)
    assert not fixed.resets



def test_auto_damping_keeps_rk4_explicit_inside_its_own_stability_region():
    """``damping_method='auto'`` switches at the integrator's own limit: RK4's stability region
    reaches dt·λ = 2.785 on the negative real axis, the Euler kick's 2. The reference
    ponytail with c = 1e-4 has dt·λ_max = 2.67 at 1/300 s: RK4 keeps explicit damping (as
    accurate as the step) and runs clean on the moving head, symplectic Euler goes implicit;
    at 1/240 s (3.33) RK4 goes implicit too."""
    motion = reference_motion()
    sim = make_sim(ponytail(damping=1e-4), motion, RK4, 1 / 300)
    assert 2.0 < sim.dt * sim.model.damping_rate < 2.78
    assert not sim.model.implicit_damping
    run = Run(sim, motion, 1.0)
    assert not run.resets
    assert run.max_gap < 1e-12
    assert make_sim(ponytail(damping=1e-4), motion, SE, 1 / 300).model.implicit_damping
    assert make_sim(ponytail(damping=1e-4), motion, RK4, 1 / 240).model.implicit_damping

# -- segment count ------------------------------------------------------------------------------
@pytest.mark.parametrize('n, dt, duration', [(1, 1 / 240, 2.0), (2, 1 / 240, 2.0),
                                             (100, 1 / 240, 1.0), (1000, 1 / 2000, 0.05)])
def test_segment_counts_1_to_1000_conserve_energy_and_joints(n, dt, duration):
    """Chains of n segments of the reference ponytail's size (4 cm, 10 g), released at 45°."""
    chain = ponytail(n, length=0.04 * n, mass=0.01 * n, rest_direction=tilted(45))
    run = Run(make_sim(chain, dt=dt), STILL, duration, fps=min(60.0, 1.0 / (5 * dt)))
    assert not run.resets
    assert run.max_gap < 1e-12
    assert run.growth(releasable(chain, dt=dt)) < 1e-4


def test_thousand_segments_at_the_default_step_are_caught_and_a_smaller_step_fixes_it():
    """Known limit 2: 40 m of chain, 10 kg hanging from the top link: dt·ω ≈ 3.6 at 1/240 s."""
    chain = ponytail(1000, length=40.0, mass=10.0, rest_direction=tilted(45))
    sim = make_sim(chain, dt=1 / 240)
    run = Run(sim, STILL, 0.1)
    assert run.resets
    assert_reset_to_rest(run, STILL)
    # the fix (1/2000 s) is the clean run of test_segment_counts_1_to_1000_...


# -- mass ratios --------------------------------------------------------------------------------
def alternating(n, ratio, base=0.01):
    return tuple(base * (ratio if i % 2 else 1.0) for i in range(n))


@pytest.mark.parametrize('ratio', [1e-3, 1e-2, 1e2, 1e3])
def test_neighbouring_mass_ratios_rk4(ratio):
    """Segments alternate m and ratio·m (inertia scales with mass), released horizontal, at
    1/960 s: clean, joints closed, energy conserved to 1e-4 of the releasable energy (measured
    ≤ 2e-5; it converges as dt⁴: 1.5e-3, 5e-6, 2e-8 at 1/240, 1/960, 1/3840 for ratio 1e-2)."""
    chain = ponytail(10, segment_masses=alternating(10, ratio), rest_direction=(-1.0, 0.0, 0.0))
    run = Run(make_sim(chain, dt=1 / 960), STILL, 2.0)
    assert not run.resets
    assert run.max_gap < 1e-12
    assert run.growth(releasable(chain)) < 1e-4


@pytest.mark.parametrize('ratio', [1e-3, 1e-2, 1e2, 1e3])
def test_neighbouring_mass_ratios_at_the_default_step_stay_finite(ratio):
    """Known limit 2 at 1/240 s: RK4 is inaccurate here (it dissipates 30-80 % of the energy in
    3 s) and with ratio 1e2 blows up at ~0.9 s; the guard resets (never a NaN, gaps bounded)."""
    chain = ponytail(10, segment_masses=alternating(10, ratio), rest_direction=(-1.0, 0.0, 0.0))
    run = Run(make_sim(chain, dt=1 / 240), STILL, 1.5)
    if run.resets:
        assert_reset_to_rest(run, STILL)


@pytest.mark.parametrize('ratio', [1e-3, 1e3])
def test_mass_ratios_symplectic_euler_stays_bounded_and_a_smaller_step_is_accurate(ratio):
    """Known limit 2 for symplectic Euler: a light link under a heavy one's tension is stiff.
    At 1/240 s it used to blow up; the constrained step keeps it bounded (joints closed, energy
    never up by more than 0.8 % of the releasable energy, measured) but inaccurate: it loses
    45-50 % of that energy in 2 s. 1/3840 s keeps it within 0.4 %."""
    chain = ponytail(10, segment_masses=alternating(10, ratio), rest_direction=(-1.0, 0.0, 0.0))
    scale = releasable(chain)
    run = Run(make_sim(chain, integrator=SE, dt=1 / 240), STILL, 2.0)
    assert not run.resets
    assert run.max_gap < 1e-12
    assert run.growth(scale) < 0.02
    fixed = Run(make_sim(chain, integrator=SE, dt=1 / 3840), STILL, 1.0)
    assert not fixed.resets
    assert np.max(np.abs(fixed.energies - fixed.energies[0])) < 0.01 * scale


# -- thin spinning segments ---------------------------------------------------------------------
def thin_chain(n, **kw):
    m, l = 0.1 / n, 0.4 / n
    ip = m * l * l / 12.0
    return ponytail(n, length=0.4, mass=0.1, inertia=tuple((1e-4 * ip, ip, ip) for _ in range(n)),
                    rest_direction=(0.3, 0.0, -1.0), **kw)


def spun(n, spin, integrator, dt, wobble=(0.5, 0.0, 0.3)):
    """Thin segments (I_axial = 1e-4 I_perp) hanging tilted, each spinning about its own axis
    at ``spin`` rad/s plus a small wobble, velocities consistent with the joints."""
    sim = make_sim(thin_chain(n), integrator=integrator, dt=dt)
    st_ = sim.state.copy()
    st_.w = spin * quat_axis_x(st_.q) + np.asarray(wobble)
    anchor = sim.anchors(STILL.state_at(0.0))
    st_.v = project_velocities(sim.model, anchor.velocity, st_.w,
                               half_vectors(sim.model.length, st_.q))
    sim.reset(STILL.state_at(0.0), 0.0, state=st_)
    return sim


def spin_scale(n):
    """Releasable energy of the tilted thin chain (J): the yardstick for its energy errors."""
    return releasable(thin_chain(n))


def axial_spin(sim):
    return np.sum(quat_axis_x(sim.state.q) * sim.state.w, axis=1)


@pytest.mark.parametrize('spin, dt, duration', [(10.0, 1 / 240, 2.0), (100.0, 1 / 960, 2.0),
                                                (600.0, 1 / 3840, 0.5)])
def test_rk4_thin_spinning_segments_conserve_energy_and_axial_spin(spin, dt, duration):
    """dt·Ω ≤ 0.16: energy conserved to 2e-4 of the releasable energy (measured ≤ 5e-5; it falls
    as dt⁴), and the axial spin, a constant of motion here (ball-joint forces act on the axis,
    no damping), kept to rounding by RK4 in body-frame ω."""
    sim = spun(5, spin, RK4, dt)
    s0, e0 = axial_spin(sim), energy(sim)
    run = Run(sim, STILL, duration)
    assert not run.resets
    assert run.max_gap < 1e-12
    assert run.energies.max() - e0 < 2e-4 * spin_scale(5)
    assert np.max(np.abs(axial_spin(sim) - s0)) < 1e-9 * spin


def test_rk4_axial_spin_is_conserved_on_the_moving_head():
    """Regression: world-frame ω in RK4 let the axial spin drift (3 -> 26 rad/s in 10 s at 1/240)
    until the undamped moving-head scene blew up after ~136 s."""
    motion = reference_motion()
    sim = make_sim(ponytail(), motion)
    s0 = axial_spin(sim)
    Run(sim, motion, 10.0, fps=30.0)
    assert np.max(np.abs(axial_spin(sim) - s0)) < 1e-6


def test_rk4_spin_beyond_its_reach_is_caught_and_a_smaller_step_fixes_it():
    """Known limit 4: RK4's reach is dt·Ω ≲ 1 here (250 rad/s at 1/240 s already gains energy,
    300 rad/s blows up); Ω = 1000 rad/s at 1/240 s is caught, at 1/4000 s it is clean."""
    sim = spun(5, 1000.0, RK4, 1 / 240)
    run = Run(sim, STILL, 1.0)
    assert run.resets
    assert_reset_to_rest(run, STILL)
    sim = spun(5, 1000.0, RK4, 1 / 4000)
    e0 = energy(sim)
    run = Run(sim, STILL, 0.25)
    assert not run.resets
    assert run.energies.max() - e0 < 1e-3 * spin_scale(5)


def test_guard_catches_a_spurious_spin_up_of_a_thin_segment():
    """Regression: one thin segment (I_axial = 1e-4 I_perp, 8 cm, 20 g) spinning at 300 rad/s
    about its axis at 1/240 s (dt·Ω = 1.25, beyond RK4's reach) goes unstable in its
    perpendicular rate, which saturates at ~400 rad/s (energy x1e4 of the releasable energy in
    3 s, tip 16 m/s), below guard_max_speed: the guard used to miss it. Its gyroscopic
    precession check (1.25 rad per step > 1) now resets it at the first call."""
    m, l = 0.02, 0.08
    ip = m * l * l / 12.0
    chain = ChainSpec(n_segments=1, length=l, mass=m, radius=0.01, attach=(0.0, 0.0, 0.0),
                      damping=0.0, inertia=((1e-4 * ip, ip, ip),), rest_direction=(0.3, 0.0, -1.0))
    sim = make_sim(chain)
    st_ = sim.state.copy()
    st_.w = 300.0 * quat_axis_x(st_.q) + np.array([0.5, 0.0, 0.3])
    anchor = sim.anchors(STILL.state_at(0.0))
    st_.v = project_velocities(sim.model, anchor.velocity, st_.w,
                               half_vectors(sim.model.length, st_.q))
    sim.reset(STILL.state_at(0.0), 0.0, state=st_)
    e0 = energy(sim)
    scale = releasable(chain)
    run = Run(sim, STILL, 3.0)
    # Either the energy stays put, or the guard said something was wrong.
    assert run.resets or run.energies.max() - e0 < 0.1 * scale


@pytest.mark.parametrize('spin', [100.0, 1000.0])
def test_symplectic_euler_follows_fast_axial_spins(spin):
    """Known limit 4 no longer holds for symplectic Euler: a spin about a segment's own axis is
    carried exactly (the gyroscopic term's stiff part is the transport of the axial spin along
    the moving axis, the rest is implicit). It used to blow up within 1 s at 100 rad/s; now at
    dt·Ω = 0.42 and 4.2: no reset, joints closed, axial spin conserved to rounding."""
    sim = spun(5, spin, SE, 1 / 240)
    s0 = axial_spin(sim)
    run = Run(sim, STILL, 2.0)
    assert not run.resets
    assert run.max_gap < 1e-12
    assert np.max(np.abs(axial_spin(sim) - s0)) < 1e-9 * spin


@pytest.mark.xfail(strict=True, reason=(
    'first-order limit, no longer a spin defect: the gyroscopic term is handled (axial spin '
    'conserved to 1e-14; the energy curve at 100 rad/s equals the one without spin to 3e-6 of '
    'the releasable energy, see test_core_integrators), but symplectic Euler\'s energy oscillates '
    'by its first-order ±dt·Ω₁/2 for the chain\'s slowest mode, the same with or without spin: '
    '+1.16 % at 1/240 s (0.58 % at 1/480 s), above this 1 % bound. Fixed by half the step or by '
    'the 2nd-order step with the same two solves, integrator=\'rattle\' (next test) '
    'or numerical damping (a prototype with Catto\'s implicit Euler on the whole gyroscopic '
    'term passes by losing 68 % of the energy in 2 s).'))
def test_symplectic_euler_thin_spinning_segments_do_not_gain_energy():
    sim = spun(5, 100.0, SE, 1 / 240)
    e0 = energy(sim)
    run = Run(sim, STILL, 2.0)
    assert not run.resets
    assert run.energies.max() - e0 < 1e-2 * spin_scale(5)


@pytest.mark.parametrize('integrator, dt, spin', [
    (SE, 1 / 480, 100.0), (RATTLE, 1 / 240, 100.0), (RATTLE, 1 / 240, 1000.0)])
def test_thin_spinning_segments_do_not_gain_energy(integrator, dt, spin):
    """The settings that fix the expected failure above, same bound: symplectic Euler at half
    the step (measured +0.58 %), or RATTLE, its 2nd-order form, at the default step (measured:
    the energy never rises above its start, at 100 and at 1000 rad/s, dt·Ω = 4.2)."""
    sim = spun(5, spin, integrator, dt)
    e0 = energy(sim)
    run = Run(sim, STILL, 2.0)
    assert not run.resets
    assert run.energies.max() - e0 < 1e-2 * spin_scale(5)


# -- violent heads ------------------------------------------------------------------------------
def shaker(accel, amplitude):
    f = math.sqrt(accel / amplitude) / (2.0 * math.pi)
    return SinusoidHead(p0=HEAD, amplitude=(amplitude, 0.0, 0.0), frequency=(f, 0.0, 0.0),
                        yaw_amplitude=0.0, yaw_frequency=0.0)


@pytest.mark.parametrize('accel, amplitude, dt, duration', [
    (1e3, 0.01, 1 / 960, 0.5), (1e4, 0.01, 1 / 8000, 0.15), (1e4, 1.0, 1 / 32000, 0.1)])
def test_head_accelerations_up_to_1e4(accel, amplitude, dt, duration):
    """A head shaken along X at 1e3-1e4 m/s² (±1 cm at 50-159 Hz; ±1 m at 16 Hz, i.e. 100 m/s:
    guard_max_speed raised to 1000 m/s). Fixes of known limit 3: 1/8000 s, and 1/32000 s for
    the ±1 m shake whose whip spins segments far faster."""
    motion = shaker(accel, amplitude)
    run = Run(make_sim(ponytail(), motion, dt=dt, guard_max_speed=1e3), motion, duration, fps=120)
    assert not run.resets
    assert run.max_gap < 1e-12


def test_head_acceleration_1e4_at_the_default_step_is_caught():
    """Known limit 3: tension ~ m a = 1000 N makes the top link stiff (ω ≈ 2700 rad/s)."""
    motion = shaker(1e4, 0.01)
    sim = make_sim(ponytail(), motion)
    run = Run(sim, motion, 0.5)
    assert run.resets
    assert_reset_to_rest(run, motion)


def test_head_spinning_at_50_rad_s():
    """Spun up in 0.2 s to 50 rad/s: the ponytail flies out (tip ~40 m/s) and its segments
    whirl at up to ~900 rad/s, so RK4 needs 1/3840 s (dt·ω ≈ 0.25)."""
    motion = SpinHead(50.0, HEAD, ramp=0.2)
    run = Run(make_sim(ponytail(), motion, RK4, 1 / 3840), motion, 1.0)
    assert not run.resets
    assert run.max_gap < 1e-12


@pytest.mark.parametrize('integrator, dt', [(RK4, 1 / 240), (RK4, 1 / 960)])
def test_head_spinning_at_50_rad_s_too_coarse_is_caught(integrator, dt):
    """Known limit 3."""
    motion = SpinHead(50.0, HEAD, ramp=0.2)
    run = Run(make_sim(ponytail(), motion, integrator, dt), motion, 1.0)
    assert run.resets
    assert_reset_to_rest(run, motion)


@pytest.mark.parametrize('dt', [1 / 240, 1 / 960])
def test_head_spinning_at_50_rad_s_symplectic_euler_stays_bounded(dt):
    """Known limit 3 for symplectic Euler (it used to blow up even at 1/3840 s): no reset and
    joints closed from 1/240 s on, but first order is inaccurate in this whirl until ~1/16000 s.
    Mean tip distance from the spin axis over 0.5-2 s, measured: 0.15 m at 1/240 s (the whirl
    dissipated), 0.49 m at 1/960 s, 0.43 m at 1/3840 s, 0.27 m at 1/16000 s (RK4 at 1/8000 s:
    0.28 m)."""
    motion = SpinHead(50.0, HEAD, ramp=0.2)
    run = Run(make_sim(ponytail(), motion, SE, dt), motion, 1.0)
    assert not run.resets
    assert run.max_gap < 1e-12


# -- teleports ----------------------------------------------------------------------------------
@pytest.mark.parametrize('integrator, jump', [(RK4, 0.1), (RK4, 1.0), (RK4, 10.0), (RK4, 1000.0),
                                               (SE, 1.0), (SE, 10.0), (SE, 1000.0)])
def test_teleport_of_the_head_resets_and_reports(integrator, jump):
    """Known limit 5: a head given at frames that jumps far within one frame (symplectic Euler
    follows 0.1-0.2 m, see below, and is reset from 0.5 m)."""
    sim = make_sim(ponytail(), STILL, integrator)
    here = KinematicState.still(HEAD)
    there = KinematicState.still((HEAD[0] + jump, HEAD[1], HEAD[2]))
    for k in range(1, 31):
        assert sim.advance_frame(k / 60, here).reset_reason is None
    r = sim.advance_frame(31 / 60, there)
    reasons = [r.reset_reason]
    reasons += [sim.advance_frame(k / 60, there).reset_reason for k in range(32, 35)]
    assert any(reasons[:2]), 'the teleport must be caught'
    assert all(x is None for x in reasons[2:]), 'and the chain must run clean afterwards'
    root = there.position[0] + np.array([-0.1, 0.0, 0.05])
    assert np.allclose(sim.joint_positions()[0][0], root)
    assert np.max(sim.joint_gaps()) < 1e-9


@pytest.mark.parametrize('integrator, jump', [(RK4, 0.01), (SE, 0.01), (SE, 0.1)])
def test_small_head_jump_is_followed_without_reset(integrator, jump):
    """Symplectic Euler's position-level joint correction follows a 0.1 m jump within one 60 Hz
    frame (tip up to 5.7 m/s, measured), where RK4 blows up."""
    sim = make_sim(ponytail(), STILL, integrator)
    here = KinematicState.still(HEAD)
    there = KinematicState.still((HEAD[0] + jump, HEAD[1], HEAD[2]))
    for k in range(1, 31):
        sim.advance_frame(k / 60, here)
    assert all(sim.advance_frame(k / 60, there).reset_reason is None for k in range(31, 91))
    assert np.max(sim.joint_gaps()) < 1e-12


def test_head_turned_half_round_in_one_frame_is_caught():
    sim = make_sim(ponytail(), STILL)
    here = KinematicState.still(HEAD)
    turned = KinematicState.still(HEAD, quat_from_rotvec(np.array([0.0, 0.0, 0.99 * math.pi])))
    for k in range(1, 31):
        sim.advance_frame(k / 60, here)
    reasons = [sim.advance_frame(k / 60, turned).reset_reason for k in range(31, 40)]
    assert any(reasons) and reasons[-1] is None
    assert np.max(sim.joint_gaps()) < 1e-9


def test_jump_in_time_is_capped_and_reported():
    """A frame hitch of 1000 s: at most max_steps_per_call steps, the rest dropped and reported."""
    motion = reference_motion()
    sc = Scene(chains=(ponytail(),), solver=SolverSpec(dt=1 / 240, max_steps_per_call=240))
    sim = Simulator(sc, motion)
    r = sim.advance_to(1000.0, motion)
    assert r.steps == 240 and r.dropped_time == pytest.approx(1000.0 - 1.0, abs=1 / 240)
    assert r.reset_reason is None and sim.state.is_finite()


@pytest.mark.parametrize('integrator', [RK4, SE, RATTLE])
def test_a_hitch_carries_the_chain_with_the_head(integrator):
    """A 0.3 s hitch on a head moving at 1 m/s and yawing at 3 rad/s, with at most 12 steps per
    call: the 0.25 s beyond the cap are dropped and the chain skips ahead carried by the head,
    its shape and motion relative to the head kept, so the next steps go on without a jolt: no
    reset, joints closed, and the chain no faster relative to the head than before the hitch.
    (Not carried, the first step after the skip had to close the head's 0.25 s of motion at
    once: symplectic Euler and RATTLE then fail the speed bound; RK4's velocity rebuild from ω
    happened to absorb it here.)"""
    motion = SinusoidHead(p0=HEAD, amplitude=(0.2, 0.0, 0.0), frequency=(0.8, 0.0, 0.0),
                          yaw_amplitude=0.6, yaw_frequency=0.8)
    sim = make_sim(ponytail(damping=1e-3), motion, integrator, 1 / 240, max_steps_per_call=12)
    for k in range(1, 61):
        assert sim.advance_to(k / 120, motion).reset_reason is None

    def relative_speeds():
        head = motion.state_at(sim.t)
        a = sim.anchors(head)
        st = sim.state
        return np.linalg.norm(st.v - a.velocity[0] - np.cross(a.angular_velocity[0],
                                                             st.x - a.position[0]), axis=1)
    before = relative_speeds()
    r = sim.advance_to(0.5 + 0.3, motion)
    assert r.dropped_time == pytest.approx(0.25, abs=1e-9) and r.steps == 12
    assert r.reset_reason is None and r.max_gap < 1e-12
    assert np.max(relative_speeds()) < 2.0 * np.max(before) + 0.1
    for k in range(97, 121):
        r = sim.advance_to(k / 120, motion)
        assert r.reset_reason is None and r.max_gap < 1e-12


def test_carry_with_anchors_keeps_the_chain_relative_to_its_anchor():
    """The carry itself: the chain's positions, orientations and velocities seen from the anchor
    body are the same before and after, so closed joints stay closed (position and velocity)."""
    from ponytail_ros.core.rotations import quat_conjugate, quat_multiply, quat_rotate
    from ponytail_ros.core.simulator import carry_with_anchors
    motion = reference_motion()
    sim = make_sim(ponytail(), motion, RK4, 1 / 240)
    sim.advance_to(0.7, motion)
    st = sim.state
    a0, a1 = sim.anchors(motion.state_at(0.7)), sim.anchors(motion.state_at(2.3))
    x, q, v, w = carry_with_anchors(sim.model, a0, a1, st.x, st.q, st.v, st.w)

    def seen_from(a, x, q, v, w):
        qc = quat_conjugate(a.orientation[0])
        r = x - a.position[0]
        return (quat_rotate(qc, r), quat_multiply(qc, q),
                quat_rotate(qc, v - a.velocity[0] - np.cross(a.angular_velocity[0], r)),
                quat_rotate(qc, w - a.angular_velocity[0]))
    for before, after in zip(seen_from(a0, st.x, st.q, st.v, st.w), seen_from(a1, x, q, v, w),
                             strict=True):
        assert np.allclose(before, after, rtol=0, atol=1e-12)
    sim.reset(motion.state_at(2.3), 2.3, state=ChainState(x, q, v, w))
    assert np.max(sim.joint_gaps()) < 1e-12


def test_non_finite_head_never_reaches_the_chain():
    sim = make_sim(ponytail(), STILL)
    bad = KinematicState.still((np.nan, 0.0, 1.6))
    try:
        r = sim.advance_frame(1 / 60, bad)
    except (SceneError, ValueError):
        pass
    else:
        assert r.reset_reason is not None
    assert sim.state.is_finite()


# -- property-based -----------------------------------------------------------------------------
@st.composite
def chains(draw, max_segments=8, damped=False):
    n = draw(st.integers(1, max_segments))
    length = draw(st.floats(0.05, 2.0))
    radius = draw(st.floats(0.002, 0.03))
    base = draw(st.floats(0.005, 0.2))
    ratios = draw(st.lists(st.floats(0.1, 10.0), min_size=n, max_size=n))
    masses = tuple(base * r / n for r in ratios)
    theta = draw(st.floats(0.0, math.pi))
    phi = draw(st.floats(-math.pi, math.pi))
    rest = (math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), -math.cos(theta))
    damping = draw(st.floats(1e-6, 1e-3)) if damped else draw(st.sampled_from([0.0, 1e-5, 1e-4]))
    return ChainSpec(n_segments=n, length=length, mass=sum(masses), radius=radius,
                     segment_masses=masses, attach=(-0.1, 0.0, 0.05),
                     rest_direction=rest if draw(st.booleans()) else None, damping=damping,
                     drag_linear=draw(st.sampled_from([0.0, 0.01])))


@st.composite
def head_motions(draw):
    return SinusoidHead(
        p0=HEAD,
        amplitude=tuple(draw(st.floats(0.0, 0.1)) for _ in range(3)),
        frequency=tuple(draw(st.floats(0.0, 3.0)) for _ in range(3)),
        phase=tuple(draw(st.floats(0.0, 6.3)) for _ in range(3)),
        yaw_amplitude=draw(st.floats(0.0, 1.0)), yaw_frequency=draw(st.floats(0.0, 2.0)))


PROPERTY = settings(max_examples=25, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@PROPERTY
@given(chain=chains(), motion=head_motions(), integrator=st.sampled_from([RK4, SE, RATTLE]),
       dt=st.sampled_from([1e-3, 1 / 480, 1 / 240, 1 / 120, 1 / 60, 1 / 30, 1 / 15]),
       frames=st.booleans())
def test_property_never_nan_and_joints_bounded(chain, motion, integrator, dt, frames):
    """Any valid scene, any step (including ones far too large): never NaN, gaps bounded; the
    guard is the only way a blow-up shows, and without one the joints are closed to rounding."""
    sim = make_sim(chain, motion, integrator, dt)
    run = Run(sim, motion, 0.5, fps=30.0, frames=frames)
    if not run.resets:
        assert run.max_gap < 1e-9


@PROPERTY
@given(chain=chains(damped=True), dt=st.sampled_from([1 / 960, 1 / 480, 1 / 240]))
def test_property_still_head_with_damping_energy_never_increases(chain, dt):
    """RK4, still head, joint damping > 0 (+ optional drag): E(t) never rises above any earlier
    value by more than 1e-6 of the releasable energy (E0 - E_rest) + 1e-12 J.

    Why that tolerance: with nothing putting energy in, every term is dissipative; what is left is
    RK4's truncation error (O(dt⁵) per step, measured ≤ 2e-6 of E0 - E_rest over 5 s undamped at
    1/240 s, and damping only lowers it) and rounding of E itself (~1e-16 of m g z ≈ 1e-15 J).
    Steps where the guard resets are excluded (the reset lowers E)."""
    sim = make_sim(chain, STILL, RK4, dt)
    scale = max(releasable(chain, dt=dt), 1e-9)
    run = Run(sim, STILL, 1.0, fps=60.0)
    e = run.energies
    rises = e[1:] - np.maximum.accumulate(e)[:-1]
    assert not run.resets
    assert np.max(rises) <= 1e-6 * scale + 1e-12


# -- the hour ------------------------------------------------------------------------------------
SOAK_SECONDS = float(os.environ.get('PONYTAIL_SOAK_SECONDS', 3600.0))


@pytest.mark.soak
def test_one_hour_at_120_hz_on_the_moving_head():
    """Default solver, the reference ponytail with light damping (c = 2e-5), the head given at
    120 Hz frames (as the node does) for 3600 simulated seconds: never a NaN, joints closed,
    energy bounded, no time drift, nothing dropped, and blow-ups rare, each caught and reported,
    and recovered from.

    A whip can outrun the step (a link mode with dt·ω beyond RK4's limit): the guard catches
    it ('speed ... > guard_max_speed' or 'non-finite state') and the chain recovers. Minutes of
    CPU; ``PONYTAIL_SOAK_SECONDS`` shortens it."""
    motion = reference_motion()
    sim = make_sim(ponytail(damping=2e-5), motion, max_steps_per_call=240)
    t0 = time.perf_counter()
    n = int(round(SOAK_SECONDS * 120))
    gap_max, kes, resets = 0.0, [], []
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)
        for k in range(1, n + 1):
            t = k / 120.0
            r = sim.advance_frame(t, motion.state_at(t))
            assert sim.state.is_finite(), f'NaN at t={t}'
            assert r.dropped_time == 0.0
            if r.reset_reason:
                resets.append((t, r.reset_reason))
            else:
                gap_max = max(gap_max, r.max_gap)
            if k % 120 == 0:
                kes.append(float(sim.energy()[0][0]))
    wall = time.perf_counter() - t0
    print(f'\n{SOAK_SECONDS:g} s at 120 Hz: wall {wall:.0f} s, resets {resets}, '
          f'KE median {np.median(kes):.3g} J, 99.9th pct {np.percentile(kes, 99.9):.3g} J, '
          f'max gap {gap_max:.2g} m')
    assert abs(sim.t - n / 120.0) <= sim.dt
    assert gap_max < 1e-12
    assert len(resets) <= max(3, int(3 * SOAK_SECONDS / 3600))
    assert all(b[0] - a[0] > 10.0 for a, b in pairwise(resets)), 'no reset storms'
    assert np.percentile(kes, 99.9) < 2.0   # typical 0.1 J, whips to ~0.5 J; a runaway is more
