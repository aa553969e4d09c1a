"""Extra kinematic frames (``frames``): colliders and chain anchors fixed in bodies whose pose
arrives on their own topic (a forearm), in the runner (ROS-free), in the parameters, in a real
node on an in-process executor, and in a recording and its replay."""
import math

import numpy as np
import pytest

from ponytail_ros.app.param_values import (
    complete_values,
    scene_and_settings,
    values_from_params_file,
)
from ponytail_ros.app.parameters import ParameterError
from ponytail_ros.app.runner import START_SAMPLES, ChainRunner, RunnerSettings
from ponytail_ros.core import ChainSpec, Scene
from ponytail_ros.core.scene import ColliderSpec
from ponytail_ros.resources import config_path

#: Stated penetration bound (the position stage stops at 1e-5 m), as in test_core_collision.
TOLERANCE = 2e-5
Q_ID = np.array([0.0, 0.0, 0.0, 1.0])
ATTACH = np.array([-0.09, 0.0, 0.06])
P_STILL = np.array([1.0, -2.0, 1.5])
#: The capsule of the tests: fixed in the frame, along the frame's y, 0.3 m core.
CAPSULE = dict(center=(0.0, 0.0, 0.0), axis=(0.0, 1.0, 0.0), half_length=0.15, radius=0.04)
CHAIN = dict(name='ponytail', n_segments=6, length=0.3, mass=0.1, radius=0.03,
             attach=tuple(ATTACH), damping=1e-3, drag_linear=0.05)


def capsule_depths(origins, orientations, seg_length, seg_radius, centre, axis, half_length,
                   radius, samples=41):
    """Deepest penetration of each segment (a capsule of ``seg_radius`` from its origin along
    its local +X) into a capsule collider, each segment's axis sampled at ``samples`` points
    (closed-form point-to-segment distance): independent of the solver's own measure."""
    from ponytail_ros.core.rotations import quat_axis_x
    s = np.linspace(0.0, seg_length, samples)
    pts = origins[:, None, :] + quat_axis_x(orientations)[:, None, :] * s[None, :, None]
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    rel = pts - np.asarray(centre, float)
    along = np.clip(rel @ axis, -half_length, half_length)
    dist = np.linalg.norm(rel - along[..., None] * axis, axis=-1)
    return (radius + seg_radius - dist).max(axis=1)


def arm_path(t, a, start=0.3, duration=1.0):
    """The frame's position at ``t`` s: from 0.25 m beside the chain (in +x, 0.22 m below its
    attachment point ``a``) across to the chain's rest line, smoothly, then held."""
    s = min(max((t - start) / duration, 0.0), 1.0)
    s = s * s * (3.0 - 2.0 * s)
    return np.asarray(a) + np.array([0.25 - 0.25 * s, 0.0, -0.22])


# -- the runner (ROS-free) ----------------------------------------------------------------------

def arm_scene(**chain):
    return Scene(chains=(ChainSpec(**{**CHAIN, **chain}),), n_kinematic_bodies=2,
                 colliders=(ColliderSpec.capsule(body=1, **CAPSULE),))


