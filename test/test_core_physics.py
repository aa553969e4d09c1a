"""Physical facts of the chain dynamics core (no ROS): closed forms, conservation, coupling."""
import numpy as np
import pytest

from ponytail_ros.core import (
    ChainSpec,
    KinematicState,
    Scene,
    SceneError,
    Simulator,
    SolverSpec,
    StillMotion,
    SwayYawMotion,
)
from ponytail_ros.core.rotations import quat_from_rotvec, quat_rotate
from ponytail_ros.core.state import half_vectors

from helpers import total_energy
from oracle.forces import applied_forces
from oracle.solver import Dynamics

G = 9.81
ANCHOR = np.array([0.0, 0.0, 2.0])


def chain_scene(n=5, length=0.5, mass=0.2, radius=0.01, damping=0.0, integrator='rk4',
                dt=1e-3, **solver):
    chain = ChainSpec(n_segments=n, length=length, mass=mass, radius=radius, attach=(0, 0, 0),
                      damping=damping)
    return Scene(chains=(chain,), solver=SolverSpec(integrator=integrator, dt=dt,
                                                    max_steps_per_call=100_000, **solver))


def released(scene, angle, axis=(0.0, 1.0, 0.0)):
    """A chain hanging from a still anchor, then rotated rigidly by ``angle`` about ``axis``."""
    sim = Simulator(scene, KinematicState.still(ANCHOR))
    q_tilt = quat_from_rotvec(np.asarray(axis) * angle)
    st = sim.state
    st.q[:] = quat_multiply_left(q_tilt, st.q)
    st.x[:] = ANCHOR + quat_rotate(np.broadcast_to(q_tilt, st.q.shape), st.x - ANCHOR)
    sim.reset(KinematicState.still(ANCHOR), state=st)
    return sim


def quat_multiply_left(a, q):
    from ponytail_ros.core.rotations import quat_multiply
    return quat_multiply(np.broadcast_to(a, q.shape), q)



def test_single_segment_small_angle_period_is_compound_pendulum():
    length, mass, radius = 0.3, 0.05, 0.01
    scene = chain_scene(n=1, length=length, mass=mass, radius=radius)
    sim = released(scene, np.radians(1.0))
    motion = StillMotion(ANCHOR)
    # Solid cylinder about its end: I = I_perp + m (l/2)²; T = 2π sqrt(I / (m g l/2)).
    i_end = mass * (3 * radius ** 2 + length ** 2) / 12 + mass * (length / 2) ** 2
    period = 2 * np.pi * np.sqrt(i_end / (mass * G * length / 2))
    # Time the upward zero crossings of the tip's x over 5 periods (linear interpolation).
    ts, xs = [], []
    dt_sample = 1e-3
    for k in range(1, int(5.2 * period / dt_sample)):
        sim.advance_to(k * dt_sample, motion)
        ts.append(k * dt_sample)
        xs.append(sim.joint_positions()[1][0, 0])
    ts, xs = np.array(ts), np.array(xs)
    up = np.nonzero((xs[:-1] < 0) & (xs[1:] >= 0))[0]
    crossings = ts[up] - xs[up] * (ts[up + 1] - ts[up]) / (xs[up + 1] - xs[up])
    measured = np.mean(np.diff(crossings))
    assert len(crossings) >= 4
    assert abs(measured / period - 1) < 1e-3


@pytest.mark.parametrize('integrator, dt, bound', [('rk4', 1e-3, 1e-4)])
def test_energy_conserved_without_damping(integrator, dt, bound):
    """5 segments released 45° from vertical, still anchor, 10 s."""
    scene = chain_scene(n=5, integrator=integrator, dt=dt)
    rest = total_energy(Simulator(scene, KinematicState.still(ANCHOR)))
    sim = released(scene, np.radians(45.0))
    e0 = total_energy(sim)
    motion = StillMotion(ANCHOR)
    drift = 0.0
    for k in range(1, 101):
        sim.advance_to(0.1 * k, motion)
        drift = max(drift, abs(total_energy(sim) - e0))
    # Relative to the energy released (E0 - E_rest), the part that can move around.
    assert drift / (e0 - rest) < bound


