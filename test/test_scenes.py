"""The ready-made scenes (``config/*.yaml``): each runs in the node and in replay, and the
colliders and limits each enables hold under a violent shake.

The first part is ROS-free (the scenes built from their params files, stepped in the core);
the second runs each scene in a real node on an in-process executor, records it, and replays
the recording offline.
"""
import time
from dataclasses import fields

import numpy as np
import pytest

from ponytail_ros.app.motions import ShakeNodHead
from ponytail_ros.app.param_values import (
    complete_values,
    scene_and_settings,
    values_from_params_file,
)
from ponytail_ros.core import Simulator
from ponytail_ros.core.head import HeadMotion, KinematicState, WithStaticBodies
from ponytail_ros.core.rotations import quat_multiply, quat_rotate
from ponytail_ros.resources import config_path

from helpers import ANGLE_TOLERANCE, PENETRATION_TOLERANCE as TOLERANCE

SCENES = ('ponytail.yaml', 'pigtails.yaml', 'rope.yaml', 'sword.yaml', 'tail.yaml',
          'tail_and_ponytail.yaml', 'ponytail_arm.yaml')
DT = 1.0 / 120.0            # frames: the node's default rate


def scene_of(name):
    values = complete_values(values_from_params_file(config_path(name)))
    chains, scene, _ = scene_and_settings(values)
    return values, scene


# -- what each scene models (ROS-free) ----------------------------------------------------------

def test_each_scene_enables_only_what_it_needs():
    scenes = {name: scene_of(name)[1] for name in SCENES}
    pony = scenes['ponytail.yaml']
    (c,) = pony.chains
    assert [k.kind for k in pony.colliders] == ['sphere'] and pony.colliders[0].body == 0
    assert c.damping > 0 and c.stiffness > 0 and c.drag_linear > 0
    assert c.swing_limit is None and c.twist_limit is None
    pig = scenes['pigtails.yaml']
    assert [ch.name for ch in pig.chains] == ['left', 'right']
    assert np.allclose(np.array(pig.chains[0].attach) * [1, -1, 1], pig.chains[1].attach)
    rope = scenes['rope.yaml']
    (c,) = rope.chains
    assert c.n_segments == 40 and rope.n_kinematic_bodies == 2 and c.anchor_body == 1
    assert not rope.colliders and c.swing_limit is None and c.twist_limit is None
    assert c.damping == c.stiffness == c.drag_linear == c.drag_quadratic == 0.0
    assert np.allclose(rope.wind, 0.0)
    sword = scenes['sword.yaml']
    (c,) = sword.chains
    assert c.n_segments <= 2 and c.swing_limit > 0 and c.stiffness == 0.0
    assert [k.kind for k in sword.colliders] == ['capsule']
    tail = scenes['tail.yaml']
    (c,) = tail.chains
    assert c.stiffness > 0 and [k.kind for k in tail.colliders] == ['capsule']
    assert np.all(np.diff(c.joint_limits('swing_limit')) > 0) and c.twist_limit is None
    arm = scenes['ponytail_arm.yaml']
    assert arm.chains == pony.chains and arm.colliders[0] == pony.colliders[0]
    assert arm.n_kinematic_bodies == 2 and arm.colliders[1].kind == 'capsule'
    assert arm.colliders[1].body == 1                        # the left forearm frame


def test_rope_from_the_ceiling_conserves_energy_with_gravity_only():
    """The rope is undamped and its anchor static: released 60° from the vertical it swings
    with its energy conserved (RK4 at 1/240 s) and its root on the ceiling point."""
    values, scene = scene_of('rope.yaml')
    # The head is irrelevant.
    motion = WithStaticBodies(ShakeNodHead(), scene.n_kinematic_bodies - 1)
    sim = Simulator(scene, motion)
    (c,) = scene.chains
    e0 = sum(float(e.sum()) for e in sim.energy())
    # Energy the release can give: from 60° (centre of mass 0.5 m below the ceiling) to
    # hanging straight (1 m below).
    releasable = c.mass * 9.81 * (0.5 * c.length - 0.5 * c.length * 0.5)
    lowest, fastest, drift = np.inf, 0.0, 0.0
    for k in range(1, int(round(5.0 / DT)) + 1):
        report = sim.advance_to(k * DT, motion)
        assert report.reset_reason is None and report.max_gap < 1e-9
        lowest = min(lowest, float(sim.joint_positions()[1][-1, 2]))
        ke, pe = sim.energy()
        drift = max(drift, abs(float(ke.sum() + pe.sum()) - e0))
        fastest = max(fastest, float(ke.sum()))
    assert drift < 1e-3 * releasable
    assert fastest > 0.5 * releasable                          # it did swing
    assert lowest < 3.0 - 0.95 * c.length                      # through the vertical
    assert np.allclose(sim.joint_positions()[0][0], values['rope.attach'], atol=1e-12)


