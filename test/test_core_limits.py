"""Joint limits (no ROS): swing cones and twist ranges as one-sided constraints.

Angles are checked with an independent computation (``angles`` below): the swing as the angle
between the child's axis and its parent's (the rest direction for the first joint), the twist
from the swing–twist decomposition of the relative rotation.
"""
import numpy as np
import pytest

from ponytail_ros.app.motions import ShakeNodHead
from ponytail_ros.core import ChainSpec, KinematicState, Scene, SceneError, Simulator, StillMotion
from ponytail_ros.core.limits import joint_angles, limit_rows, project_limits
from ponytail_ros.core.rotations import (
    quat_axis_x,
    quat_conjugate,
    quat_from_rotvec,
    quat_integrate,
    quat_multiply,
    quat_rotate,
)
from ponytail_ros.core.state import half_vectors

from helpers import ANGLE_TOLERANCE, total_energy
from oracle.stabilization import project_positions

DT = 1.0 / 240.0


def angles(sim, state=None):
    """Swing and twist of every joint, computed from scratch (rad)."""
    m = sim.model
    st = sim.state if state is None else state
    anchor_q = sim.anchors(sim_head(sim)).orientation
    q_parent = np.concatenate([anchor_q, st.q])[parent_index(m)]
    q_frame = quat_multiply(q_parent, m.q_rest)
    d, e = quat_axis_x(q_frame), quat_axis_x(st.q)
    swing = np.arccos(np.clip(np.sum(d * e, axis=1), -1.0, 1.0))
    rel = quat_multiply(quat_conjugate(q_frame), st.q)
    rel = np.where(rel[:, 3:] < 0, -rel, rel)
    twist = 2.0 * np.arctan2(rel[:, 0], rel[:, 3])
    return swing, twist


def parent_index(m):
    """Per joint, the row of its parent in ``[anchors, segments]``."""
    return np.where(m.is_first, m.chain_of, m.n_chains + m.parent)


def sim_head(sim):
    return sim._head_for_test


def make(scene, motion):
    sim = Simulator(scene, motion)
    sim._head_for_test = motion.state_at(0.0)
    return sim



# -- scene description --------------------------------------------------------------------------
@pytest.mark.parametrize('field, value, fragment', [
    ('swing_limit', 0.0, '(0, 3.1]'),
    ('swing_limit', -0.5, '(0, 3.1]'),
    ('swing_limit', 3.5, '(0, 3.1]'),
    ('twist_limit', float('nan'), 'twist_limit = nan'),
    ('twist_limit', (0.1, 0.2), 'one angle or 3 angles'),
    ('swing_limit', 'wide', 'one angle or 3 angles'),
])
def test_limit_fields_are_validated_with_name_value_and_range(field, value, fragment):
    with pytest.raises(SceneError) as err:
        Scene(chains=(ChainSpec(n_segments=3, **{field: value}),))
    assert err.value.field == f'chains[0].{field}'
    assert fragment in str(err.value)


def test_limits_per_chain_or_per_joint_become_model_arrays():
    scene = Scene(chains=(ChainSpec(n_segments=3, swing_limit=0.5),
                          ChainSpec(n_segments=2, twist_limit=(0.1, 0.2))))
    sim = Simulator(scene)
    assert np.array_equal(sim.model.swing_limit, [0.5, 0.5, 0.5, np.inf, np.inf])
    assert np.array_equal(sim.model.twist_limit, [np.inf, np.inf, np.inf, 0.1, 0.2])
    assert sim.model.has_limits and not sim.model.has_colliders


# -- the constraint's pieces ----------------------------------------------------------------------
def random_pose(seed=0, n=6, spread=0.9):
    scene = Scene(chains=(ChainSpec(n_segments=n, swing_limit=0.4, twist_limit=0.25,
                                    rest_direction=(0.3, 0.2, -1.0)),), gravity=(0, 0, 0))
    head = KinematicState.still((0.0, 0.0, 1.0), (0.1, -0.2, 0.3, 0.927))
    head.orientation /= np.linalg.norm(head.orientation)
    head.angular_velocity[:] = (0.4, -0.3, 0.8)
    sim = Simulator(scene, head)
    sim._head_for_test = head
    rng = np.random.default_rng(seed)
    st = sim.state
    st.q[:] = quat_multiply(quat_from_rotvec(rng.normal(size=(n, 3)) * spread), st.q)
    st.w[:] = rng.normal(size=(n, 3)) * 2.0
    st.x[:] = project_positions(sim.model, sim.anchors(head).position,
                                half_vectors(sim.model.length, st.q))
    return sim, head


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_limit_rates_are_the_time_derivatives_of_the_angles(seed):
    """The rows' separation rates are exactly -d(angle)/dt (finite differences)."""
    sim, head = random_pose(seed)
    m, st = sim.model, sim.state
    anchor = sim.anchors(head)
    rows = limit_rows(m, st.q, st.w, anchor, lambda gap, sep: np.ones(gap.shape, bool))
    n = m.n
    eps = 1e-7
    swing0, twist0 = joint_angles(m, st.q, anchor.orientation)
    q1 = quat_integrate(st.q, st.w, eps)
    a1 = quat_integrate(anchor.orientation, anchor.angular_velocity, eps)
    swing1, twist1 = joint_angles(m, q1, a1)
    assert np.allclose(-rows['sep'][:n], (swing1 - swing0) / eps, rtol=1e-4, atol=1e-5)
    assert np.allclose(-rows['sep'][n:], np.sign(twist0) * (twist1 - twist0) / eps,
                       rtol=1e-4, atol=1e-5)
    swing, twist = angles(sim)
    assert np.allclose(swing, swing0) and np.allclose(twist, twist0)


