"""The head from TF in ``ponytail_replay``: a bag with only ``/tf`` and ``/tf_static`` (written
by rosbags, which knows tf2_msgs' types without tf2_msgs) replays to the same segment poses at
the same stamps as the same motion given as ``PoseStamped``; errors name the frames."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip('rclpy')

from ponytail_ros.recording.inputs import ReplayError  # noqa: E402
from ponytail_ros.recording.offline import replay  # noqa: E402

from ros_helpers import poses_by_stamp  # noqa: E402

pytestmark = pytest.mark.ros

T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 10_000_000                # 100 Hz
N = 150
NECK = ((0.05, 0.0, 0.4), Rotation.from_rotvec([0.0, 0.1, 0.0]).as_quat())
PARAMS = """/**:
  ros__parameters:
    rate: 100.0
    fixed_frame: {fixed}
    head_frame: '{head}'
    ponytail:
      n_segments: 4
"""


def _base(t):
    """world -> base_link: walking along x, yawing."""
    return ((0.3 * t, 0.05 * math.sin(2 * t), 1.0),
            Rotation.from_rotvec([0.0, 0.0, 0.4 * math.sin(1.5 * t)]).as_quat())


def _head(t):
    """neck -> head: nodding and a little bob."""
    return ((0.0, 0.0, 0.1 + 0.01 * math.sin(5 * t)),
            Rotation.from_rotvec([0.0, 0.3 * math.sin(3 * t), 0.1 * math.cos(2 * t)]).as_quat())


def _hand(t):
    """base_link -> hand: an arm swinging."""
    return ((0.2, -0.3 + 0.1 * math.sin(4 * t), 0.3),
            Rotation.from_rotvec([0.5 * math.sin(4 * t), 0.0, 0.2]).as_quat())


def _compose(*poses):
    """The poses composed by rotation matrices (the test's own arithmetic)."""
    m = np.eye(4)
    for t, q in poses:
        e = np.eye(4)
        e[:3, :3] = Rotation.from_quat(q).as_matrix()
        e[:3, 3] = t
        m = m @ e
    return m[:3, 3], Rotation.from_matrix(m[:3, :3]).as_quat()


class _Messages:
    """Messages serialised by rosbags' ros2 typestore (tf2_msgs' types without tf2_msgs)."""

    def __init__(self):
        from rosbags.typesys import Stores, get_typestore
        self.ts = get_typestore(Stores.ROS2_KILTED)
        self.T = self.ts.types

    def header(self, stamp, frame):
        T = self.T
        return T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
            sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=frame)

    def transform(self, stamp, parent, child, pose):
        (x, y, z), (qx, qy, qz, qw) = pose
        T = self.T
        return T['geometry_msgs/msg/TransformStamped'](
            header=self.header(stamp, parent), child_frame_id=child,
            transform=T['geometry_msgs/msg/Transform'](
                translation=T['geometry_msgs/msg/Vector3'](x=x, y=y, z=z),
                rotation=T['geometry_msgs/msg/Quaternion'](x=qx, y=qy, z=qz, w=qw)))

    def tf(self, stamp, parent, child, pose):
        return self.ts.serialize_cdr(self.T['tf2_msgs/msg/TFMessage'](
            transforms=[self.transform(stamp, parent, child, pose)]), 'tf2_msgs/msg/TFMessage')

    def pose_stamped(self, stamp, pose):
        (x, y, z), (qx, qy, qz, qw) = pose
        T = self.T
        return self.ts.serialize_cdr(T['geometry_msgs/msg/PoseStamped'](
            header=self.header(stamp, 'world'),
            pose=T['geometry_msgs/msg/Pose'](
                position=T['geometry_msgs/msg/Point'](x=x, y=y, z=z),
                orientation=T['geometry_msgs/msg/Quaternion'](x=qx, y=qy, z=qz, w=qw))),
            'geometry_msgs/msg/PoseStamped')


def _write(tmp_path, name, tf=True, arm=False):
    """The motion as a TF-only bag (head stamps = the moving edges' stamps; the static edge
    once, first) or as PoseStamped on /head_pose (the head composed by hand), same log times;
    ``arm``: an arm too, base_link -> hand on TF or its pose composed by hand on /arm_pose."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    m = _Messages()
    ts = m.ts
    folder = tmp_path / name
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        pose_type = 'geometry_msgs/msg/PoseStamped'
        if tf:
            dynamic = w.add_connection('/tf', 'tf2_msgs/msg/TFMessage', typestore=ts)
            static = w.add_connection('/tf_static', 'tf2_msgs/msg/TFMessage', typestore=ts)
            w.write(static, T0_NS, m.tf(T0_NS, 'base_link', 'neck', NECK))
        else:
            head = w.add_connection('/head_pose', pose_type, typestore=ts)
            arm_pose = w.add_connection('/arm_pose', pose_type, typestore=ts) if arm else None
        for i in range(N):
            stamp = T0_NS + i * PERIOD_NS
            t = i * PERIOD_NS * 1e-9
            log = stamp + 2_000_000
            if tf:
                # the moving edges in separate messages, as separate publishers send them
                w.write(dynamic, log, m.tf(stamp, 'world', 'base_link', _base(t)))
                if arm:
                    w.write(dynamic, log + 500, m.tf(stamp, 'base_link', 'hand', _hand(t)))
                w.write(dynamic, log + 1000, m.tf(stamp, 'neck', 'head', _head(t)))
                continue
            if arm_pose is not None:
                w.write(arm_pose, log + 500, m.pose_stamped(stamp, _compose(_base(t), _hand(t))))
            w.write(head, log + 1000, m.pose_stamped(stamp, _compose(_base(t), NECK, _head(t))))
    (path,) = folder.glob('*.mcap')
    return path


def _params(tmp_path, head='', fixed='world', arm=None):
    """``arm``: an extra frame ``arm`` the chain hangs from, its tf_frame ``arm`` ('': from
    its topic, arm_pose)."""
    path = tmp_path / f'params_{head or "topic"}_{fixed}_{arm}.yaml'
    text = PARAMS.format(head=head, fixed=fixed)
    if arm is not None:
        text = text.replace('    ponytail:\n', f"    frames: [arm]\n    arm:\n"
                                               f"      tf_frame: '{arm}'\n    ponytail:\n"
                                               f"      anchor: arm\n")
    path.write_text(text)
    return path


def _same_poses(a, b):
    """The two replays' segment poses, at the same stamps, within 1e-6 m."""
    pa, pb = poses_by_stamp(a.output), poses_by_stamp(b.output)
    assert sorted(pa) == sorted(pb)
    worst = 0.0
    for stamp in pb:
        assert pa[stamp].header.frame_id == pb[stamp].header.frame_id == 'world'
        for x, y in zip(pa[stamp].poses, pb[stamp].poses, strict=True):
            worst = max(worst, math.dist((x.position.x, x.position.y, x.position.z),
                                         (y.position.x, y.position.y, y.position.z)))
    assert worst <= 1e-6


def test_a_tf_only_bag_replays_as_the_same_motion_on_head_pose(tmp_path):
    tf_bag, pose_bag = _write(tmp_path, 'tf'), _write(tmp_path, 'pose', tf=False)
    a = replay(tf_bag, tmp_path / 'a.mcap', params_file=_params(tmp_path, 'head'))
    b = replay(pose_bag, tmp_path / 'b.mcap', params_file=_params(tmp_path))
    assert a.head_samples == b.head_samples == N
    assert a.ticks == b.ticks > 100
    _same_poses(a, b)
    # the head it composed is recorded on head_pose, in fixed_frame, at the edges' stamps
    heads = poses_by_stamp(a.output, '/head_pose')
    assert sorted(heads) == [T0_NS + i * PERIOD_NS for i in range(N)]
    t = 7 * PERIOD_NS * 1e-9
    p, _ = _compose(_base(t), NECK, _head(t))
    h = heads[T0_NS + 7 * PERIOD_NS]
    assert h.header.frame_id == 'world'
    assert math.dist((h.pose.position.x, h.pose.position.y, h.pose.position.z), p) < 1e-12


def test_tf_head_errors_name_the_frames(tmp_path):
    tf_bag = _write(tmp_path, 'tf')
    with pytest.raises(ReplayError, match="holds tf2_msgs/msg/TFMessage.*head_frame"):
        replay(tf_bag, tmp_path / 'x.mcap', params_file=_params(tmp_path),
               head_topic='/tf')
    with pytest.raises(ReplayError, match="no topic /head_pose.*head_frame"):
        replay(tf_bag, tmp_path / 'x.mcap', params_file=_params(tmp_path))
    with pytest.raises(ReplayError, match="no head pose from TF \\(world -> nose\\): frame "
                                          "'nose' has not appeared.*base_link, head, neck"):
        replay(tf_bag, tmp_path / 'x.mcap', params_file=_params(tmp_path, 'nose'))
    with pytest.raises(ReplayError, match="no head pose from TF \\(odom -> head\\): frame "
                                          "'odom' has not appeared"):
        replay(tf_bag, tmp_path / 'x.mcap', params_file=_params(tmp_path, 'head', 'odom'))
    assert not (tmp_path / 'x.mcap').exists()


def test_an_extra_frame_from_tf_replays_as_its_pose_topic(tmp_path):
    """A chain hanging from an arm whose pose is on TF (arm.tf_frame: hand) moves as with the
    arm's pose given on its topic."""
    tf_bag, pose_bag = _write(tmp_path, 'tf', arm=True), _write(tmp_path, 'pose', False, True)
    a = replay(tf_bag, tmp_path / 'a.mcap', params_file=_params(tmp_path, 'head', arm='hand'))
    b = replay(pose_bag, tmp_path / 'b.mcap', params_file=_params(tmp_path, arm=''))
    assert a.frame_samples == b.frame_samples == N
    assert a.ticks == b.ticks > 100
    _same_poses(a, b)
    arm = poses_by_stamp(a.output, '/arm_pose')           # recorded on its topic
    assert len(arm) == N and arm[T0_NS].header.frame_id == 'world'


def test_the_command_line_takes_the_head_frame(tmp_path, capsys):
    """``ponytail_replay BAG --head-frame head`` is the params file's ``head_frame: head``."""
    from ponytail_ros.recording.cli import main
    tf_bag = _write(tmp_path, 'tf')
    a = replay(tf_bag, tmp_path / 'a.mcap', params_file=_params(tmp_path, 'head'))
    assert main([str(tf_bag), '-o', str(tmp_path / 'b.mcap'), '-q', '--head-frame', 'head',
                 '--fixed-frame', 'world', '--params', str(_params(tmp_path))]) == 0
    pa, pb = poses_by_stamp(a.output), poses_by_stamp(tmp_path / 'b.mcap')
    assert sorted(pa) == sorted(pb) and len(pb) > 100
    assert all(pa[s].poses == pb[s].poses for s in pb)
    assert main([str(tf_bag), '-o', str(tmp_path / 'c.mcap'), '-q', '--head-frame', 'nose',
                 '--params', str(_params(tmp_path))]) == 2
    assert "frame 'nose' has not appeared" in capsys.readouterr().err
