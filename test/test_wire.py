"""The segment poses as CDR laid out with NumPy (``app/wire.py``), byte for byte the ROS
serialisers' output.

``PoseArray`` against rclpy's ``serialize_message`` (rmw_fastrtps): the same length, the same
bytes outside the alignment gaps (Fast CDR leaves those unwritten, so they hold heap bytes),
exactly its canonical form (gaps zeroed, ``recording/cdr.py``), and rclpy decodes it back to
the message. ``TFMessage`` (no ``tf2_msgs`` among the wheels) against rosbags' independent CDR
serialiser and ``recording/tf.py``'s hand-written one. Random poses (NaN, infinities, -0.0
included), stamps over the whole ``int32``/``uint32`` range, frame names of every length modulo
4 (the alignment) and of several UTF-8 widths, 0, 1 and many poses.
"""
import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

pytest.importorskip('rclpy')
from builtin_interfaces.msg import Time  # noqa: E402
from geometry_msgs.msg import Pose, PoseArray  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from ponytail_ros.app.messages import SegmentPoses, segment_frame, tf_cdr  # noqa: E402
from ponytail_ros.app.wire import pose_array_cdr, pose_array_layout, pose_block, tf_layout  # noqa: E402
from ponytail_ros.recording.cdr import serialize_canonical  # noqa: E402
from ponytail_ros.recording.tf import TFMESSAGE_TYPE, tf_message_cdr  # noqa: E402

FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)
FINITE = st.floats(allow_nan=False, allow_infinity=False, width=64)
FRAMES = st.text(alphabet=st.sampled_from('aZ_/09é€'), max_size=13)
SEC = st.integers(-2**31, 2**31 - 1)
NANOSEC = st.integers(0, 2**32 - 1)


def poses_of(n, floats):
    return st.lists(st.lists(floats, min_size=7, max_size=7), min_size=n, max_size=n).map(
        lambda rows: np.array(rows, dtype=float).reshape(n, 7))


def counts():
    return st.one_of(st.just(0), st.just(1), st.integers(2, 40))


def pose_array(block, sec, nanosec, frame_id):
    msg = PoseArray()
    msg.header.frame_id = frame_id
    msg.header.stamp = Time(sec=sec, nanosec=nanosec)
    poses = []
    for row in block.tolist():
        p = Pose()
        p.position.x, p.position.y, p.position.z = row[:3]
        o = p.orientation
        o.x, o.y, o.z, o.w = row[3:]
        poses.append(p)
    msg.poses = poses
    return msg


def gaps(frame_id, n):
    """Byte positions of the alignment gaps of a ``PoseArray`` (absolute, header included)."""
    end = 4 + 8 + 4 + len(frame_id.encode('utf-8')) + 1     # after the frame's NUL
    count = end + (-(end - 4)) % 4
    out = set(range(end, count))
    after = count + 4
    if n:
        out |= set(range(after, after + (-(after - 4)) % 8))
    return out


@settings(max_examples=300, deadline=None)
@given(data=st.data(), n=counts(), frame_id=FRAMES, sec=SEC, nanosec=NANOSEC)
def test_pose_array_is_serialize_messages_bytes(data, n, frame_id, sec, nanosec):
    block = data.draw(poses_of(n, FLOATS))
    ours = pose_array_cdr(block[:, :3], block[:, 3:], sec, nanosec, frame_id)
    msg = pose_array(block, sec, nanosec, frame_id)
    raw = serialize_message(msg)
    assert len(ours) == len(raw) == pose_array_layout(frame_id, n).size
    skip = gaps(frame_id, n)
    assert all(ours[i] == raw[i] for i in range(len(raw)) if i not in skip)
    assert all(ours[i] == 0 for i in skip)
    assert ours == serialize_canonical(msg)