#: Poses of the scenes' extra frames, relative to the head (position in the head frame,
#: rotation): the left forearm across the back of the neck, just clear of the hanging ponytail
#: (its +X, the forearm's axis, along the head's -Y), touched when the head swings.
FRAME_OFFSETS = {'left_forearm': (np.array([-0.17, 0.13, -0.2]),
                                  np.array([0.0, 0.0, -np.sqrt(0.5), np.sqrt(0.5)]))}


class FramesOnHead(HeadMotion):
    """``motion``'s head followed by the scene's frames carried rigidly by it
    (``FRAME_OFFSETS``), then ``n_static`` static bodies: exact derivatives (Eq. 1-3)."""

    def __init__(self, motion, frames, n_static=0):
        self.motion, self.frames, self.n_static = motion, list(frames), n_static

    def state_at(self, t):
        head = self.motion.state_at(t)
        states = [head]
        for f in self.frames:
            offset, rotation = FRAME_OFFSETS[f]
            point = head.point_kinematics(np.array([0]), offset[None])
            states.append(KinematicState(
                point.position, quat_multiply(head.orientation, rotation[None]), point.velocity,
                head.angular_velocity.copy(), point.acceleration,
                head.angular_acceleration.copy()))
        stacked = KinematicState(*(np.concatenate([getattr(st, f.name) for st in states])
                                   for f in fields(KinematicState)))
        return stacked.with_static_bodies(self.n_static)


@pytest.mark.parametrize('name', ['ponytail.yaml', 'pigtails.yaml', 'sword.yaml', 'tail.yaml',
                                  'ponytail_arm.yaml'])
def test_colliders_and_limits_of_each_scene_hold_under_a_violent_shake(name):
    """The violent shake (±0.1 m at 3 Hz, ±1 rad of yaw at 2.5 Hz, ±0.3 rad of nod) for 6 s
    at the node's 120 Hz frames: no reset, joints closed, no segment deeper than TOLERANCE in
    a collider (a chain's rooted first segment on its outer half, as the solver treats it),
    no joint beyond its swing or twist limit by more than ANGLE_TOLERANCE. Extra frames (the
    forearm) are carried by the shaken head."""
    values, scene = scene_of(name)
    frames = list(values['frames'])
    motion = FramesOnHead(ShakeNodHead(), frames, scene.n_kinematic_bodies - 1 - len(frames))
    sim = Simulator(scene, motion)
    m = sim.model
    swing_max = np.concatenate([c.joint_limits('swing_limit') for c in scene.chains])
    twist_max = np.concatenate([c.joint_limits('twist_limit') for c in scene.chains])
    worst_depth = worst_swing = worst_twist = -np.inf
    touching = 0
    for k in range(1, int(round(6.0 / DT)) + 1):
        report = sim.advance_to(k * DT, motion)
        assert report.reset_reason is None and report.max_gap < 1e-6
        depth = sim.contact_depths()
        worst_depth = max(worst_depth, float(depth.max()))
        touching += int(np.count_nonzero(depth > -1e-3))
        if m.has_limits:
            swing, twist = sim.joint_angles()
            worst_swing = max(worst_swing, float((swing - swing_max).max()))
            worst_twist = max(worst_twist, float((np.abs(twist) - twist_max).max()))
    assert worst_depth < TOLERANCE and touching > 0
    if m.has_limits:
        assert worst_swing < ANGLE_TOLERANCE and worst_twist < ANGLE_TOLERANCE


# -- in the node and in replay -----------------------------------------------------------------

rclpy = pytest.importorskip('rclpy')
from geometry_msgs.msg import PoseArray, PoseStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from ponytail_ros.app.head_script import HeadScript  # noqa: E402
from ponytail_ros.node import PonytailNode  # noqa: E402
from ponytail_ros.recording.offline import replay  # noqa: E402