def test_runner_frame_drops_are_counted_by_reason_and_nothing_runs_without_the_frame():
    """``push_frame`` samples go through the head's checks, counted in the same ``dropped``
    (a NaN pose as 'nonfinite'), reported to ``on_drop`` with the frame's name; the scene that
    uses the frame publishes nothing until the frame has a pose; a clock going backwards
    restarts the frame's history too."""
    r = ChainRunner(arm_scene(), RunnerSettings(max_queue=8), frames=('arm',))
    drops = []
    r.on_drop = lambda reason, t, source: drops.append((reason, source))
    a = P_STILL + ATTACH
    t = 10.0
    for _ in range(5):
        r.push(t, P_STILL, Q_ID, 'world')
        assert r.tick(t) is None                        # the head alone is not enough
        t += 0.01
    assert r.has_head and r.missing_inputs() == ['arm'] and not r.has_frame(0)

    r.push_frame(0, t, [math.nan, 0.0, 0.0], Q_ID, 'world')            # nonfinite
    r.push_frame(0, t, arm_path(0.0, a), [0.0, 0.0, 0.0, 2.0], 'world')  # non-unit quaternion
    r.push_frame(0, t, arm_path(0.0, a), Q_ID, 'map')                  # not the head's frame
    r.push(t, P_STILL, Q_ID, 'world')
    assert r.tick(t) is None
    assert drops == [('nonfinite', 'arm'), ('non_unit_quaternion', 'arm'),
                     ('frame_changed', 'arm')]
    assert (r.dropped['nonfinite'], r.dropped['non_unit_quaternion'],
            r.dropped['frame_changed']) == (1, 1, 1)

    # A flood overflows the frame's own queue (oldest first); the rest is taken in.
    t += 0.01
    for k in range(10):
        r.push_frame(0, t + k * 1e-3, arm_path(0.0, a), Q_ID, 'world')
    r.push(t, P_STILL, Q_ID, 'world')
    out = r.tick(t + 0.01)
    assert out is not None and r.missing_inputs() == []
    assert r.dropped['queue_overflow'] == 2 and drops[-1] == ('queue_overflow', 'arm')
    assert r.frame_accepted_total == [8]
    r.push_frame(0, t + 9e-3, arm_path(0.0, a), Q_ID, 'world')          # same stamp again
    r.tick(t + 0.02)
    assert r.dropped['stamp_repeated'] == 1 and drops[-1] == ('stamp_repeated', 'arm')
    assert sum(r.dropped.values()) == 6

    # The bodies: head, then the frame (the world body only with a world anchor).
    bodies = r.bodies_at(out.t_head)
    assert bodies.n_bodies == 2
    assert np.allclose(bodies.position, [P_STILL, arm_path(0.0, a)], atol=1e-12)
    assert r.needs_head and r.needs_frame(0) and not r.frame_stale(0, t + 0.02)
    assert r.frame_stale(0, t + 0.02 + 2 * r.settings.stale_timeout)

    # Clock backwards: everything restarts, the frame's history too.
    assert r.tick(t - 1.0) is None
    assert r.resets['clock_backwards'] == 1 and not r.has_frame(0) and not r.has_head
    assert r.missing_inputs() == ['head', 'arm']


def test_runner_frames_only_scene_latches_the_world_frame_from_a_frame():
    """A rope from the ceiling (world anchor) with a collider on a frame needs no head: the
    frame's first pose latches the world frame, and a pose in another frame is dropped."""
    scene = Scene(chains=(ChainSpec(**{**CHAIN, 'anchor_body': 2,
                                       'attach': (0.0, 0.0, 2.0)}),),
                  n_kinematic_bodies=3, colliders=(ColliderSpec.capsule(body=1, **CAPSULE),))
    r = ChainRunner(scene, frames=('arm',))
    assert not r.needs_head and r.missing_inputs() == ['arm']
    assert r.tick(5.0) is None
    r.push_frame(0, 5.0, [0.3, 0.0, 1.8], Q_ID, 'map')
    out = r.tick(5.01)
    assert out is not None and out.frame_id == 'map'
    assert np.allclose(out.origins[0], [0.0, 0.0, 2.0], atol=1e-12)       # on the ceiling
    bodies = r.bodies_at(out.t_head)
    assert bodies.n_bodies == 3 and np.allclose(bodies.position[2], 0.0)
    r.push_frame(0, 5.02, [0.3, 0.0, 1.8], Q_ID, 'world')
    r.tick(5.03)
    assert r.dropped['frame_changed'] == 1


def test_runner_capsule_on_a_frame_pushes_the_chain_aside():
    """The forearm's capsule swept across a chain hanging from a still head: the chain is
    pushed aside and no reported state is deeper in it than TOLERANCE."""
    r = ChainRunner(arm_scene(), frames=('arm',))
    a = P_STILL + ATTACH
    worst = -np.inf
    for k in range(200):
        t = 10.0 + k / 100.0
        r.push(t, P_STILL, Q_ID, 'world')
        r.push_frame(0, t, arm_path(t - 10.0, a), Q_ID, 'world')
        out = r.tick(t + 1e-3)
        if out is None:               # the head's first poses: no velocity estimate yet
            assert k < START_SAMPLES - 1
            continue
        worst = max(worst, float(r.sim.contact_depths().max()))
    assert worst < TOLERANCE and r.resets['guard'] == 0
    depth = capsule_depths(out.origins, out.orientations, 0.05, 0.03, arm_path(2.0, a),
                           [0.0, 1.0, 0.0], 0.15, 0.04)
    assert depth.max() < TOLERANCE
    assert out.origins[-1, 0] < a[0] - 0.05                     # pushed aside (in -x)


