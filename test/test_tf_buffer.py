"""The ROS-free TF buffer (``app/tf_buffer.py``) against transforms composed by hand with
rotation matrices (scipy), and the TFMessage reader against rosbags' serialiser."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from ponytail_ros.app.tf_buffer import TFBuffer, TFError, TFPoseSource
from ponytail_ros.app.wire import tf_message_fields

EPOCH = 1_700_000_000_123_456_789          # a wall-clock stamp, ns


def _matrix(t, q):
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(q).as_matrix()
    m[:3, 3] = t
    return m


def _pose_of(m):
    return m[:3, 3], Rotation.from_matrix(m[:3, :3])


def _random_pose(rng):
    return rng.normal(size=3), Rotation.random(random_state=rng).as_quat()


def _assert_pose(look, m, tol=1e-12):
    t, r = _pose_of(m)
    assert np.allclose(look.position, t, atol=tol, rtol=0)
    got = Rotation.from_quat(look.orientation)
    assert (got.inv() * r).magnitude() < 1e-9


def test_lookup_composes_up_to_the_common_ancestor_and_down():
    """world -> base (moving), base -> neck (static), neck -> head (moving), base -> arm ->
    hand: head in world, hand in head, world in hand, each the product of the edge matrices."""
    rng = np.random.default_rng(1)
    buf = TFBuffer()
    edges = {('world', 'base'): _random_pose(rng), ('base', 'neck'): _random_pose(rng),
             ('neck', 'head'): _random_pose(rng), ('base', 'arm'): _random_pose(rng),
             ('arm', 'hand'): _random_pose(rng)}
    for (parent, child), (t, q) in edges.items():
        buf.add(parent, child, EPOCH, t, q, static=(child == 'neck'))
    m = {k: _matrix(*v) for k, v in edges.items()}
    world_head = m['world', 'base'] @ m['base', 'neck'] @ m['neck', 'head']
    world_hand = m['world', 'base'] @ m['base', 'arm'] @ m['arm', 'hand']
    _assert_pose(buf.lookup('world', 'head', EPOCH), world_head)
    _assert_pose(buf.lookup('head', 'hand', EPOCH), np.linalg.inv(world_head) @ world_hand)
    _assert_pose(buf.lookup('hand', 'world', EPOCH), np.linalg.inv(world_hand))
    _assert_pose(buf.lookup('neck', 'arm', EPOCH),
                 np.linalg.inv(m['base', 'neck']) @ m['base', 'arm'])


def test_a_moving_edge_is_interpolated_between_its_samples_at_epoch_stamps():
    """Translation lerped, rotation slerped (scipy's Slerp), the ratio from integer ns: one
    ns after the first of two samples 1 ms apart at a 2023 epoch stamp moves by 1e-6 of the
    way (a float64 of seconds would not resolve it)."""
    rng = np.random.default_rng(2)
    (t0, q0), (t1, q1) = _random_pose(rng), _random_pose(rng)
    buf = TFBuffer()
    buf.add('world', 'head', EPOCH, t0, q0)
    buf.add('world', 'head', EPOCH + 1_000_000, t1, q1)
    slerp = Slerp([0.0, 1.0], Rotation.from_quat([q0, q1]))
    for dt_ns in (1, 250_000, 500_000, 999_999):
        ratio = dt_ns / 1_000_000
        look = buf.lookup('world', 'head', EPOCH + dt_ns)
        assert look.held == ()
        assert np.allclose(look.position, t0 + ratio * (t1 - t0), atol=1e-14, rtol=0)
        assert (Rotation.from_quat(look.orientation).inv() * slerp([ratio])[0]).magnitude() \
            < 1e-9
    # the samples themselves, exactly
    assert buf.lookup('world', 'head', EPOCH).position == tuple(t0)


def test_slerp_takes_the_shorter_arc():
    buf = TFBuffer()
    q0 = Rotation.from_rotvec([0, 0, 0.1]).as_quat()
    q1 = -Rotation.from_rotvec([0, 0, 0.3]).as_quat()        # the same rotation, other sign
    buf.add('w', 'h', 0, (0, 0, 0), q0)
    buf.add('w', 'h', 10, (0, 0, 0), q1)
    angle = Rotation.from_quat(buf.lookup('w', 'h', 5).orientation).as_rotvec()
    assert np.allclose(angle, [0, 0, 0.2], atol=1e-12)


def test_beyond_the_samples_the_nearest_is_held_and_named():
    buf = TFBuffer()
    buf.add('world', 'base', 100, (1, 0, 0), (0, 0, 0, 1))
    buf.add('world', 'base', 200, (2, 0, 0), (0, 0, 0, 1))
    buf.add('base', 'head', 0, (0, 0, 1), (0, 0, 0, 1), static=True)
    late = buf.lookup('world', 'head', 250)
    assert late.position == (2.0, 0.0, 1.0) and late.held == (('world -> base', 50),)
    early = buf.lookup('world', 'head', 40)
    assert early.position == (1.0, 0.0, 1.0) and early.held == (('world -> base', 60),)


def test_errors_name_the_frames():
    buf = TFBuffer()
    buf.add('world', 'base', 0, (0, 0, 0), (0, 0, 0, 1))
    buf.add('odom', 'head', 0, (0, 0, 0), (0, 0, 0, 1))
    with pytest.raises(TFError, match="'nose' has not appeared.*base, head, odom, world"):
        buf.lookup('world', 'nose', 0)
    with pytest.raises(TFError, match="'base' and 'head' are not connected.*world -> base"
                                      ".*odom -> head"):
        buf.lookup('base', 'head', 0)
    buf.add('head', 'odom', 0, (0, 0, 0), (0, 0, 0, 1))        # odom -> head -> odom
    with pytest.raises(TFError, match='loop: head -> odom -> head'):
        buf.lookup('world', 'head', 0)
    with pytest.raises(ValueError, match='itself'):
        buf.add('a', 'a', 0, (0, 0, 0), (0, 0, 0, 1))
    with pytest.raises(ValueError, match='not finite'):
        buf.add('a', 'b', 0, (np.nan, 0, 0), (0, 0, 0, 1))


def test_cache_repeated_and_old_samples():
    buf = TFBuffer(cache_ns=1000)
    for t in (0, 500, 1000, 1500):
        assert buf.add('w', 'h', t, (t, 0, 0), (0, 0, 0, 1))
    assert buf.edges['h'].stamps == [500, 1000, 1500]          # 0 is older than 1 s cache
    assert not buf.add('w', 'h', 1000, (9, 0, 0), (0, 0, 0, 1)) and buf.repeated == 1
    assert not buf.add('w', 'h', 100, (9, 0, 0), (0, 0, 0, 1)) and buf.old == 1
    assert buf.add('w', 'h', 750, (750, 0, 0), (0, 0, 0, 1))   # out of order, inside the cache
    assert buf.lookup('w', 'h', 700).position[0] == pytest.approx(700.0, abs=1e-12)


def _feed(buf, src, parent, child, stamp, x):
    src.note(buf.add_transforms([(stamp // 10**9, stamp % 10**9, parent, child, (x, 0, 0),
                                  (0, 0, 0, 1))]))


def test_pose_source_gives_poses_at_the_moving_edges_stamps_once_all_cover_them():
    """Two moving edges with interleaved stamps: a stamp is due once both have a sample at or
    after it; each pose interpolates the other edge; no stamp twice."""
    buf = TFBuffer()
    src = TFPoseSource(buf, 'world', 'head', wait_ns=10**9)
    buf.add('base', 'neck', 0, (0, 0, 0.5), (0, 0, 0, 1), static=True)
    assert src.poll() == [] and src.missing == 1 and "'world'" in src.error
    _feed(buf, src, 'world', 'base', EPOCH, 0.0)
    _feed(buf, src, 'neck', 'head', EPOCH + 5, 0.0)
    assert src.poll() == [] and src.late == 1        # EPOCH: before head's first sample
    _feed(buf, src, 'world', 'base', EPOCH + 10, 1.0)
    _feed(buf, src, 'neck', 'head', EPOCH + 15, 2.0)
    out = src.poll()
    assert [s.stamp_ns for s in out] == [EPOCH + 5, EPOCH + 10]
    # at EPOCH + 5 base is half way (0.5), head at its sample (0); at + 10 head half way (1)
    assert out[0].position == pytest.approx((0.5, 0, 0.5), abs=1e-12)
    assert out[1].position == pytest.approx((1.0 + 1.0, 0, 0.5), abs=1e-12)
    assert src.poll() == [] and not src.extrapolated
    _feed(buf, src, 'world', 'base', EPOCH + 3, 0.3)              # late: not given again
    assert src.poll() == [] and src.late == 2


def test_pose_source_waits_a_bounded_time_then_holds_and_counts():
    """An edge that stops: poses keep coming ``wait_ns`` behind the live edge, with the stopped
    edge held, counted as extrapolated and, past ``stale_ns``, as stale."""
    buf = TFBuffer()
    src = TFPoseSource(buf, 'world', 'head', wait_ns=100, stale_ns=250)
    _feed(buf, src, 'world', 'base', 0, 0.0)
    _feed(buf, src, 'base', 'head', 0, 1.0)
    assert len(src.poll()) == 1
    got = []
    for t in range(50, 501, 50):                                   # base -> head stopped at 0
        _feed(buf, src, 'world', 'base', t, t / 100)
        got += src.poll()
    assert [s.stamp_ns for s in got] == list(range(50, 401, 50))   # 100 ns behind
    assert all(s.position[0] == pytest.approx(s.stamp_ns / 100 + 1.0) for s in got)
    assert src.extrapolated == {'base -> head': 8}
    assert src.stale == {'base -> head': 3}                         # 300, 350, 400


def test_tf_message_fields_reads_what_rosbags_serialises():
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_KILTED)
    T = ts.types
    tr = [T['geometry_msgs/msg/TransformStamped'](
        header=T['std_msgs/msg/Header'](
            stamp=T['builtin_interfaces/msg/Time'](sec=s, nanosec=ns), frame_id=parent),
        child_frame_id=child,
        transform=T['geometry_msgs/msg/Transform'](
            translation=T['geometry_msgs/msg/Vector3'](x=x, y=2.0, z=3.0),
            rotation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.6, w=0.8)))
        for s, ns, parent, child, x in ((1, 2, 'world', 'b', 1.5), (3, 4, 'b', 'neck_x', -1.0),
                                        (5, 6, 'neck_x', 'hé', 0.25))]
    data = bytes(ts.serialize_cdr(T['tf2_msgs/msg/TFMessage'](transforms=tr),
                                  'tf2_msgs/msg/TFMessage'))
    assert tf_message_fields(data) == [
        (1, 2, 'world', 'b', (1.5, 2.0, 3.0), (0.0, 0.0, 0.6, 0.8)),
        (3, 4, 'b', 'neck_x', (-1.0, 2.0, 3.0), (0.0, 0.0, 0.6, 0.8)),
        (5, 6, 'neck_x', 'hé', (0.25, 2.0, 3.0), (0.0, 0.0, 0.6, 0.8))]
    with pytest.raises(ValueError):
        tf_message_fields(data[:-9])


def test_tf_input_gives_head_poses_and_says_what_is_missing_or_held():
    """``TFInput``: poses as PoseStamped heads in fixed_frame; a frame that never appears is
    said (after the tree had its chance to come in) and flagged in diagnostics; a stopped
    transform is said held, then stale, naming it."""
    from ponytail_ros.app.tf_input import FAILING_SAID, TFInput
    values = {'head_frame': 'head', 'fixed_frame': 'world', 'stale_timeout': 0.25,
              'frames': []}
    tf = TFInput(values)

    def msg(stamp, parent, child, x):
        return [(stamp // 10**9, stamp % 10**9, parent, child, (x, 0.0, 0.0), (0, 0, 0, 1))]
    for i in range(FAILING_SAID):
        assert tf.add(msg(EPOCH + i * 10**7, 'world', 'base', 0.1 * i), False) == []
        said = tf.news()
        assert not said if i < FAILING_SAID - 1 else [k for k, _ in said] == ['tf:missing:head']
    assert "frame 'head' has not appeared" in said[0][1]
    problems, kv = tf.diagnostics()
    assert problems == [f"TF head: {tf.sources['head'].error}"]
    assert dict(kv)['tf head lookups failed'] == str(FAILING_SAID)
    tf.add(msg(0, 'base', 'neck', 0.0), True)
    out = tf.add(msg(EPOCH + 9 * 10**7, 'neck', 'head', 1.0), False)
    assert [(s, p.stamp, p.frame_id, p.position) for s, p in out] == [
        ('head', (1_700_000_000, 213_456_789), 'world', (0.9 + 1.0, 0.0, 0.0))]
    assert tf.diagnostics()[0] == [] and tf.news() == []
    for i in range(10, 40):                       # neck -> head stopped at 0.09 s
        out = tf.add(msg(EPOCH + i * 10**7, 'world', 'base', 0.1 * i), False)
    said = dict(tf.news())                        # held 0.05 s at 0.39 - 0.25 s
    assert 'holds neck -> head (0.050 s past its samples): no newer' in said['tf:held:head']
    assert tf.diagnostics()[0] == []
    for i in range(40, 80):
        out = tf.add(msg(EPOCH + i * 10**7, 'world', 'base', 0.1 * i), False)
    said = dict(tf.news())                        # held 0.45 s: stale
    assert 'holds neck -> head (0.450 s past its samples): stale,' in said['tf:held:head']
    problems, kv = tf.diagnostics()
    assert problems == ['TF head: stale transform neck -> head']
    assert int(dict(kv)['tf head extrapolated: neck -> head']) > 0
    assert int(dict(kv)['tf head stale: neck -> head']) > 0


def test_tf_input_skips_the_nodes_own_segments():
    from ponytail_ros.app.tf_input import TFInput
    tf = TFInput({'head_frame': 'head', 'fixed_frame': 'world', 'stale_timeout': 0.25})
    tf.ignore_prefixes = ('alice/ponytail/',)
    tf.add([(0, 0, 'world', 'alice/ponytail/0', (0, 0, 0), (0, 0, 0, 1)),
            (0, 0, 'world', 'head', (0, 0, 0), (0, 0, 0, 1))], False)
    assert tf.buffer.frames() == {'world', 'head'}


@pytest.mark.parametrize('changes, names, words', [
    ({'fixed_frame': ''}, ('fixed_frame',), 'inertial'),
    ({'fixed_frame': 'my world'}, ('fixed_frame',), 'no spaces'),
    ({'head_frame': 'world'}, ('head_frame',), 'other than fixed_frame'),
    ({'head_frame': 'a head'}, ('head_frame',), 'no spaces'),
    ({'frames': ['arm'], 'arm.tf_frame': 'hand'}, ('arm.tf_frame', 'head_frame'),
     'set head_frame'),
    ({'frames': ['arm'], 'arm.tf_frame': 'hand', 'head_frame': 'head', 'frames_topic': 'fp'},
     ('arm.tf_frame', 'frames_topic'), 'not allowed with frames_topic'),
])
def test_tf_parameters_are_refused_naming_them(changes, names, words):
    from ponytail_ros.app.parameters import (
        CHAIN_PARAMS,
        FRAME_PARAMS,
        GLOBAL_PARAMS,
        ParameterError,
        check_values,
    )
    values = {p.name: p.default for p in GLOBAL_PARAMS}
    values.update({f'ponytail.{p.name}': p.default for p in CHAIN_PARAMS})
    values.update({f'arm.{p.name}': p.default for p in FRAME_PARAMS})
    check_values(values, ['ponytail'])                  # the defaults: the head on head_pose
    values.update(changes)
    with pytest.raises(ParameterError, match=words) as err:
        check_values(values, ['ponytail'])
    assert err.value.names == names