from ros_helpers import TIMEOUT_SCALE, pose_msg, poses_by_stamp  # noqa: E402

TICKS = 60


@pytest.mark.parametrize('name', SCENES)
def test_each_scene_runs_in_the_node_and_replays_exactly(name, ros_context, tmp_path):
    """The scene's params file as the node's parameters, recorded; a scripted head at 100 Hz
    (none for a scene that needs no head: the rope hangs from the ceiling alone). Every chain
    publishes TICKS ticks with closed joints, the world-anchored root on its ceiling point,
    colliders drawn in the markers; then ``ponytail_replay`` reproduces every tick exactly."""
    values, scene = scene_of(name)
    params = dict(values_from_params_file(config_path(name)))
    path = tmp_path / 'run.mcap'
    params.update(record_path=str(path), diagnostics_period=0.2)
    node = PonytailNode(context=ros_context,
                        parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    chains = list(values['chains'])
    topics = ['segment_poses'] if len(chains) == 1 else [f'segment_poses/{c}' for c in chains]
    tester = rclpy.create_node('tester', context=ros_context)
    got = {tp: [] for tp in topics}
    for tp in topics:
        tester.create_subscription(PoseArray, tp, got[tp].append, 100)
    markers = []
    tester.create_subscription(MarkerArray, 'segment_markers', markers.append, 100)
    head_pub = tester.create_publisher(PoseStamped, 'head_pose', 10)
    frames = list(values['frames'])
    frame_pubs = [tester.create_publisher(PoseStamped, values[f'{f}.topic'] or f'{f}_pose', 10)
                  for f in frames]
    needs_head = node.runner.needs_head
    script, t0 = HeadScript(origin=np.array([0.0, 0.0, 1.0])), time.monotonic()

    def publish_head():
        state = script.state_at(time.monotonic() - t0)
        t = tester.get_clock().now().nanoseconds * 1e-9
        p, q = state.position[0], state.orientation[0]
        head_pub.publish(pose_msg(t, p, q))
        for f, pub in zip(frames, frame_pubs, strict=True):     # each frame carried by the head
            offset, rotation = FRAME_OFFSETS[f]
            pub.publish(pose_msg(t, p + quat_rotate(q, offset), quat_multiply(q, rotation)))
    if needs_head:
        tester.create_timer(0.01, publish_head)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(tester)
    try:
        deadline = time.monotonic() + 30.0 * TIMEOUT_SCALE
        while min(len(v) for v in got.values()) < TICKS and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.005)
        resets = dict(node.runner.resets)
    finally:
        executor.shutdown()
        node.destroy_node()               # finalises the recording
        tester.destroy_node()
    assert min(len(v) for v in got.values()) >= TICKS
    assert resets['guard'] == 0
    assert needs_head == (name != 'rope.yaml')

    for tp, spec in zip(topics, scene.chains, strict=True):
        lengths = spec.lengths()
        for msg in got[tp]:
            assert msg.header.frame_id == 'world' and len(msg.poses) == spec.n_segments
            o = np.array([[p.position.x, p.position.y, p.position.z] for p in msg.poses])
            q = np.array([[p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]
                          for p in msg.poses])
            tips = o + quat_rotate(q, np.outer(lengths, [1.0, 0.0, 0.0]))
            assert np.abs(tips[:-1] - o[1:]).max(initial=0.0) < 1e-6    # joints closed
            if spec.anchor_body == 1:
                assert np.allclose(o[0], spec.attach, atol=1e-9)         # on the ceiling
    drawn = {m.ns for a in markers for m in a.markers}
    assert set(chains) <= drawn and (('colliders' in drawn) == bool(scene.colliders))

    out = tmp_path / 'replayed.mcap'
    result = replay(path, out)
    assert result.ticks >= TICKS
    for tp in topics:
        live, again = poses_by_stamp(path, '/' + tp), poses_by_stamp(out, '/' + tp)
        assert list(again) == list(live) and len(live) >= TICKS
        assert all(again[s] == live[s] for s in live)