@pytest.mark.parametrize('integrator', ['rk4', 'symplectic_euler'])
def test_energy_never_increases_with_damping(integrator):
    scene = chain_scene(n=5, damping=2e-3, integrator=integrator, dt=1e-3)
    sim = released(scene, np.radians(45.0))
    motion = StillMotion(ANCHOR)
    energies = [total_energy(sim)]
    for k in range(1, 301):
        sim.advance_to(0.01 * k, motion)
        energies.append(total_energy(sim))
    e = np.array(energies)
    assert np.all(np.diff(e) <= 1e-12 * abs(e[0]))
    assert e[-1] < e[0] - 1e-3 * abs(e[0] - e.min())  # it does dissipate


def random_state(n_chains=3, n=7, seed=0, inertia_general=False):
    rng = np.random.default_rng(seed)
    chains = []
    for c in range(n_chains):
        k = n + c
        masses = rng.uniform(0.01, 0.2, k)
        inertia = None
        if inertia_general:
            inertia = tuple(tuple(row) for row in rng.uniform(1e-6, 1e-4, (k, 3)))
        chains.append(ChainSpec(name=f'c{c}', n_segments=k, length=rng.uniform(0.2, 1.0),
                                segment_masses=tuple(masses), inertia=inertia,
                                attach=tuple(rng.uniform(-0.1, 0.1, 3)), anchor_body=c,
                                damping=1e-3))
    scene = Scene(chains=tuple(chains), n_kinematic_bodies=n_chains)
    head = KinematicState(
        position=rng.normal(size=(n_chains, 3)),
        orientation=np.tile([0, 0, 0, 1.0], (n_chains, 1)),
        linear_velocity=rng.normal(size=(n_chains, 3)),
        angular_velocity=rng.normal(size=(n_chains, 3)),
        linear_acceleration=rng.normal(size=(n_chains, 3)) * 5,
        angular_acceleration=rng.normal(size=(n_chains, 3)))
    sim = Simulator(scene, head)
    st = sim.state
    m = sim.model
    st.q[:] = quat_from_rotvec(rng.normal(size=(m.n, 3)))
    st.w[:] = rng.normal(size=(m.n, 3)) * 3
    sim.reset(head, state=st)
    return sim, head


@pytest.mark.parametrize('general', [False, True])
def test_dense_and_banded_solves_agree(general):
    sim, head = random_state(inertia_general=general)
    dyn, m, st = Dynamics(sim.model), sim.model, sim.state
    h, G_blocks, inv_I, gyro = dyn.mass_terms(st.q, st.w)
    D, L = dyn.blocks(G_blocks)
    rng = np.random.default_rng(1)
    b = rng.normal(size=(m.n, 3))
    f_band = dyn.solve_banded(D, L, b)
    f_dense = dyn.solve_dense(D, L, b)
    assert np.linalg.norm(f_band - f_dense) <= 1e-9 * np.linalg.norm(f_dense)
    # And the dense matrix really is J M⁻¹ Jᵀ: symmetric positive definite.
    A = dyn.assemble_dense(D, L)
    assert np.allclose(A, A.T, atol=1e-12 * np.abs(A).max())
    assert np.linalg.eigvalsh(A).min() > 0


def test_axisymmetric_fast_path_matches_general_inertia():
    sim, head = random_state(inertia_general=False)
    dyn, st = Dynamics(sim.model), sim.state
    assert dyn.axisymmetric
    fast = dyn.mass_terms(st.q, st.w)
    dyn.axisymmetric = False
    slow = dyn.mass_terms(st.q, st.w)
    v = np.random.default_rng(2).normal(size=st.w.shape)
    assert np.allclose(fast[0], slow[0]) and np.allclose(fast[1], slow[1], rtol=1e-10, atol=0)
    assert np.allclose(fast[2](v), slow[2](v), rtol=1e-10)
    assert np.allclose(fast[3], slow[3], rtol=1e-9)