@settings(max_examples=100, deadline=None)
@given(data=st.data(), n=counts(), frame_id=FRAMES, sec=SEC, nanosec=NANOSEC)
def test_pose_array_decodes_to_the_message(data, n, frame_id, sec, nanosec):
    block = data.draw(poses_of(n, FINITE))
    ours = pose_array_cdr(block[:, :3], block[:, 3:], sec, nanosec, frame_id)
    msg = pose_array(block, sec, nanosec, frame_id)
    assert deserialize_message(ours, PoseArray) == msg
    layout = pose_array_layout(frame_id, n)
    assert np.array_equal(layout.poses(ours), block)


@settings(max_examples=100, deadline=None)
@given(data=st.data(), n=counts(), frame_id=FRAMES, chain=FRAMES.filter(bool),
       stamp_ns=st.integers(-2**62, 2**62))
def test_segment_poses_message_and_arrays_are_its_bytes(data, n, frame_id, chain, stamp_ns):
    stamp_ns = max(min(stamp_ns, (2**31 - 1) * 10**9), -2**31 * 10**9)
    block = data.draw(poses_of(n, FINITE))
    s = SegmentPoses(chain, block[:, :3], block[:, 3:], frame_id, stamp_ns)
    msg = s.message()
    assert serialize_canonical(msg) == s.cdr
    assert s.message() is msg                         # built once
    assert (msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec) == stamp_ns
    assert np.array_equal(s.origins, block[:, :3]) and np.array_equal(s.orientations,
                                                                       block[:, 3:])
    assert not s.poses.flags.writeable


def test_bit_patterns_survive_nan_negative_zero_and_subnormals():
    block = np.array([[-0.0, math.nan, math.inf, -math.inf, 5e-324, -1e308, 1.0]])
    data = pose_array_cdr(block[:, :3], block[:, 3:], 0, 0, 'w')
    got = pose_array_layout('w', 1).poses(data)
    assert got.tobytes() == pose_block(block[:, :3], block[:, 3:]).astype('<f8').tobytes()


def test_a_wrong_shape_is_refused():
    with pytest.raises(ValueError, match='shape'):
        pose_array_layout('w', 3).encode(0, 0, np.zeros((2, 7)))
    with pytest.raises(ValueError, match='shape'):
        tf_layout('w', ('a', 'b')).encode(0, 0, np.zeros((3, 7)))


@settings(max_examples=200, deadline=None)
@given(data=st.data(), n=counts(), parent=FRAMES, prefix=FRAMES, chain=FRAMES.filter(bool),
       sec=SEC, nanosec=NANOSEC)