# -- parameters (ROS-free) -----------------------------------------------------------------------

def test_runner_bodies_from_the_estimator_bank_equal_each_estimators_own():
    """With frames the runner fits every input in one call (``HeadEstimatorBank``): the same
    bodies, bit for bit, as each estimator's own ``state_at`` stacked, before and after the
    frame's first pose and when the head goes stale."""
    r = ChainRunner(arm_scene(), frames=('arm',))
    a = P_STILL + ATTACH
    seen = 0
    for k in range(80):
        t = 10.0 + k / 100.0
        if k < 60:
            r.push(t, P_STILL + [0.0, 0.01 * math.sin(3 * t), 0.0], Q_ID, 'world')
        if k >= 5:
            r.push_frame(0, t, arm_path(t - 10.0, a), Q_ID, 'world')
        r.tick(t + 0.004)
        for tq in (t - 0.03, t, t + 0.02):
            banked = r.bodies_at(tq)
            bank, r._bank = r._bank, None
            own = r.bodies_at(tq)
            r._bank = bank
            seen += banked.n_bodies
            for name in ('position', 'orientation', 'linear_velocity', 'angular_velocity',
                         'linear_acceleration', 'angular_acceleration'):
                assert np.array_equal(getattr(banked, name), getattr(own, name)), (k, name)
    assert seen == 80 * 3 * 2


def base_values(**changes):
    values = {'chains': ['ponytail'], 'frames': ['arm'], 'colliders': ['box'],
              'box.kind': 'capsule', 'box.frame': 'arm', 'box.axis': [0.0, 1.0, 0.0],
              'box.half_length': 0.15, 'box.radius': 0.04}
    values.update({k.replace('__', '.'): v for k, v in changes.items()})
    return values


def test_frame_parameters_build_the_bodies_in_order_and_bad_values_are_named():
    values = complete_values(base_values(frames=['arm', 'leg'], ponytail__anchor='leg'))
    _, scene, _ = scene_and_settings(values)
    assert scene.n_kinematic_bodies == 3                        # head, arm, leg
    assert scene.chains[0].anchor_body == 2 and scene.colliders[0].body == 1
    assert values['arm.topic'] == '' and values['leg.topic'] == ''
    # A world anchor comes after the frames.
    values = complete_values(base_values(ponytail__anchor='world'))
    _, scene, _ = scene_and_settings(values)
    assert scene.n_kinematic_bodies == 3 and scene.chains[0].anchor_body == 2
    assert scene.colliders[0].body == 1

    bad = [
        (dict(ponytail__anchor='elbow'),
         r"ponytail\.anchor = 'elbow' is not allowed: must be one of head, world, arm"),
        (dict(box__frame='leg'),
         r"box\.frame = 'leg' is not allowed: must be one of head, world, arm"),
        (dict(frames=['ponytail']), r'chains and frames share the name'),
        (dict(frames=['box']), r'colliders and frames share the name'),
        (dict(frames=['head']), r"frames: 'head' is not a valid name"),
        (dict(frames=['arm', 'arm']), r'frames: duplicate names'),
        (dict(arm__topic='head_pose'), r'arm\.topic .*the head already reads'),
        (dict(frames=['arm', 'leg'], leg__topic='arm_pose'), r'leg\.topic .*frame arm'),
        (dict(arm__topic='bad topic'), r'arm\.topic .*ROS topic name'),
    ]
    for changes, message in bad:
        with pytest.raises(ParameterError, match=message):
            complete_values(base_values(**changes))


# -- in the node -------------------------------------------------------------------------------

rclpy = pytest.importorskip('rclpy')
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from ponytail_ros.node import PonytailNode  # noqa: E402
from ponytail_ros.recording.bag import BagReader  # noqa: E402
from ponytail_ros.recording.inputs import ReplayError  # noqa: E402
from ponytail_ros.recording.offline import replay  # noqa: E402
from ponytail_ros.recording.recorder import RECORDING_METADATA, RunLayout  # noqa: E402

from ros_helpers import Harness, arrays, diag_values, overrides, pose_msg, t_of  # noqa: E402

A = P_STILL + ATTACH            # the attachment point of the still head (identity rotation)


