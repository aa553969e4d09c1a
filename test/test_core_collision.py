"""Contacts with kinematic colliders (no ROS): spheres, capsules, planes; segments as capsules.

Penetration is measured independently of the solver: every segment's axis is sampled densely
and the depth of the capsule around it computed in closed form against each collider.
"""
import numpy as np
import pytest

from ponytail_ros.app.motions import ShakeNodHead
from ponytail_ros.core import (
    ChainSpec,
    KinematicState,
    Scene,
    SceneError,
    Simulator,
    StillMotion,
    collision,
    limits,
)
from ponytail_ros.core.rotations import quat_rotate
from ponytail_ros.core.scene import ColliderSpec, SolverSpec
from ponytail_ros.core.state import half_vectors

from helpers import PENETRATION_TOLERANCE, TwoBodies, total_energy
from oracle.stabilization import project_velocities

DT = 1.0 / 240.0
TOLERANCE = PENETRATION_TOLERANCE
SAMPLES = np.linspace(0.0, 1.0, 41)


def sampled_depth_sphere(sim, centre, radius, skip_first=False):
    """Deepest penetration of the segments' capsules into a sphere, sampled along each axis."""
    prox, dist = sim.joint_positions()
    pts = prox[:, None, :] + SAMPLES[None, :, None] * (dist - prox)[:, None, :]
    depth = radius + sim.model.radius[:, None] - np.linalg.norm(pts - centre, axis=2)
    if skip_first:
        # A chain rooted on the collider: its first segment is held out on its outer half.
        depth[sim.model.is_first, :SAMPLES.size // 2] = -np.inf
    return float(depth.max())


def sampled_depth_capsule(sim, a, b, radius):
    prox, dist = sim.joint_positions()
    pts = prox[:, None, :] + SAMPLES[None, :, None] * (dist - prox)[:, None, :]
    ab = b - a
    t = np.clip(np.einsum('nkj,j->nk', pts - a, ab) / (ab @ ab), 0.0, 1.0)
    d = np.linalg.norm(pts - (a + t[..., None] * ab), axis=2)
    return float((radius + sim.model.radius[:, None] - d).max())



# -- scene description --------------------------------------------------------------------------
@pytest.mark.parametrize('collider, field, fragment', [
    (ColliderSpec(kind='box'), 'kind', "one of ('sphere', 'capsule', 'plane')"),
    (ColliderSpec(body=2), 'body', 'None (world) or an integer in [0, 0]'),
    (ColliderSpec(body=True), 'body', 'None (world)'),
    (ColliderSpec(radius=0.0), 'radius', '(0.0, 100.0]'),
    (ColliderSpec(radius=float('nan')), 'radius', 'radius = nan'),
    (ColliderSpec.capsule(half_length=-0.1), 'half_length', '[0.0, 100.0]'),
    (ColliderSpec.plane(normal=(0, 0, 0)), 'axis', 'non-zero'),
    (ColliderSpec(center=(0, 0)), 'center', '3 finite numbers'),
    (ColliderSpec(friction=-1.0), 'friction', '[0.0, 10.0]'),
])
def test_collider_fields_are_validated_with_name_value_and_range(collider, field, fragment):
    with pytest.raises(SceneError) as err:
        Scene(colliders=(ColliderSpec.sphere(), collider))
    assert err.value.field == f'colliders[1].{field}'
    assert fragment in str(err.value)


def test_scene_collider_list_and_chain_collide_flag_are_validated():
    with pytest.raises(SceneError, match='colliders'):
        Scene(colliders=('sphere',))
    with pytest.raises(SceneError) as err:
        Scene(chains=(ChainSpec(collide=1),))
    assert err.value.field == 'chains[0].collide'
    scene = Scene(colliders=[ColliderSpec.plane()], n_kinematic_bodies=2)
    assert isinstance(scene.colliders, tuple) and scene.colliders[0].body is None


# -- a switched-off feature costs nothing --------------------------------------------------------
def test_scenes_without_colliders_or_limits_never_run_collision_code(monkeypatch):
    """No colliders (or only chains that do not collide) and no limits: the step is the one it
    was before this feature; the collision and limit code is never entered."""
    def fail(*args, **kwargs):
        raise AssertionError('collision code ran')
    for name in ('resolve', 'rows', '_solve', '__init__'):
        monkeypatch.setattr(collision.Unilateral, name, fail)
    monkeypatch.setattr(collision._Detector, 'detect', fail)
    monkeypatch.setattr(limits, 'limit_rows', fail)
    monkeypatch.setattr(limits, 'project_limits', fail)
    motion = ShakeNodHead()
    for scene in (Scene(chains=(ChainSpec(n_segments=6, damping=2e-4),)),
                  Scene(chains=(ChainSpec(n_segments=6, damping=2e-4, collide=False),),
                        colliders=(ColliderSpec.sphere(radius=0.1),))):
        sim = Simulator(scene, motion)
        assert sim.unilateral is None
        sim.advance_to(0.2, motion)
        sim.advance_frame(0.3, motion.state_at(0.3))
        assert np.all(sim.contact_depths() == -np.inf)


def test_a_chain_that_does_not_collide_passes_through_while_another_collides():
    scene = Scene(chains=(ChainSpec(n_segments=4, length=0.4, attach=(0, 0, 0), anchor_body=0,
                                    rest_direction=(1, 0, 0), collide=False),
                          ChainSpec(n_segments=4, length=0.4, attach=(0, 0.1, 0),
                                    rest_direction=(1, 0, 0))),
                  colliders=(ColliderSpec.plane(point=(0, 0, 0.8)),))
    motion = StillMotion((0.0, 0.0, 1.0))
    sim = Simulator(scene, motion)
    lowest = np.full(2, np.inf)
    for k in range(1, 361):
        sim.advance_to(k * DT, motion)
        prox, dist = sim.joint_positions()
        lowest = np.minimum(lowest, [dist[:4, 2].min(), dist[4:, 2].min()])
    assert lowest[0] < 0.7                              # the first swings through the plane
    assert lowest[1] > 0.8 + 0.01 - TOLERANCE           # the second lands on it


# -- the head and its ponytail --------------------------------------------------------------------
@pytest.mark.parametrize('friction', [0.0, 0.4])
def test_ponytail_stays_out_of_a_violently_shaken_head(friction):
    """Head sphere R = 0.1 m centred on the head; ponytail rooted on its surface at the back;
    ±0.1 m at 3 Hz, ±1 rad of yaw at 2.5 Hz and ±0.3 rad of nod, 10 s, dt 1/240, RK4.

    Every reported state: no segment deeper than TOLERANCE in the head (the rooted first
    segment on its outer half; its inner half, by the root, at most the sag of a chord of half
    its length, (l/2)²/(8(R + r)) = 0.45 mm), joints closed to 1e-6 m.
    """
    R, r = 0.1, 0.01
    root = (R + r) * np.array([-np.cos(0.35), 0.0, np.sin(0.35)])
    chain = ChainSpec(n_segments=10, length=0.4, mass=0.1, radius=r, attach=tuple(root),
                      damping=2e-4, drag_linear=0.1, drag_quadratic=0.1)
    scene = Scene(chains=(chain,), colliders=(ColliderSpec.sphere(radius=R, friction=friction),))
    motion = ShakeNodHead()
    sim = Simulator(scene, motion)
    worst, worst_root, worst_gap, touching, fastest = -1.0, -1.0, 0.0, 0, 0.0
    for k in range(1, int(round(10.0 / DT)) + 1):
        report = sim.advance_to(k * DT, motion)
        assert report.reset_reason is None
        worst_gap = max(worst_gap, report.max_gap)
        centre = motion.state_at(sim.t).position[0]
        depth = sampled_depth_sphere(sim, centre, R, skip_first=True)
        worst = max(worst, depth)
        worst_root = max(worst_root, sampled_depth_sphere(sim, centre, R))
        touching += depth > -1e-3
        fastest = max(fastest, float(np.linalg.norm(sim.state.v, axis=1).max()))
    assert worst < TOLERANCE
    assert worst_root < (0.02 ** 2) / (8 * (R + r)) + TOLERANCE
    assert worst_gap < 1e-6
    assert touching > 200 and fastest > 3.0      # it did hit the head, hard


# -- floor --------------------------------------------------------------------------------------
def test_rope_falls_onto_a_floor_stops_above_it_and_rests():
    """A 1 m rope hung 0.6 m above the floor, released horizontally: it lands on the floor,
    never sinks more than TOLERANCE into it, comes to rest lying on it, and (still anchor)
    its energy never increases."""
    r = 0.005
    chain = ChainSpec(name='rope', n_segments=10, length=1.0, mass=0.2, radius=r,
                      attach=(0, 0, 0), rest_direction=(1, 0, 0), damping=2e-4,
                      drag_linear=0.05, drag_quadratic=0.05)
    scene = Scene(chains=(chain,),
                  colliders=(ColliderSpec.plane(point=(0, 0, 0), normal=(0, 0, 1), friction=0.5),))
    motion = StillMotion((0.0, 0.0, 0.6))
    sim = Simulator(scene, motion)
    energies = [total_energy(sim)]
    worst, speed = -1.0, 0.0
    for k in range(1, int(round(6.0 / DT)) + 1):
        sim.advance_to(k * DT, motion)
        prox, dist = sim.joint_positions()
        worst = max(worst, r - float(min(prox[:, 2].min(), dist[:, 2].min())))
        speed = max(speed, float(np.linalg.norm(sim.state.v, axis=1).max()))
        energies.append(total_energy(sim))
    e = np.array(energies)
    assert worst < TOLERANCE and speed > 3.0
    assert np.all(np.diff(e) <= 1e-9)
    prox, dist = sim.joint_positions()
    assert np.count_nonzero(dist[:, 2] < r + 1e-3) >= 4        # lying on the floor
    assert sim.energy()[0].sum() < 1e-5                        # at rest


# -- along the whole length ---------------------------------------------------------------------
def bar_sides(sim, centre):
    """Side of each segment (in the XZ plane) a bar along Y through ``centre`` is on, where
    the bar projects well inside the segment (0 elsewhere)."""
    prox, dist = sim.joint_positions()
    d, rel = dist - prox, centre - prox
    s = np.sum(rel * d, axis=1) / np.sum(d * d, axis=1)
    side = np.sign(d[:, 0] * rel[:, 2] - d[:, 2] * rel[:, 0])
    return np.where((s > 0.1) & (s < 0.9), side, 0.0)


def test_a_bar_between_two_joints_catches_the_segment():
    """A thin bar (capsule, r = 4 mm, μ = 0.5) lies across the path of a falling rope under the
    middle of a 0.1 m segment, where no joint passes: the rope is caught mid-segment, never
    crosses the bar and comes to rest draped over it."""
    r, bar_r = 0.005, 0.004
    a, b = np.array([0.25, -0.2, 0.8]), np.array([0.25, 0.2, 0.8])   # under segment 2's middle
    chain = ChainSpec(n_segments=6, length=0.6, mass=0.1, radius=r, attach=(0, 0, 0),
                      rest_direction=(1, 0, 0), damping=2e-4, drag_linear=0.05)
    # At 1/240 s, the step this scene was set up with: how far the rope slides over the bar
    # before friction (one Jacobi step per step) holds it depends on the step.
    scene = Scene(chains=(chain,),
                  colliders=(ColliderSpec.capsule(center=tuple((a + b) / 2), axis=(0, 1, 0),
                                                  half_length=0.2, radius=bar_r, body=None,
                                                  friction=0.5),),
                  solver=SolverSpec(dt=1 / 240))
    motion = StillMotion((0.0, 0.0, 1.0))
    sim = Simulator(scene, motion)
    worst, first_touch, side = -1.0, None, bar_sides(sim, a)
    for k in range(1, int(round(3.0 / DT)) + 1):
        sim.advance_to(k * DT, motion)
        depth = sampled_depth_capsule(sim, a, b, bar_r)
        worst = max(worst, depth)
        if first_touch is None and depth > -1e-4:
            prox, dist = sim.joint_positions()
            joints = np.vstack([prox, dist[-1:]])
            first_touch = np.linalg.norm(joints[:, [0, 2]] - a[[0, 2]], axis=1).min()
        new = bar_sides(sim, a)
        assert not np.any(new * side < 0), 'a segment crossed the bar'
        side = new
    assert worst < TOLERANCE
    # When it first touched, every joint was clear of the bar: it was hit mid-segment.
    assert first_touch is not None and first_touch > 2 * (r + bar_r)
    # Draped over it: the rope first reaches the bar's x above the bar, its end hangs below.
    prox, dist = sim.joint_positions()
    i = int(np.argmax(dist[:, 0] >= a[0]))
    assert dist[i, 0] >= a[0]
    s = (a[0] - prox[i, 0]) / (dist[i, 0] - prox[i, 0])
    assert prox[i, 2] + s * (dist[i, 2] - prox[i, 2]) > a[2] + bar_r
    assert dist[-1, 2] < a[2] - 0.2 and sim.energy()[0].sum() < 1e-3


@pytest.mark.parametrize('speed', [5.0, 20.0, 50.0])
def test_fast_segments_neither_sink_into_nor_tunnel_through_a_thin_bar(speed):
    """No gravity: a 4-segment rope spun about its anchor so that its far end moves at
    ``speed`` m/s sweeps into a 3 mm bar between its second and third joints. Every reported
    state is within TOLERANCE of the bar's surface, and no segment ever jumps across it."""
    L, n, r, bar_r = 0.4, 4, 0.005, 0.003
    centre = np.array([0.12, 0.0, 0.85])
    chain = ChainSpec(n_segments=n, length=L, mass=0.05, radius=r, attach=(0, 0, 0),
                      rest_direction=(0, 0, -1))
    scene = Scene(chains=(chain,), gravity=(0, 0, 0),
                  colliders=(ColliderSpec.capsule(center=tuple(centre), axis=(0, 1, 0),
                                                  half_length=0.2, radius=bar_r, body=None),))
    anchor = np.array([0.0, 0.0, 1.0])
    sim = Simulator(scene, KinematicState.still(anchor))
    st, m = sim.state, sim.model
    st.w[:] = (0.0, -speed / L, 0.0)
    st.v[:] = project_velocities(m, np.zeros((1, 3)), st.w, half_vectors(m.length, st.q))
    sim.reset(KinematicState.still(anchor), state=st)
    a, b = centre - (0, 0.2, 0), centre + (0, 0.2, 0)
    worst, side, hits = -1.0, bar_sides(sim, centre), 0
    for k in range(1, 121):
        report = sim.advance_to(k * DT, StillMotion(anchor))
        assert report.reset_reason is None
        depth = sampled_depth_capsule(sim, a, b, bar_r)
        worst, hits = max(worst, depth), hits + (depth > -1e-4)
        new = bar_sides(sim, centre)
        assert not np.any(new * side < 0), 'a segment jumped across the bar'
        side = new
    assert hits > 0 and worst < TOLERANCE


# -- energy ---------------------------------------------------------------------------------------
def test_contacts_never_add_energy_on_a_still_head():
    """A rope dropped over a sphere and a capsule onto a floor, damping only: its energy never
    increases from one step to the next (contacts are inelastic; friction dissipates)."""
    chain = ChainSpec(n_segments=12, length=0.8, mass=0.1, radius=0.006, attach=(0, 0, 0),
                      rest_direction=(1, 0.3, 0), damping=1e-3)
    scene = Scene(chains=(chain,), colliders=(
        ColliderSpec.sphere(center=(0.3, 0.1, -0.25), radius=0.1, friction=0.3),
        ColliderSpec.capsule(center=(0.55, 0.0, -0.35), axis=(0, 1, 0.2), half_length=0.3,
                             radius=0.03),
        ColliderSpec.plane(point=(0, 0, -0.6), normal=(0, 0.1, 1), body=None, friction=0.6)))
    motion = StillMotion((0.0, 0.0, 0.0))
    sim = Simulator(scene, motion)
    e = [total_energy(sim)]
    contacts = 0
    for k in range(1, int(round(4.0 / DT)) + 1):
        sim.advance_to(k * DT, motion)
        e.append(total_energy(sim))
        contacts += sim.unilateral.last['contacts']
    rises = np.diff(e)
    assert contacts > 500
    assert rises.max() <= 1e-9, f'energy rose by {rises.max():.3g} J in one step'


# -- colliders on a second, moving body; frames only ---------------------------------------------
@pytest.mark.parametrize('frames', [None, 60])
def test_a_collider_fixed_in_a_second_moving_body(frames):
    """A capsule 'shoulder' on kinematic body 1 sweeps under a rope hung from body 0; driven
    exactly or by head frames at 60 Hz (the body is interpolated like the anchors)."""
    chain = ChainSpec(n_segments=8, length=0.5, mass=0.05, radius=0.005, attach=(0, 0, 0),
                      damping=2e-4, drag_linear=0.05)
    shoulder = ColliderSpec.capsule(center=(0, 0, 0), axis=(0, 1, 0), half_length=0.15,
                                    radius=0.04, body=1)
    scene = Scene(chains=(chain,), n_kinematic_bodies=2, colliders=(shoulder,))
    motion = TwoBodies()
    sim = Simulator(scene, motion)
    worst, hits = -1.0, 0
    for k in range(1, int(round(3.0 / DT)) + 1):
        if frames is None:
            sim.advance_to(k * DT, motion)
        elif k % 4 == 0:
            sim.advance_frame(k / 240.0, motion.state_at(k / 240.0))
        else:
            continue
        st = motion.state_at(sim.t)
        axis = quat_rotate(st.orientation[1], np.array([0.0, 1.0, 0.0]))
        centre = st.position[1]
        depth = sampled_depth_capsule(sim, centre - 0.15 * axis, centre + 0.15 * axis, 0.04)
        worst, hits = max(worst, depth), hits + (depth > -1e-3)
    assert hits > 50
    assert worst < (TOLERANCE if frames is None else 1e-3)


def test_steps_after_a_sub_stepped_one_take_the_rest_of_the_frames_tables():
    """A frame's call (``advance_frame`` with ``head_prev``, as the runner calls it) whose
    step is taken in sub-steps goes on with the rest of the frame's anchor and collider
    tables, sliced from the call's (``Simulator._tables``), bit for bit the tables evaluated
    again at the steps' stage times; the ponytail on its skull in the violent shake (some of
    whose steps sub-step, which this checks first)."""
    from ponytail_ros.app.motions import shake_motion
    from ponytail_ros.testing import load_config
    scene = load_config('config/ponytail.yaml').scene
    motion = shake_motion()
    sims = [Simulator(scene, motion.state_at(0.0)) for _ in range(2)]
    resumed = []

    def evaluated(sim):
        tables = sim._tables

        def again(n_steps, anchor_at, anchor_table, planned, *args):
            if planned is not None and planned[0] != sim._n_steps:
                resumed.append(sim.t)
                planned = None          # evaluated at the stage times, as before slicing
            return tables(n_steps, anchor_at, anchor_table, planned, *args)
        sim._tables = again
    evaluated(sims[1])
    for k in range(1, 4 * 120):
        for sim in sims:
            report = sim.advance_frame(k / 120, motion.state_at(k / 120),
                                       motion.state_at((k - 1) / 120))
            assert report.reset_reason is None
        for f in ('x', 'q', 'v', 'w'):
            assert np.array_equal(getattr(sims[0].state, f), getattr(sims[1].state, f))
    assert len(resumed) >= 5