@pytest.mark.parametrize('seed', [0, 1, 2, 3])
def test_projection_puts_every_joint_on_its_limits_in_one_pass(seed):
    """Violating joints end exactly on their limits; the others keep their relative rotation."""
    sim, head = random_pose(seed, n=8, spread=1.2)
    m, st = sim.model, sim.state
    anchor_q = sim.anchors(head).orientation
    swing0, twist0 = joint_angles(m, st.q, anchor_q)
    assert np.any(swing0 > 0.4) and np.any(np.abs(twist0) > 0.25)
    q = project_limits(m, st.q, anchor_q)
    swing, twist = joint_angles(m, q, anchor_q)
    assert np.all(swing <= 0.4 + 1e-9) and np.all(np.abs(twist) <= 0.25 + 1e-9)
    ok = (swing0 <= 0.4) & (np.abs(twist0) <= 0.25)
    parent = np.concatenate([anchor_q, st.q])[parent_index(m)]
    parent_new = np.concatenate([anchor_q, q])[parent_index(m)]
    rel0 = quat_multiply(quat_conjugate(parent), st.q)
    rel1 = quat_multiply(quat_conjugate(parent_new), q)
    same = np.abs(np.sum(rel0 * rel1, axis=1))
    assert np.allclose(same[ok], 1.0, atol=1e-12)
    assert np.allclose(swing[~(swing0 <= 0.4)], 0.4)
    assert project_limits(m, q, anchor_q, 1e-9) is None


# -- in motion ----------------------------------------------------------------------------------
def test_swing_and_twist_hold_under_a_violent_shake():
    """Ponytail with a 0.3 rad cone and ±0.2 rad of twist at every joint, on the violent shake
    (±0.1 m at 3 Hz, ±1 rad yaw at 2.5 Hz, nod), 10 s at dt 1/240: every reported state is
    within ANGLE_TOLERANCE of the limits; joints closed."""
    chain = ChainSpec(n_segments=10, length=0.4, mass=0.1, radius=0.01, attach=(-0.1, 0, 0),
                      damping=2e-4, drag_linear=0.1, drag_quadratic=0.1, swing_limit=0.3,
                      twist_limit=0.2)
    motion = ShakeNodHead()
    sim = make(Scene(chains=(chain,)), motion)
    worst_s = worst_t = -1.0
    at_limit = 0
    for k in range(1, int(round(10.0 / DT)) + 1):
        report = sim.advance_to(k * DT, motion)
        assert report.reset_reason is None and report.max_gap < 1e-6
        sim._head_for_test = motion.state_at(sim.t)
        swing, twist = angles(sim)
        worst_s = max(worst_s, float((swing - 0.3).max()))
        worst_t = max(worst_t, float((np.abs(twist) - 0.2).max()))
        at_limit += int(np.count_nonzero(swing > 0.3 - 1e-3))
    assert worst_s < ANGLE_TOLERANCE and worst_t < ANGLE_TOLERANCE
    assert at_limit > 1000                       # the limits were doing work


def test_first_joint_limit_is_about_the_rest_direction_in_the_head_frame():
    """A short 'tail' sticking out backwards (rest direction -X in the head frame) with a
    0.25 rad cone at its root only: while the head yaws, gravity bends it down onto the cone
    about the head's -X, not about the vertical."""
    chain = ChainSpec(n_segments=4, length=0.3, mass=0.05, radius=0.01, attach=(-0.1, 0, 0),
                      rest_direction=(-1, 0, 0), damping=1e-3, swing_limit=(0.25, 3.1, 3.1, 3.1))
    motion = ShakeNodHead(amplitude=0.0, pitch=0.0, yaw=0.8, yaw_frequency=0.5)
    sim = make(Scene(chains=(chain,)), motion)
    for k in range(1, int(round(3.0 / DT)) + 1):
        sim.advance_to(k * DT, motion)
        head = motion.state_at(sim.t)
        back = quat_rotate(head.orientation[0], np.array([-1.0, 0.0, 0.0]))
        e = quat_axis_x(sim.state.q)[0]
        assert np.arccos(np.clip(e @ back, -1, 1)) < 0.25 + ANGLE_TOLERANCE
    assert e[2] < -0.2                               # pulled down onto the cone


def test_limits_never_add_energy_on_a_still_head():
    """Released bent far beyond its limits at rest, gravity and joint damping only: after the
    first step (which puts it onto its limits), energy never increases."""
    chain = ChainSpec(n_segments=8, length=0.4, mass=0.08, radius=0.01, attach=(0, 0, 0),
                      damping=1e-3, swing_limit=0.35, twist_limit=0.15)
    scene = Scene(chains=(chain,))
    head = KinematicState.still((0.0, 0.0, 1.0))
    sim = make(scene, StillMotion((0.0, 0.0, 1.0)))
    rng = np.random.default_rng(4)
    st = sim.state
    st.q[:] = quat_multiply(quat_from_rotvec(rng.normal(size=(8, 3)) * 0.8), st.q)
    st.x[:] = project_positions(sim.model, sim.anchors(head).position,
                                half_vectors(sim.model.length, st.q))
    sim.reset(head, state=st)
    sim.advance_to(DT, StillMotion((0.0, 0.0, 1.0)))
    e = [total_energy(sim)]
    active = 0
    for k in range(2, int(round(3.0 / DT)) + 1):
        sim.advance_to(k * DT, StillMotion((0.0, 0.0, 1.0)))
        e.append(total_energy(sim))
        active += sim.unilateral.last['limits']
    rises = np.diff(e)
    assert active > 100                          # the limits were doing work
    assert rises.max() <= 1e-9, f'energy rose by {rises.max():.3g} J in one step'