def arm_overrides(**values):
    # For a loaded test machine: 60 Hz ticks and 1/120 s steps (a third of the default CPU);
    # a stall of the executor of up to 2 s is bridged (the estimators interpolate across the
    # gap in the samples, every step is taken) instead of the forearm jumping across the chain
    # (frames have no teleport detection); an input is stale after 1 s without a pose.
    return overrides(**{'rate': 60.0, 'solver__dt': 1.0 / 120.0, 'head__max_gap': 2.0,
                        'solver__max_steps_per_call': 2400, 'stale_timeout': 1.0,
                        'frames': ['arm'], 'colliders': ['box'],
                        'box__kind': 'capsule', 'box__frame': 'arm',
                        'box__axis': [0.0, 1.0, 0.0], 'box__half_length': 0.15,
                        'box__radius': 0.04, **values})


def diag_until(h, pred, timeout=5.0):
    """The first /diagnostics status from now on whose values satisfy ``pred`` (input states
    may flicker on a loaded machine: wait for the one wanted), as ``(values, status)``."""
    start, found = len(h.diags), []

    def check():
        found[:] = [m for m in h.diags[start:] if pred(diag_values(m))][:1]
        return bool(found)
    assert h.spin_until(check, timeout), [diag_values(m) for m in h.diags[start:]][-3:]
    return diag_values(found[0]), found[0].status[0]


@pytest.fixture
def frames_harness(ros_context):
    made = []

    def make(params, arm_topic='arm_pose'):
        h = Harness(ros_context, params)
        h.arm = None                    # callable t -> position, published at 100 Hz when set
        h.arm_pub = h.tester.create_publisher(PoseStamped, arm_topic, 10)

        def publish_arm():
            if h.arm is not None:
                t = h.now()
                h.arm_pub.publish(pose_msg(t, h.arm(t), Q_ID))
        h.tester.create_timer(0.01, publish_arm)
        close = h.close
        h.closed = False

        def close_once():
            if not h.closed:
                h.closed = True
                close()
        h.close = close_once
        made.append(h)
        return h
    yield make
    for h in made:
        h.close()


def test_a_capsule_on_a_frame_topic_pushes_the_hanging_chain_aside(frames_harness):
    """A capsule collider fixed in frame ``arm`` (its pose on its own topic, here renamed
    ``forearm``) is swept across the chain hanging from a still head: the chain is pushed aside,
    no segment is ever deeper in it than TOLERANCE (the solver's measure after every tick), and
    the final published chain, measured independently against the held capsule, neither."""
    h = frames_harness(arm_overrides(arm__topic='forearm'), arm_topic='forearm')
    h.head = lambda t: (P_STILL, Q_ID, 'world')
    depths = []
    h.node.tick_hook = lambda out, *_: depths.append(
        float(h.node.runner.sim.contact_depths().max()))
    # The sweep's own clock advances at most 50 ms per published pose: if the test process
    # stalls (a loaded CI machine), the forearm's next pose would otherwise be up to the whole
    # sweep further on, and the node may tick before it arrives: the capsule would jump across
    # the chain in one tick (frames have no teleport detection), which is not this test's scene.
    sweep = {'s': 0.0, 'last': None, 'still_since': None}

    def arm(t):
        if sweep['last'] is not None:
            sweep['s'] += min(t - sweep['last'], 0.05)   # the forearm moves <= 19 mm per pose
        sweep['last'] = t
        if sweep['s'] >= 2.3 and sweep['still_since'] is None:
            sweep['still_since'] = t          # the forearm has been still for a second
        return arm_path(sweep['s'], A)
    h.arm = arm
    got = h.poses['segment_poses']
    # Until a tick after the forearm has been still for a second.
    assert h.spin_until(lambda: got and sweep['still_since'] is not None
                        and t_of(got[-1].header) > sweep['still_since'], 30.0)
    assert h.node.runner.resets['guard'] == 0 and sum(h.node.runner.dropped.values()) == 0
    assert max(depths) < TOLERANCE
    assert max(depths) > -1e-3                                   # it did touch
    o, q = arrays(got[-1])
    depth = capsule_depths(o, q, 0.05, 0.03, arm_path(10.0, A), [0.0, 1.0, 0.0], 0.15, 0.04)
    assert depth.max() < TOLERANCE
    assert o[-1, 0] < A[0] - 0.05                                # pushed aside (in -x)
    assert np.linalg.norm(o[0] - A) < 1e-6                       # still on the head
    d, _ = diag_until(h, lambda d: d['frame arm'] == 'ok', timeout=20.0)
    assert int(d['frame arm poses accepted']) > 5
    assert h.node._input_topics['arm'] == '/forearm'