def test_tf_message_is_the_hand_written_and_rosbags_serialisation(data, n, parent, prefix,
                                                                  chain, sec, nanosec):
    typesys = pytest.importorskip('rosbags.typesys')
    store = typesys.get_typestore(typesys.Stores.ROS2_KILTED)
    tm = store.types
    block = data.draw(poses_of(n, FLOATS))
    children = tuple(segment_frame(prefix, chain, i) for i in range(n))
    ours = tf_layout(parent, children).encode(sec, nanosec, block)
    rows = block.tolist()
    assert ours == tf_message_cdr((sec, nanosec, parent, c, r[:3], r[3:])
                                  for c, r in zip(children, rows, strict=True))
    msg = tm[TFMESSAGE_TYPE](transforms=[
        tm['geometry_msgs/msg/TransformStamped'](
            header=tm['std_msgs/msg/Header'](
                stamp=tm['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec),
                frame_id=parent),
            child_frame_id=c,
            transform=tm['geometry_msgs/msg/Transform'](
                translation=tm['geometry_msgs/msg/Vector3'](x=r[0], y=r[1], z=r[2]),
                rotation=tm['geometry_msgs/msg/Quaternion'](x=r[3], y=r[4], z=r[5], w=r[6])))
        for c, r in zip(children, rows, strict=True)])
    assert ours == bytes(store.serialize_cdr(msg, TFMESSAGE_TYPE))


def test_tf_of_several_chains_is_one_message_chain_after_chain():
    rng = np.random.default_rng(0)
    a = SegmentPoses('left', rng.normal(size=(3, 3)), rng.normal(size=(3, 4)), 'head', 7)
    b = SegmentPoses('right', rng.normal(size=(2, 3)), rng.normal(size=(2, 4)), 'head', 7)
    rows = np.concatenate([a.poses, b.poses]).tolist()
    names = ['p/left/0', 'p/left/1', 'p/left/2', 'p/right/0', 'p/right/1']
    assert tf_cdr([a, b], 'p/') == tf_message_cdr((0, 7, 'head', c, r[:3], r[3:])
                                                  for c, r in zip(names, rows, strict=True))
    assert a.tf_cdr('p/') == tf_message_cdr((0, 7, 'head', c, r[:3], r[3:])
                                            for c, r in zip(names[:3], rows[:3], strict=True))


# -- MarkerArray -------------------------------------------------------------------------------
def marker_ticks(params, overrides, changes=()):
    """Every tick with markers of a 1.2 s run of ``NodeCore`` (markers at every tick) under a
    moving head; ``changes``: ``(tick, {name: value})`` live changes."""
    from ponytail_ros.app.node_core import NodeCore
    from ponytail_ros.testing.config import load_config
    from ponytail_ros.testing.offline import stamp_msg
    core = NodeCore(load_config(params, {'markers.rate': 1000.0, **overrides}).values)
    changes = dict(changes)
    out = []
    for k in range(1, 145):
        t = k / 120
        if k in changes:
            core.check_change(changes[k])
            core.apply_change(changes[k])
        core.push_head(stamp_msg(t), int(t * 1e9),
                       (0.1 * math.sin(3 * t), 0.05 * t, 1.6),
                       (0.0, 0.0, math.sin(0.4 * t), math.cos(0.4 * t)), 'world')
        tick = core.tick(round(k * 1e9 / 120))
        if tick is not None and tick.segment_markers is not None:
            out.append(tick)
    return out


FLOOR = {'colliders': ['skull', 'floor'], 'floor.kind': 'plane', 'floor.frame': 'world',
         'floor.center': [0.0, 0.0, 0.2], 'floor.axis': [0.0, 0.3, 1.0]}


@pytest.mark.parametrize('params, overrides, changes', [
    ('config/ponytail.yaml', {}, ()),                                       # capsules, sphere
    ('config/ponytail.yaml', {'markers.style': 'line'}, ()),
    ('config/ponytail.yaml', FLOOR, ()),                                    # a plane
    ('config/sword.yaml', {}, ()),                                          # a capsule
    ('config/pigtails.yaml', {}, ()),                                       # two chains
    ('config/ponytail.yaml', {}, [(40, {'markers.style': 'line'}),          # DELETEALLs
                                  (60, {'markers.style': 'off'}),
                                  (80, {'markers.style': 'capsules'}),
                                  (90, {'ponytail.color': [0.1, 0.2, 0.3, 0.4]}),
                                  (100, {'ponytail.n_segments': 5})]),
], ids=['capsules', 'line', 'plane', 'sword', 'pigtails', 'live_changes'])
def test_marker_array_is_serialize_messages_bytes(params, overrides, changes):
    ticks = marker_ticks(params, overrides, changes)
    assert len(ticks) >= 100
    kinds = set()
    for tick in ticks:
        msg, data = tick.markers, tick.segment_markers.cdr
        assert tick.markers is msg                                  # built once
        kinds |= {(m.type, m.action) for m in msg.markers}
        assert data == serialize_canonical(msg)
        raw = serialize_message(msg)
        wire = tick.segment_markers.wire
        assert len(wire) == len(raw) and data[:len(wire)] == wire
        # (decoded, the colours are float32's: compared as bytes again)
        assert serialize_canonical(deserialize_message(wire, type(msg))) == data
    if changes:
        from visualization_msgs.msg import Marker
        assert (Marker.ARROW, Marker.DELETEALL) in kinds
        assert (Marker.LINE_STRIP, Marker.ADD) in kinds and (Marker.CYLINDER, Marker.ADD) in kinds
        colors = {tuple(round(c, 6) for c in (m.color.r, m.color.g, m.color.b, m.color.a))
                  for m in ticks[-1].markers.markers if m.ns == 'ponytail'}
        assert colors == {(0.1, 0.2, 0.3, 0.4)}
        assert len(ticks[-1].markers.markers[0].points) == 6


# -- PoseStamped in ------------------------------------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(data=st.data(), frame_id=FRAMES, sec=SEC, nanosec=NANOSEC)
def test_received_pose_is_what_rclpy_deserialises(data, frame_id, sec, nanosec):
    from geometry_msgs.msg import PoseStamped

    from ponytail_ros.app.messages import ReceivedPose
    from ponytail_ros.app.wire import pose_stamped_fields
    row = data.draw(poses_of(1, FLOATS))[0].tolist()
    msg = PoseStamped()
    msg.header.frame_id = frame_id
    msg.header.stamp = Time(sec=sec, nanosec=nanosec)
    p, o = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z = row[:3]
    o.x, o.y, o.z, o.w = row[3:]
    raw = serialize_message(msg)
    sec2, nanosec2, frame2, position, orientation = pose_stamped_fields(raw)
    assert (sec2, nanosec2, frame2) == (sec, nanosec, frame_id)
    assert np.array(position + orientation).tobytes() == np.array(row).tobytes()   # bits
    got = ReceivedPose.decode(raw)
    assert got.message() is got.message()
    canonical = serialize_canonical(deserialize_message(raw, PoseStamped))
    assert serialize_canonical(got.message()) == canonical
    # What the recorder writes for a pose received as bytes, without a message object.
    assert got.canonical_cdr() == canonical


def test_what_the_decoder_leaves_to_rclpy():
    from geometry_msgs.msg import PoseStamped

    from ponytail_ros.app.wire import pose_stamped_fields
    msg = PoseStamped()
    msg.header.frame_id = 'world'
    raw = serialize_message(msg)
    assert pose_stamped_fields(raw) is not None
    assert pose_stamped_fields(b'\x00\x00' + raw[2:]) is None          # big endian
    assert pose_stamped_fields(raw[:-1]) is None                        # cut short
    assert pose_stamped_fields(raw[:12]) is None
    bad = bytearray(raw)
    bad[16] = 0xff                                                      # not UTF-8
    assert pose_stamped_fields(bytes(bad)) is None
    bad[16] = 0                                                         # a NUL inside
    assert pose_stamped_fields(bytes(bad)) is None


def test_received_pose_canonical_cdr_normalises_what_is_not():
    """Bytes that are canonical already are recorded as they are; encapsulation options, a
    set alignment gap or slack after the data are normalised away."""
    from geometry_msgs.msg import PoseStamped

    from ponytail_ros.app.messages import ReceivedPose
    from ponytail_ros.app.wire import is_canonical_pose_stamped
    msg = PoseStamped()
    msg.header.frame_id = 'world'                       # a 6-byte gap before the pose
    msg.header.stamp = Time(sec=3, nanosec=4)
    msg.pose.position.x, msg.pose.orientation.w = 1.5, 1.0
    canonical = serialize_canonical(msg)
    assert is_canonical_pose_stamped(canonical)
    assert ReceivedPose.decode(canonical).canonical_cdr() is canonical
    gap = bytearray(canonical)
    gap[23] = 7
    for raw in (canonical[:2] + b'\x00\x03' + canonical[4:], bytes(gap),
                canonical + bytes(4)):
        assert not is_canonical_pose_stamped(raw)
        assert ReceivedPose.decode(raw).canonical_cdr() == canonical