def test_constraint_accelerations_satisfy_the_joint_equation():
    """C̈ = 0: every joint's two points accelerate together (Eq. 14), the anchor's as prescribed."""
    sim, head = random_state(inertia_general=True)
    m, st, dyn = sim.model, sim.state, Dynamics(sim.model)
    anchor = sim.anchors(head)
    F, T = applied_forces(m, st.x, st.q, st.v, st.w, anchor.orientation, anchor.angular_velocity)
    a, alpha = dyn.accelerations(st.x, st.q, st.v, st.w, anchor, F, T)
    h = dyn.mass_terms(st.q, st.w)[0]

    def point_acc(r):
        return a + np.cross(alpha, r) + np.cross(st.w, np.cross(st.w, r))
    child = point_acc(-h)
    parent = m.parent_side(anchor.acceleration, point_acc(h))
    scale = np.abs(child).max()
    assert np.abs(parent - child).max() < 1e-9 * scale


def test_one_way_coupling_reaction_only_on_first_segment():
    """The head's motion is exactly the prescribed one; the anchor's reaction acts on segment 1.

    Newton for the whole chain: Σ m_i a_i = Σ F_applied + f_c[0]: the inner joint forces cancel
    and the only constraint force from outside is the first joint's, on the first segment.
    """
    sim, head = random_state(n_chains=1, n=8)
    before = {k: v.copy() for k, v in vars(head).items()}
    m, st, dyn = sim.model, sim.state, Dynamics(sim.model)
    anchor = sim.anchors(head)
    F, T = applied_forces(m, st.x, st.q, st.v, st.w, anchor.orientation, anchor.angular_velocity)
    a, _ = dyn.accelerations(st.x, st.q, st.v, st.w, anchor, F, T)
    f_c = dyn.last_f_c
    lhs = (m.mass[:, None] * a).sum(axis=0) - F.sum(axis=0)
    assert np.allclose(lhs, f_c[0], rtol=1e-9, atol=1e-12)
    # The simulator never writes to the head's state, and the first joint sits on the anchor.
    motion = SwayYawMotion()
    sim2 = Simulator(chain_scene(n=6, dt=1 / 240), motion)
    for k in range(1, 50):
        sim2.advance_to(k / 120, motion)
        prox, _ = sim2.joint_positions()
        expected = sim2.anchors(motion.state_at(sim2.t)).position[0]
        assert np.linalg.norm(prox[0] - expected) < 1e-12
    for k, v in vars(head).items():
        assert np.array_equal(v, before[k])


def test_rope_settles_straight_down():
    # The whole rope's swing is damped only through the first joint: c = 0.05 N·m·s/rad gives
    # an energy time constant of ~1.4 s for this 1 m, 0.2 kg rope.
    scene = chain_scene(n=10, length=1.0, damping=0.05, dt=1 / 480)
    sim = released(scene, np.radians(60.0), axis=(1.0, 1.0, 0.0) / np.sqrt(2))
    sim.advance_to(30.0, StillMotion(ANCHOR))
    prox, dist = sim.joint_positions()
    direction = (dist - prox) / np.linalg.norm(dist - prox, axis=1, keepdims=True)
    assert np.all(direction[:, 2] < -0.999)            # every segment within 2.6° of vertical
    assert np.linalg.norm(dist[-1, :2] - ANCHOR[:2]) < 0.01


def test_rope_released_horizontally_swings_through_vertical():
    scene = chain_scene(n=10, length=1.0, dt=1 / 480)
    sim = released(scene, np.radians(-90.0))         # down rotated -90° about +Y: along +X
    motion = StillMotion(ANCHOR)
    tip_x = []
    for k in range(1, 200):
        sim.advance_to(k * 0.005, motion)
        tip_x.append(sim.joint_positions()[1][-1, 0])
    tip_x = np.array(tip_x)
    assert tip_x[0] > 0.9 and tip_x.min() < -0.2     # it crossed below the anchor to the far side