def test_nothing_is_published_until_the_frame_has_a_pose_and_the_warning_names_it(
        frames_harness):
    h = frames_harness(arm_overrides(frames=['arm', 'spare']))
    logs = []
    h.node._log_throttled = lambda key, period, level, text: logs.append(text)
    got = h.poses['segment_poses']
    h.spin_for(0.3)
    assert any('/head_pose, /arm_pose' in text and 'nothing is published' in text
               for text in logs)
    h.head = lambda t: (P_STILL, Q_ID, 'world')
    assert h.spin_until(lambda: h.node.runner.has_head, 5.0)
    logs.clear()
    h.spin_for(0.5)
    assert not got
    assert logs and all('No pose received on /arm_pose yet: nothing is published' == text
                        for text in logs)
    d, status = diag_until(h, lambda d: d['head'] == 'ok')
    assert (d['head'], d['frame arm'], d['frame spare']) == ('ok', 'none', 'none')
    assert 'no pose received for frame arm (arm_pose)' in status.message
    assert 'spare' not in status.message                         # not used by the scene

    h.arm = lambda t: arm_path(0.0, A)
    assert h.spin_until(lambda: len(got) >= 10, 5.0)
    d, status = diag_until(h, lambda d: d['frame arm'] == 'ok' and d['head'] == 'ok')
    assert d['frame spare'] == 'none' and 'frame' not in status.message
    # The spare frame is still at the origin, the world body absent.
    runner_now = lambda: h.node.runner.seconds(round(h.now() * 1e9))  # noqa: E731
    assert h.node.runner.bodies_at(runner_now()).n_bodies == 3

    h.arm = None                                                 # the forearm goes stale
    assert h.spin_until(lambda: h.node.runner.frame_stale(0, runner_now()), 5.0)
    n = len(got)
    assert h.spin_until(lambda: len(got) > n + 10, 5.0)         # held, still publishing
    d = h.fresh_diag()
    assert d['frame arm'] == 'stale' and 'frame arm pose stale' in h.diags[-1].status[0].message
    assert any(text.startswith('Frame arm pose stale on /arm_pose') for text in logs)


def test_bad_frame_values_are_rejected_naming_the_parameter(ros_context):
    def make(**values):
        return PonytailNode(context=ros_context, parameter_overrides=arm_overrides(**values))
    with pytest.raises(ParameterError, match=r"ponytail\.anchor = 'elbow' is not allowed: must "
                                             r"be one of head, world, arm"):
        make(ponytail__anchor='elbow')
    with pytest.raises(ParameterError, match=r"box\.frame = 'leg' is not allowed: must be one "
                                             r"of head, world, arm"):
        make(box__frame='leg')
    with pytest.raises(ParameterError, match=r'chains and frames share the name'):
        make(frames=['ponytail'])
    with pytest.raises(ParameterError, match=r'arm\.topic .*resolves to /head_pose'):
        make(arm__topic='/head_pose')

    node = make()
    try:
        (frames,) = [p.value for p in node.get_parameters(['frames'])]
        assert list(frames) == ['arm']
        desc = node.describe_parameters(['box.frame', 'ponytail.anchor', 'arm.topic'])
        assert all('one of: head, world, arm' in d.additional_constraints for d in desc[:2])
        assert desc[2].read_only
        results = node.set_parameters([Parameter('box.frame', value='leg'),
                                       Parameter('ponytail.anchor', value='elbow'),
                                       Parameter('frames', value=['arm', 'leg']),
                                       Parameter('arm.topic', value='elsewhere')])
        assert not any(r.successful for r in results)
        assert 'box.frame' in results[0].reason and 'head, world, arm' in results[0].reason
        assert 'ponytail.anchor' in results[1].reason
        assert node.core.values['box.frame'] == 'arm' and node.core.frame_topics == ['arm_pose']
        # A good live change: the chain now hangs from the forearm (rebuilt).
        (ok,) = node.set_parameters([Parameter('ponytail.anchor', value='arm')])
        assert ok.successful and node.core.scene.chains[0].anchor_body == 1
    finally:
        node.destroy_node()


def pose_messages(path, topic, type_name='geometry_msgs/msg/PoseArray'):
    return [(m, log) for t, _, m, log in BagReader(path).messages({topic: type_name})
            if t == topic]


