"""The head from TF in ``ponytail_replay``: a bag with only ``/tf`` and ``/tf_static`` (written
by rosbags, which knows tf2_msgs' types without tf2_msgs) replays to the same segment poses at
the same stamps as the same motion given as ``PoseStamped``; errors name the frames."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip('rclpy')

from ros_helpers import poses_by_stamp  # noqa: E402
from ponytail_ros.recording.inputs import ReplayError  # noqa: E402
from ponytail_ros.recording.offline import replay  # noqa: E402

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


def _compose(*poses):
    """The poses composed by rotation matrices (the test's own arithmetic)."""
    m = np.eye(4)
    for t, q in poses:
        e = np.eye(4)
        e[:3, :3] = Rotation.from_quat(q).as_matrix()
        e[:3, 3] = t
        m = m @ e
    return m[:3, 3], Rotation.from_matrix(m[:3, :3]).as_quat()


def _write(tmp_path, name, tf=True):
    """The motion as a TF-only bag (head stamps = the moving edges' stamps; the static edge
    once, first) or as PoseStamped on /head_pose (the head composed by hand), same log times."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_KILTED)
    T = ts.types

    def header(stamp, frame):
        return T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
            sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=frame)

    def transform(stamp, parent, child, pose):
        (x, y, z), (qx, qy, qz, qw) = pose
        return T['geometry_msgs/msg/TransformStamped'](
            header=header(stamp, parent), child_frame_id=child,
            transform=T['geometry_msgs/msg/Transform'](
                translation=T['geometry_msgs/msg/Vector3'](x=x, y=y, z=z),
                rotation=T['geometry_msgs/msg/Quaternion'](x=qx, y=qy, z=qz, w=qw)))

    def tf_message(*transforms):
        return ts.serialize_cdr(T['tf2_msgs/msg/TFMessage'](transforms=list(transforms)),
                                'tf2_msgs/msg/TFMessage')
    folder = tmp_path / name
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        if tf:
            dynamic = w.add_connection('/tf', 'tf2_msgs/msg/TFMessage', typestore=ts)
            static = w.add_connection('/tf_static', 'tf2_msgs/msg/TFMessage', typestore=ts)
            w.write(static, T0_NS, tf_message(transform(T0_NS, 'base_link', 'neck', NECK)))
        else:
            head = w.add_connection('/head_pose', 'geometry_msgs/msg/PoseStamped', typestore=ts)
        for i in range(N):
            stamp = T0_NS + i * PERIOD_NS
            t = i * PERIOD_NS * 1e-9
            log = stamp + 2_000_000
            if tf:
                # the two moving edges in separate messages, as two publishers would send them
                w.write(dynamic, log, tf_message(transform(stamp, 'world', 'base_link',
                                                           _base(t))))
                w.write(dynamic, log + 1000, tf_message(transform(stamp, 'neck', 'head',
                                                                  _head(t))))
            else:
                (x, y, z), (qx, qy, qz, qw) = _compose(_base(t), NECK, _head(t))
                msg = T['geometry_msgs/msg/PoseStamped'](
                    header=header(stamp, 'world'),
                    pose=T['geometry_msgs/msg/Pose'](
                        position=T['geometry_msgs/msg/Point'](x=x, y=y, z=z),
                        orientation=T['geometry_msgs/msg/Quaternion'](x=qx, y=qy, z=qz, w=qw)))
                w.write(head, log + 1000, ts.serialize_cdr(msg, 'geometry_msgs/msg/PoseStamped'))
    (path,) = folder.glob('*.mcap')
    return path


def _params(tmp_path, head='', fixed='world'):
    path = tmp_path / f'params_{head or "topic"}_{fixed}.yaml'
    path.write_text(PARAMS.format(head=head, fixed=fixed))
    return path


def test_a_tf_only_bag_replays_as_the_same_motion_on_head_pose(tmp_path):
    tf_bag, pose_bag = _write(tmp_path, 'tf'), _write(tmp_path, 'pose', tf=False)
    a = replay(tf_bag, tmp_path / 'a.mcap', params_file=_params(tmp_path, 'head'))
    b = replay(pose_bag, tmp_path / 'b.mcap', params_file=_params(tmp_path))
    assert a.head_samples == b.head_samples == N
    assert a.ticks == b.ticks > 100
    pa, pb = poses_by_stamp(a.output), poses_by_stamp(b.output)
    assert sorted(pa) == sorted(pb)
    worst = 0.0
    for stamp in pb:
        assert pa[stamp].header.frame_id == pb[stamp].header.frame_id == 'world'
        for x, y in zip(pa[stamp].poses, pb[stamp].poses):
            worst = max(worst, math.dist((x.position.x, x.position.y, x.position.z),
                                         (y.position.x, y.position.y, y.position.z)))
    assert worst <= 1e-6
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