def test_collider_and_limit_parameters_are_checked_named_and_applied_live(ros_context):
    """Bad collider/limit values are refused at start-up and live with the parameter's name
    and range (the running value stays); a good live change rebuilds the chain with it."""
    from ponytail_ros.app.parameters import ParameterError
    params = dict(values_from_params_file(config_path('ponytail.yaml')))

    def make(**changes):
        p = {**params, **{k.replace('__', '.'): v for k, v in changes.items()}}
        return PonytailNode(context=ros_context,
                            parameter_overrides=[Parameter(k, value=v) for k, v in p.items()])
    with pytest.raises(ParameterError, match=r'skull\.kind = .box. is not allowed: must be one '
                                              r'of sphere, capsule, plane'):
        make(skull__kind='box')
    with pytest.raises(ParameterError, match=r'share the name'):
        make(colliders=['ponytail'])
    with pytest.raises(Exception, match=r'skull\.radius'):
        make(skull__radius=-1.0)

    node = make()
    try:
        assert node.core.scene.colliders[0].radius == 0.09
        bad = node.set_parameters([Parameter('skull.radius', value=200.0),
                                   Parameter('ponytail.swing_limit', value=4.0),
                                   Parameter('skull.center', value=[0.0, 2e3, 0.0])])
        assert not any(r.successful for r in bad)
        assert 'skull.radius' in bad[0].reason and '100' in bad[0].reason
        assert 'ponytail.swing_limit' in bad[1].reason and '3.1' in bad[1].reason
        assert 'skull.center' in bad[2].reason and '1000' in bad[2].reason
        assert node.core.values['skull.radius'] == 0.09
        assert node.core.scene.colliders[0].radius == 0.09
        good = node.set_parameters([Parameter('skull.radius', value=0.08),
                                    Parameter('ponytail.swing_limit', value=0.5)])
        assert all(r.successful for r in good)
        assert node.core.scene.colliders[0].radius == 0.08
        assert node.core.scene.chains[0].swing_limit == 0.5
        (colliders,) = [p.value for p in node.get_parameters(['colliders'])]
        assert list(colliders) == ['skull']
    finally:
        node.destroy_node()


def test_per_segment_parameters_in_the_node(ros_context):
    """Per-segment lengths and masses and per-joint limits as node parameters: integers are
    taken for doubles, a list of the wrong size is refused naming it (the running value stays),
    a good live change rebuilds the chain with it, and [] goes back to the uniform chain."""
    from ponytail_ros.app.parameters import ParameterError
    lengths = [0.2, 0.1, 0.05]

    def make(**p):
        base = {'ponytail.n_segments': 3, 'ponytail.segment_lengths': lengths}
        return PonytailNode(context=ros_context, parameter_overrides=[
            Parameter(k, value=v) for k, v in {**base, **p}.items()])
    with pytest.raises(ParameterError, match=r'ponytail\.segment_masses = .* must be 3 positive'):
        make(**{'ponytail.segment_masses': [0.1, 0.1]})
    node = make(**{'ponytail.segment_masses': [1, 1, 1]})
    try:
        (c,) = node.core.scene.chains
        assert np.allclose(c.lengths(), lengths) and np.allclose(c.masses(), 1.0)
        bad = node.set_parameters([Parameter('ponytail.segment_lengths', value=[0.1, 0.1]),
                                   Parameter('ponytail.swing_limits', value=[0.5, 0.5, 9.0])])
        assert not any(r.successful for r in bad)
        assert 'ponytail.segment_lengths' in bad[0].reason and '3 positive' in bad[0].reason
        assert 'ponytail.swing_limits' in bad[1].reason and '3.1' in bad[1].reason
        assert np.allclose(node.core.scene.chains[0].lengths(), lengths)
        good = node.set_parameters([Parameter('ponytail.swing_limits', value=[0.2, 0.4, 0.6]),
                                    Parameter('ponytail.segment_lengths', value=[0.1, 0.1, 0.1])])
        assert all(r.successful for r in good), [r.reason for r in good]
        c = node.core.scene.chains[0]
        assert np.allclose(c.joint_limits('swing_limit'), [0.2, 0.4, 0.6])
        assert np.allclose(c.lengths(), 0.1)
        assert node.set_parameters([Parameter('ponytail.segment_lengths', value=[])])[0].successful
        assert np.allclose(node.core.scene.chains[0].lengths(), 0.4 / 3)
    finally:
        node.destroy_node()