def test_a_recording_with_a_frame_replays_bit_for_bit(frames_harness, tmp_path):
    """Head and forearm both moving, one NaN forearm pose: the replay pushes the recorded
    forearm poses as the node did and reproduces every tick's poses and markers exactly, byte
    for byte on a second replay; the layout names the frame and its topic."""
    path = tmp_path / 'run.mcap'
    # (every tick bounded, 0.5 s of steps: a loaded machine drops time rather than falling
    # further behind; the replay reproduces that too)
    h = frames_harness(arm_overrides(record_path=str(path), markers__rate=1000.0,
                                     solver__max_steps_per_call=60))
    t0 = h.now()
    h.head = lambda t: (P_STILL + [0.03 * math.sin(4.0 * (t - t0)), 0.0, 0.0], Q_ID, 'world')
    h.arm = lambda t: arm_path(t - t0, A, start=0.2, duration=0.8)
    got = h.poses['segment_poses']
    assert h.spin_until(lambda: got and t_of(got[-1].header) > t0 + 0.5, 10.0)
    h.arm_pub.publish(pose_msg(h.now(), [math.nan, 0.0, 0.0], Q_ID))
    assert h.spin_until(lambda: h.node.runner.dropped['nonfinite'] == 1, 5.0)
    assert h.spin_until(lambda: t_of(got[-1].header) > t0 + 1.5 and len(got) >= 20, 10.0)
    h.close()                                                    # finalises the recording

    meta = BagReader(path).metadata()[RECORDING_METADATA]
    layout = RunLayout.from_metadata(meta)
    assert layout.frames == ('arm',) and layout.frame_topics == ('/arm_pose',)
    assert BagReader(path).topics()['/arm_pose'] == 'geometry_msgs/msg/PoseStamped'
    arm_in = pose_messages(path, '/arm_pose', 'geometry_msgs/msg/PoseStamped')
    assert len(arm_in) > 10

    out = tmp_path / 'replayed.mcap'
    result = replay(path, out)
    assert result.tick_mode == 'recorded' and result.frame_samples == len(arm_in)
    live, again = pose_messages(path, '/segment_poses'), pose_messages(out, '/segment_poses')
    assert len(live) >= 20 and [m for m, _ in again] == [m for m, _ in live]
    assert [m for m, _ in pose_messages(out, '/segment_markers',
                                        'visualization_msgs/msg/MarkerArray')] == \
        [m for m, _ in pose_messages(path, '/segment_markers',
                                     'visualization_msgs/msg/MarkerArray')]
    assert [(repr(m), t) for m, t in pose_messages(out, '/arm_pose',
                                                   'geometry_msgs/msg/PoseStamped')] == \
        [(repr(m), t) for m, t in arm_in]
    assert RunLayout.from_metadata(BagReader(out).metadata()[RECORDING_METADATA]) == layout
    first = out.read_bytes()
    replay(path, out, overwrite=True)
    assert out.read_bytes() == first
    # Look-ahead (head and frame estimators replaced by SplineHeadEstimator) runs too.
    ahead = replay(path, tmp_path / 'ahead.mcap', look_ahead=True)
    assert ahead.frame_samples == len(arm_in) and ahead.ticks >= 20
    assert all(math.isfinite(v) for m, _ in pose_messages(tmp_path / 'ahead.mcap',
                                                          '/segment_poses')
               for pose in m.poses for v in (pose.position.x, pose.position.y,
                                             pose.position.z))

    # A scene that uses a frame the recording does not have cannot be replayed from it.
    params = tmp_path / 'elbow.yaml'
    params.write_text('/**:\n  ros__parameters:\n    frames: [elbow]\n    colliders: [box]\n'
                      '    box: {frame: elbow}\n')
    with pytest.raises(ReplayError, match=r'no topic /elbow_pose \(the poses of frame elbow'):
        replay(path, tmp_path / 'elbow.mcap', params_file=params)


def test_ponytail_arm_config_puts_a_capsule_on_the_left_forearm():
    values = complete_values(values_from_params_file(config_path('ponytail_arm.yaml')))
    _, scene, _ = scene_and_settings(values)
    assert values['frames'] == ['left_forearm']
    assert (values['left_forearm.topic'] or 'left_forearm_pose') == 'left_forearm_pose'
    assert scene.n_kinematic_bodies == 2
    assert [(c.kind, c.body) for c in scene.colliders] == [('sphere', 0), ('capsule', 1)]
