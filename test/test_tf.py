"""Segments as TF frames: ``tf2_msgs/msg/TFMessage`` on ``/tf``, written without tf2_msgs.

Checked against rosbags' independent CDR serialiser, type hash and reader (which decodes with
the schema text stored in the file).
"""
import numpy as np
import pytest

pytest.importorskip('rclpy')
highlevel = pytest.importorskip('rosbags.highlevel')
typesys = pytest.importorskip('rosbags.typesys')

from ponytail_ros.recording.tf import TFMESSAGE_TYPE, tf_message_cdr, tfmessage_type_hash  # noqa: E402

from ros_helpers import head_samples, rosbags_bag, run  # noqa: E402

STORE = typesys.get_typestore(typesys.Stores.ROS2_KILTED)


def test_tf_cdr_is_byte_for_byte_rosbags_serialisation():
    tm = STORE.types
    transforms = [
        (1700000000, 123456789, 'world', 'ponytail/0', (0.1, -0.2, 1.6), (0.0, 0.0, 0.6, 0.8)),
        (1700000000, 123456789, 'world', 'chain_long_name/11', (1e-300, 3.0, -4.5),
         (0.5, 0.5, 0.5, 0.5)),
        (0, 0, 'w', 'c/2', (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
    ]
    msg = tm[TFMESSAGE_TYPE](transforms=[
        tm['geometry_msgs/msg/TransformStamped'](
            header=tm['std_msgs/msg/Header'](
                stamp=tm['builtin_interfaces/msg/Time'](sec=s, nanosec=ns), frame_id=parent),
            child_frame_id=child,
            transform=tm['geometry_msgs/msg/Transform'](
                translation=tm['geometry_msgs/msg/Vector3'](x=t[0], y=t[1], z=t[2]),
                rotation=tm['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3])))
        for s, ns, parent, child, t, q in transforms])
    assert tf_message_cdr(transforms) == bytes(STORE.serialize_cdr(msg, TFMESSAGE_TYPE))
    assert tf_message_cdr([]) == bytes(STORE.serialize_cdr(tm[TFMESSAGE_TYPE](transforms=[]),
                                                           TFMESSAGE_TYPE))


def test_tfmessage_type_hash_is_rosidls():
    assert tfmessage_type_hash() == STORE.hash_rihs01(TFMESSAGE_TYPE)


def tf_and_arrays(path):
    with highlevel.AnyReader([path]) as reader:   # types from the schemas in the file
        out = {}
        for c, log, raw in reader.messages():
            out.setdefault(c.topic, []).append((log, reader.deserialize(raw, c.msgtype)))
    return out


@pytest.mark.parametrize('prefix', [None, 'alice/'])
def test_replay_output_has_every_segment_as_a_frame_matching_its_pose_to_1e_12(
        tmp_path, params, capsys, prefix):  # noqa: F811
    bag = rosbags_bag(tmp_path, 'in', head_samples(150))
    out = tmp_path / 'out.mcap'
    extra = [] if prefix is None else ['--tf-prefix', prefix]
    code, _, err = run([bag, '-o', out, '--params', params] + extra, capsys)
    assert code == 0, err
    got = tf_and_arrays(out)
    tf, arrays = got['/tf'], got['/segment_poses']
    assert len(tf) == len(arrays) >= 100
    for (log_tf, frames), (log_pa, array) in zip(tf, arrays, strict=True):
        assert log_tf == log_pa
        assert len(frames.transforms) == len(array.poses) == 4
        for i, (tr, pose) in enumerate(zip(frames.transforms, array.poses, strict=True)):
            assert tr.header.frame_id == array.header.frame_id == 'world'
            assert (tr.header.stamp.sec, tr.header.stamp.nanosec) == (
                array.header.stamp.sec, array.header.stamp.nanosec)
            assert tr.child_frame_id == f'{prefix or ""}ponytail/{i}'
            t, r = tr.transform.translation, tr.transform.rotation
            p, q = pose.position, pose.orientation
            assert np.max(np.abs(np.subtract([t.x, t.y, t.z, r.x, r.y, r.z, r.w],
                                             [p.x, p.y, p.z, q.x, q.y, q.z, q.w]))) <= 1e-12


def test_no_tf_leaves_it_out(tmp_path, params, capsys):  # noqa: F811
    bag = rosbags_bag(tmp_path, 'in', head_samples(50))
    out = tmp_path / 'out.mcap'
    code, _, err = run([bag, '-o', out, '--params', params, '--no-tf'], capsys)
    assert code == 0, err
    got = tf_and_arrays(out)
    assert '/tf' not in got and len(got['/segment_poses']) > 10