def test_joint_gap_stays_closed_ten_minutes_on_moving_head():
    """20 segments, moving head, frames at 120 Hz, default settings, 10 simulated minutes."""
    scene = Scene(chains=(ChainSpec(n_segments=20),))
    motion = SwayYawMotion()
    sim = Simulator(scene, motion)
    worst = 0.0
    for k in range(1, 120 * 600 + 1):
        t = k / 120
        report = sim.advance_frame(t, motion.state_at(t))
        assert report.reset_reason is None
        worst = max(worst, report.max_gap)
    assert worst < 1e-6
    assert sim.state.is_finite()


def test_impulse_moves_the_whole_chain_and_keeps_joints_closed():
    scene = chain_scene(n=6)
    sim = Simulator(scene, KinematicState.still(ANCHOR))
    sim.apply_impulse(5, (0.01, 0.0, 0.0))
    assert sim.joint_gaps().max() < 1e-12
    # Velocity-level constraint holds after the kick: every joint's two sides move together.
    m, st = sim.model, sim.state
    h = half_vectors(m.length, st.q)
    v_child = st.v - np.cross(st.w, h)
    v_parent = m.parent_side(np.zeros((1, 3)), st.v + np.cross(st.w, h))
    assert np.abs(v_parent - v_child).max() < 1e-12
    # Kelvin: from rest, an impulse P at a point gives kinetic energy ½ P · v_point(after).
    ke, _ = sim.energy()
    assert ke.sum() == pytest.approx(0.5 * 0.01 * st.v[5, 0], rel=1e-9)
    assert np.abs(st.v[:5]).max() > 1e-4              # the kick reached the segments above


def test_set_parameters_validates_and_keeps_running_values():
    sim = Simulator(chain_scene(n=3, damping=1e-3), KinematicState.still(ANCHOR))
    with pytest.raises(SceneError) as err:
        sim.set_parameters(damping=2e-3, stiffness=-1.0)
    assert 'stiffness' in str(err.value) and '-1.0' in str(err.value)
    assert np.all(sim.model.damping == 1e-3)          # all-or-nothing
    sim.set_parameters(damping=0.0, wind=(1.0, 0, 0))
    assert not sim.model.active_terms['damping'] and np.all(sim.model.wind == (1, 0, 0))


def test_accumulator_is_frame_rate_independent_and_caps_work():
    motion = SwayYawMotion()
    a = Simulator(chain_scene(n=4, dt=1 / 240), motion)
    b = Simulator(chain_scene(n=4, dt=1 / 240), motion)
    a.advance_to(1.0, motion)
    for k in range(1, 74):                            # irregular frame times
        b.advance_to(min(1.0, k * 0.0137), motion)
    assert a.t == b.t and np.array_equal(a.state.x, b.state.x)
    capped = Simulator(Scene(chains=(ChainSpec(n_segments=3),),
                             solver=SolverSpec(dt=0.01, max_steps_per_call=10)), motion)
    report = capped.advance_to(0.5, motion)
    assert report.steps == 10 and report.dropped_time == pytest.approx(0.4)
    assert capped.t == pytest.approx(0.5) and capped.joint_gaps().max() < 1e-9


def test_frame_rate_independence_on_the_moving_reference_head():
    """Head states only at 30, 60 or 144 Hz frames: tip trajectories agree within 1 mm over 3 s.

    Internal step 1/1440 s divides every frame period, so all runs share one step grid; each
    is compared with the run driven exactly at every stage, at its own frame times.
    """
    from ponytail_ros.core.reference import default_reference_dir, load_reference, reference_scene
    path = default_reference_dir() / 'ponytail_N10_moving_hanging.json'
    if not path.exists():
        pytest.skip(f'reference data not found at {path} (needs ../shared beside the project)')
    scene, motion = reference_scene(load_reference(path), SolverSpec(dt=1 / 1440))
    exact = Simulator(scene, motion)
    exact_tip = {}
    for k in range(1, 3 * 1440 + 1):
        exact.advance_to(k / 1440, motion)
        exact_tip[k] = exact.joint_positions()[1][-1].copy()
    tips = {}
    for rate in (30, 60, 144):
        sim = Simulator(scene, motion)
        errors = []
        for f in range(1, 3 * rate + 1):
            sim.advance_frame(f / rate, motion.state_at(f / rate))
            tip = sim.joint_positions()[1][-1]
            errors.append(np.linalg.norm(tip - exact_tip[f * 1440 // rate]))
            tips[(rate, f * 1440 // rate)] = tip.copy()
        assert max(errors) < 0.5e-3, rate
    common = [k for k in exact_tip if all((r, k) in tips for r in (30, 60, 144))]
    assert len(common) == 18
    for k in common:
        assert np.linalg.norm(tips[(30, k)] - tips[(144, k)]) < 1e-3


def test_frames_closer_than_one_step_stay_stable():
    """Frames 1 µs apart, the chain lagging almost a step behind: the anchor track is bounded."""
    motion = SwayYawMotion()
    sim = Simulator(Scene(chains=(ChainSpec(n_segments=10, damping=1e-3),)), motion)
    t = 0.0
    for k in range(1000):
        t += (1 / 240 + 1e-6) if k % 2 == 0 else 1e-6
        assert sim.advance_frame(t, motion.state_at(t)).reset_reason is None
    assert sim.state.is_finite() and np.abs(sim.state.v).max() < 2.0


def test_anchor_track_at_is_its_table():
    """``AnchorTrack.at`` (the Python side, scalar) and ``AnchorTrack.table`` (the compiled
    step's anchors) are two codings of one track: equal bit for bit before, inside and past
    the frame interval."""
    from ponytail_ros.core.head import AnchorTrack, SwayYawMotion
    motion = SwayYawMotion()
    attach = np.array([[-0.1, 0.0, 0.05]])
    a0, a1 = (motion.state_at(t).point_kinematics(np.array([0]), attach)
              for t in (0.3, 0.3 + 1 / 60))
    track = AnchorTrack(0.3, a0, 0.3 + 1 / 60, a1)
    times = np.array([0.3 - 1e-3, 0.3, 0.305, 0.31, 0.3 + 1 / 60, 0.3 + 1 / 60 + 2e-3])
    table = track.table(times)
    for k, t in enumerate(times):
        one = track.at(t)
        for field in ('position', 'velocity', 'acceleration', 'orientation', 'angular_velocity'):
            assert np.array_equal(getattr(one, field), getattr(table, field)[k]), (field, t)



def test_frame_tables_are_the_frame_ends_and_their_tracks():
    """``head_kernels.frame_tables`` (a tick's head side in one call) gives bit for bit what
    ``frame_ends``, ``AnchorTrack.table`` at ``Simulator._stage_times`` and ``AnchorTrack.at``
    at the frame's end give, for the anchors and for the colliders' bodies, and says whether
    both states are finite (a NaN anywhere in either: False)."""
    from ponytail_ros.core.head import STATE_FIELDS, AnchorTrack, SwayYawMotion, frame_ends
    from ponytail_ros.core.head_kernels import frame_tables

    from helpers import TwoBodies
    fields = ('position', 'velocity', 'acceleration', 'orientation', 'angular_velocity')

    def empty(S, C):
        return (np.empty((S, C, 3)), np.empty((S, C, 3)), np.empty((S, C, 3)),
                np.empty((S, C, 4)), np.empty((S, C, 3)))

    for motion in (SwayYawMotion(), TwoBodies()):
        for t0, t1, t_base, k0, n, dt in ((0.3, 0.3 + 1 / 120, 0.25, 48, 8, 1 / 960),
                                          (1.0, 1.0 + 1e-6, 0.5, 479, 0, 1 / 960),
                                          (2.0, 2.05, 1.9, 7, 3, 0.013)):
            s0, s1 = motion.state_at(t0), motion.state_at(t1)
            K = s0.position.shape[0]
            body_a, attach = np.arange(K), np.linspace(-0.1, 0.1, 3 * K).reshape(K, 3)
            body = np.concatenate([body_a, np.arange(K)])
            r_local = np.concatenate([attach, np.zeros((K, 3))])
            ends_a, ends_b = empty(2, K), empty(2, K)
            tab_a, tab_b = empty(2 * n + 2, K), empty(2 * n + 2, K)
            assert frame_tables(*(np.ascontiguousarray(getattr(s0, f)) for f in STATE_FIELDS),
                                *(np.ascontiguousarray(getattr(s1, f)) for f in STATE_FIELDS),
                                body, r_local, K, t0, t1, t_base, k0, n, dt, ends_a, ends_b,
                                tab_a, tab_b)
            kt = k0 + np.arange(n + 1)
            t = t_base + kt * dt
            times = np.empty(2 * n + 1)
            times[0::2], times[1::2] = t, t[:-1] + 0.5 * dt
            for got_ends, got_tab, b, r in ((ends_a, tab_a, body_a, attach),
                                            (ends_b, tab_b, np.arange(K), np.zeros((K, 3)))):
                ends = frame_ends(s0, s1, b, r)
                track = AnchorTrack.from_ends(t0, t1, ends)
                table, at_end = track.table(times), track.at(t1)
                for j, f in enumerate(fields):
                    assert np.array_equal(got_ends[j], getattr(ends, f)), f
                    assert np.array_equal(got_tab[j][:-1], getattr(table, f)), f
                    assert np.array_equal(got_tab[j][-1], getattr(at_end, f)), f
            bad = np.ascontiguousarray(s1.angular_acceleration).copy()
            bad[-1, 2] = np.nan
            assert not frame_tables(*(np.ascontiguousarray(getattr(s0, f))
                                      for f in STATE_FIELDS),
                                    *(np.ascontiguousarray(getattr(s1, f))
                                      for f in STATE_FIELDS[:-1]), bad,
                                    body, r_local, K, t0, t1, t_base, k0, n, dt, ends_a, ends_b,
                                    tab_a, tab_b)

def test_vectorised_motions_equal_their_per_time_states_bit_for_bit():
    """``states_at(times)`` (what ``advance_to`` evaluates before each compiled call) and
    ``state_at(t)`` at each time are two codings of one motion: equal bit for bit, and so are
    the anchor points computed from them (``point_table`` against ``point_kinematics``); a
    rounding-level difference here would change the chaotic exact-motion runs."""
    from ponytail_ros.app.motions import ShakeNodHead, SpinHead, crowd_motion, shake_motion
    from ponytail_ros.core.head import StillMotion, SwayYawMotion, WithStaticBodies, point_table

    from helpers import TwoBodies
    fields = ('position', 'orientation', 'linear_velocity', 'angular_velocity',
              'linear_acceleration', 'angular_acceleration')
    times = np.sort(np.random.default_rng(3).uniform(0.0, 30.0, 301))
    attach = np.array([[-0.1, 0.0, 0.05], [0.1, 0.02, 0.0]])
    for motion in (SwayYawMotion(), shake_motion(), crowd_motion(5), StillMotion((1, 2, 3)),
                   WithStaticBodies(SwayYawMotion(), 2), SpinHead(3.0, ramp=0.5),
                   ShakeNodHead(), TwoBodies()):
        states = motion.states_at(times)
        body = np.array([0, states.position.shape[1] - 1])
        table = point_table(states, body, attach)
        for k, t in enumerate(times):
            one = motion.state_at(t)
            for f in fields:
                assert np.array_equal(getattr(states, f)[k], getattr(one, f)), (motion, f, t)
            point = one.point_kinematics(body, attach)
            for f in ('position', 'velocity', 'acceleration', 'orientation', 'angular_velocity'):
                assert np.array_equal(getattr(table, f)[k], getattr(point, f)), (motion, f, t)


def test_stage_points_are_the_motions_states_bit_for_bit():
    """``HeadMotion.stage_points`` (what ``advance_to`` evaluates once per call; for a
    ``SinusoidMotion`` one compiled call) equals ``point_table`` of ``states_at`` at
    ``stage_times`` and each row ``state_at(t).point_kinematics``, bit for bit and sign of
    zero alike, for the compiled motions (sway and yaw, sinusoids on every axis with phases,
    several bodies, a still axis, a negative time) and the NumPy ones."""
    from ponytail_ros.app.motions import ShakeNodHead, SinusoidHead, crowd_motion, shake_motion
    from ponytail_ros.core.head import (
        HeadMotion,
        SinusoidMotion,
        StillMotion,
        SwayYawMotion,
        point_table,
        stage_times,
    )
    fields = ('position', 'velocity', 'acceleration', 'orientation', 'angular_velocity')
    rng = np.random.default_rng(5)
    motions = (SwayYawMotion(), SwayYawMotion(p0=(0.3, 0.0, 1.0), amplitude=0, frequency=2),
               shake_motion(), crowd_motion(4),
               SinusoidHead(amplitude=(0.1, 0.02, 0.05), frequency=(1.0, 2.0, 3.0),
                            phase=(0.1, 0.2, 0.3), yaw_phase=0.4),
               StillMotion((1, 2, 3), (0.0, 0.0, np.sin(0.3), np.cos(0.3))), ShakeNodHead())
    for motion in motions:
        K = motion.state_at(0.0).position.shape[0]
        for t_base, k0, n, dt in ((0.0, 0, 8, 1e-3), (0.25, 48, 9, 1 / 960),
                                  (-0.3, 7, 3, 0.013), (12.5, 123456, 0, 1e-3)):
            body = rng.integers(0, K, 3)
            r_local = rng.normal(size=(3, 3)) * 0.1
            times = stage_times(t_base, k0, n, dt)
            got = motion.stage_points(t_base, k0, n, dt, body, r_local)
            tables = (point_table(motion.states_at(times), body, r_local),
                      HeadMotion.stage_points(motion, t_base, k0, n, dt, body, r_local))
            for f in fields:
                a = getattr(got, f)
                assert a.shape[0] == 2 * n + 1 and a.flags.c_contiguous
                for b in (getattr(t, f) for t in tables):
                    assert np.array_equal(a, b) and np.array_equal(np.signbit(a),
                                                                   np.signbit(b)), (motion, f)
            for k, t in enumerate(times):
                one = motion.state_at(t).point_kinematics(body, r_local)
                for f in fields:
                    assert np.array_equal(getattr(got, f)[k], getattr(one, f)), (motion, f, t)
    assert isinstance(shake_motion(), SinusoidMotion) and isinstance(SwayYawMotion(),
                                                                    SinusoidMotion)


@pytest.mark.parametrize('scene, integrator, dt', [
    ('moving', 'rk4', 1 / 240), ('moving', 'rk4', 1 / 60), ('moving', 'symplectic_euler', 1 / 240),
    ('moving', 'rattle', 1 / 480), ('shake', 'rk4', 1 / 60), ('release', 'rk4', 1 / 1000)])
def test_rollout_is_advance_to_at_every_sample_bit_for_bit(scene, integrator, dt):
    """``Simulator.rollout(times, motion)`` evaluates the motion once for all the calls' stage
    times: every sample's state and report equal those of ``advance_to`` called at each time
    in turn, bit for bit, guard resets included (the shake at 1/60 s blows up and resets)."""
    from ponytail_ros.bench.scenes import make_scene
    b = make_scene(scene, n_segments=10, solver=SolverSpec(integrator=integrator, dt=dt))
    times = np.arange(1, 151) * 0.01
    one = Simulator(b.scene, b.motion, 0.0)
    reports, xs, ws = [], [], []
    for t in times:
        reports.append(one.advance_to(t, b.motion))
        xs.append(one.state.x.copy())
        ws.append(one.state.w.copy())
    rolled = Simulator(b.scene, b.motion, 0.0)
    out = rolled.rollout(times, b.motion)
    assert np.array_equal(out.x, np.array(xs))
    assert np.array_equal(out.w, np.array(ws))
    for f in ('x', 'q', 'v', 'w'):
        assert np.array_equal(getattr(rolled.state, f), getattr(one.state, f))
    assert [(r.steps, r.reset_reason, r.max_gap) for r in out.reports] == \
        [(r.steps, r.reset_reason, r.max_gap) for r in reports]
    assert rolled.total_resets == one.total_resets
    one.advance_to(1.6, b.motion)            # and a call after it goes on from the same place
    rolled.advance_to(1.6, b.motion)
    assert np.array_equal(rolled.state.x, one.state.x)
    if (scene, dt) == ('shake', 1 / 60):
        assert one.total_resets > 0
