"""Helpers shared by the ROS test modules (they need rclpy, the ROS message packages and, for
the bags, ``rosbags``): the node's test chain and head, message builders and checks, bags
written by third-party writers, and the recorded live run that ``test_recording.py`` and
``test_replay.py`` both read (the session fixture ``live_run`` in ``conftest.py`` makes it
once).

Test modules import these instead of importing each other.
"""
import array
import dataclasses
import math
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

pytest.importorskip('rclpy', reason='rclpy (ROS 2 wheels or a sourced workspace) is not installed')

import rclpy  # noqa: E402
from builtin_interfaces.msg import Time  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseArray, PoseStamped  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from ponytail_ros.core.rotations import quat_axis_x, quat_from_rotvec, quat_rotate  # noqa: E402
from ponytail_ros.node import PonytailNode  # noqa: E402
from ponytail_ros.recording.bag import BagReader  # noqa: E402
from ponytail_ros.recording.cli import main  # noqa: E402
from ponytail_ros.recording.recorder import stamp_ns  # noqa: E402
from ponytail_ros.testing import Harness as PublicHarness  # noqa: E402
from ponytail_ros.testing.harness import (  # noqa: E402,F401
    TIMEOUT_SCALE,
    diagnostic_values,
    pose_msg as _public_pose_msg,
)

from conftest import TEST_DOMAIN_ID  # noqa: E402

# -- the node's test chain, head and messages ---------------------------------------------------

#: ``/diagnostics`` values by key.
diag_values = diagnostic_values

ATTACH = [-0.09, 0.0, 0.06]
CHAIN = {'n_segments': 6, 'length': 0.3, 'mass': 0.1, 'radius': 0.03, 'attach': ATTACH,
         'damping': 1e-3, 'drag_linear': 0.05}
Q_TILT = quat_from_rotvec(np.array([0.2, -0.1, 0.8]))
P_HEAD = np.array([1.0, -2.0, 1.5])


def overrides(chains=('ponytail',), **values):
    params = {'diagnostics_period': 0.2, 'chains': list(chains)}
    for c in chains:
        params.update({f'{c}.{k}': v for k, v in CHAIN.items()})
    params.update({k.replace('__', '.'): v for k, v in values.items()})
    return [Parameter(k, value=v) for k, v in params.items()]


def stamp(t):
    sec = math.floor(t)
    return Time(sec=int(sec), nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000)


def t_of(header):
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def pose_msg(t, p=P_HEAD, q=Q_TILT, frame='world'):
    return _public_pose_msg(stamp(t) if isinstance(t, float) else t, p, q, frame)


def attach_point(p, q, attach=ATTACH):
    return np.asarray(p) + quat_rotate(np.asarray(q, dtype=float), np.asarray(attach))


def arrays(msg):
    o = np.array([[p.position.x, p.position.y, p.position.z] for p in msg.poses])
    q = np.array([[p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]
                  for p in msg.poses])
    return o, q


def check_geometry(msg, n, length):
    """N poses, finite, neighbouring segments meet: distal = origin + R (l, 0, 0)."""
    assert len(msg.poses) == n
    o, q = arrays(msg)
    assert np.all(np.isfinite(o)) and np.all(np.isfinite(q))
    distal = o + quat_axis_x(q) * (length / n)
    assert np.max(np.linalg.norm(distal[:-1] - o[1:], axis=1)) < 1e-6
    return o, q


class Harness(PublicHarness):
    """The public harness on the wall clock (the node, a tester node publishing ``h.head`` at
    100 Hz and collecting every output, one executor, a fresh context of its own with
    discovery off), called as this module always called its harness: ``Harness(ctx, params)``
    with ``Parameter`` overrides (``ctx`` is not used: the harness makes its own context), and
    the names ``diags`` / ``fresh_diag`` that ``test_frames.py`` uses."""

    def __init__(self, ctx=None, params=(), topics=('segment_poses',), namespace=None,
                 head_qos=10):
        super().__init__(None, {p.name: p.value for p in params}, sim_time=False,
                         topics=topics, namespace=namespace, head_qos=head_qos)

    @property
    def diags(self):
        return self.diagnostics

    def fresh_diag(self):
        return self.fresh_diagnostics(3.0)


# -- bags by third-party writers (rosbags) ----------------------------------------------------
HEAD = '/head_pose'
T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 10_000_000   # 100 Hz
N_POSES = 300            # 3 s
PARAMS = """/**:
  ros__parameters:
    rate: 100.0
    diagnostics_period: 1.0
    ponytail:
      n_segments: 4
"""


def head_msg(i, stamp_ns, nan=False):
    t = i * PERIOD_NS * 1e-9
    m = PoseStamped()
    m.header.frame_id = 'world'
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    m.pose.position.x = 0.1 * math.sin(2 * math.pi * t)
    m.pose.position.z = 1.6
    m.pose.orientation.z = math.sin(0.2 * math.sin(3 * t))
    m.pose.orientation.w = math.cos(0.2 * math.sin(3 * t))
    if nan:
        m.pose.orientation.w = float('nan')
    return m


def head_samples(n=N_POSES, stamp_offset_ns=0, nan=()):
    """(log time, serialised PoseStamped) at 100 Hz from T0; stamps = log time + offset."""
    return [(T0_NS + i * PERIOD_NS,
             serialize_message(head_msg(i, T0_NS + i * PERIOD_NS + stamp_offset_ns, i in nan)))
            for i in range(n)]


def rosbags_bag(tmp_path, name, samples):
    """A rosbag2 MCAP bag written by rosbags (one chunk, no CRCs), messages in list order;
    the .mcap file's path."""
    from rosbags.rosbag2 import StoragePlugin, Writer as RosbagsWriter
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_KILTED)
    folder = tmp_path / name
    with RosbagsWriter(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(HEAD, 'geometry_msgs/msg/PoseStamped', typestore=store)
        for log_ns, data in samples:
            writer.write(conn, log_ns, data)
    (path,) = folder.glob('*.mcap')
    return path


def run(argv, capsys):
    """main(argv) -> (exit code, stdout, stderr lines)."""
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, [line for line in err.splitlines() if line.strip()]


def plain(value):
    """rclpy or rosbags message -> nested dicts/lists of Python scalars, for comparison."""
    if hasattr(value, 'get_fields_and_field_types'):
        return {f: plain(getattr(value, f)) for f in value.get_fields_and_field_types()}
    if dataclasses.is_dataclass(value):
        # rosbags lists constants (upper case; ROS field names are lower case) as fields too.
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)
                if not f.name.startswith('_') and not f.name.isupper()}
    if isinstance(value, bytes) and len(value) == 1:  # rclpy 'byte' field; rosbags gives int
        return value[0]
    if isinstance(value, (bytes, bytearray, list, tuple, array.array, np.ndarray)):
        return [plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


# -- the recorded live run ---------------------------------------------------------------------
#: Head samples (counted from the node's first output) sent with NaN / with a zero stamp.
NAN_SAMPLE, ZERO_STAMP_SAMPLE = 20, 40
#: Live parameter changes of the recorded run: (after this many ticks, {name: value}).
CHANGES = ((50, {'ponytail.damping': 0.01}), (100, {'ponytail.n_segments': 8}))
#: Ticks recorded (1.25 s at 120 Hz; counted, not timed, so that a loaded machine gets as many).
RUN_TICKS = 150
TYPES = {
    '/head_pose': 'geometry_msgs/msg/PoseStamped',
    '/segment_poses': 'geometry_msgs/msg/PoseArray',
    '/segment_markers': 'visualization_msgs/msg/MarkerArray',
    '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray',
    '/parameter_events': 'rcl_interfaces/msg/ParameterEvent',
    '/tf': 'tf2_msgs/msg/TFMessage',
}


def head_at(t):
    """A swaying, turning head (m, quaternion)."""
    w = 2.0 * math.pi * 1.5
    p = P_HEAD + np.array([0.12 * math.sin(w * t), 0.04 * math.cos(w * t),
                           0.02 * math.sin(2 * w * t)])
    q = quat_from_rotvec(np.array([0.2, -0.1, 0.8 + 0.3 * math.sin(w * t)]))
    return p, q


_LIVE: dict[str, Any] = {}


def live_recording(tmp_root):
    """Run the node in-process with ``record_path`` set for ``RUN_TICKS`` ticks, a moving head
    published at 100 Hz (one NaN sample, one zero stamp), a live tunable and a live structural
    parameter change; return what was sent and received and the recording's path. Made once."""
    if 'run' in _LIVE:
        return _LIVE['run']
    path = Path(tmp_root) / 'live_run.mcap'
    ctx = Context()
    rclpy.init(context=ctx, domain_id=TEST_DOMAIN_ID)
    try:
        # One RK4 step per tick (dt = 1/rate): a loaded machine's late ticks then cost few
        # steps, so the run cannot fall further and further behind.
        node = PonytailNode(context=ctx, parameter_overrides=overrides(
            record_path=str(path), diagnostics_period=0.2, solver__dt=1.0 / 120.0))
        tester = rclpy.create_node('tester', context=ctx)
        head_pub = tester.create_publisher(PoseStamped, 'head_pose', 10)
        got = SimpleNamespace(path=path, sent=[], poses=[], markers=[], diags=[], first=10**9)
        tester.create_subscription(PoseArray, 'segment_poses', got.poses.append, 100)
        tester.create_subscription(MarkerArray, 'segment_markers', got.markers.append, 100)
        tester.create_subscription(DiagnosticArray, '/diagnostics', got.diags.append, 100)

        def publish_head():
            t = tester.get_clock().now().nanoseconds * 1e-9
            p, q = head_at(t)
            k = len(got.sent) - got.first
            if k == NAN_SAMPLE:
                p = np.array([math.nan, 0.0, 0.0])
            msg = pose_msg(t, p, q, 'world')
            if k == ZERO_STAMP_SAMPLE:
                msg.header.stamp.sec, msg.header.stamp.nanosec = 0, 0
            head_pub.publish(msg)
            got.sent.append(msg)
        tester.create_timer(0.01, publish_head)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        executor.add_node(tester)
        deadline = time.monotonic() + 10.0 * TIMEOUT_SCALE
        while not got.poses and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.005)
        assert got.poses, 'the node published nothing'
        got.first = len(got.sent)
        pending = list(CHANGES)
        deadline = time.monotonic() + 30.0 * TIMEOUT_SCALE
        while len(got.poses) < RUN_TICKS and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.005)
            if pending and len(got.poses) >= pending[0][0]:
                _, change = pending.pop(0)
                results = node.set_parameters([Parameter(k, value=v) for k, v in change.items()])
                assert all(r.successful for r in results)
        names = node.list_parameters([], 0).names
        got.parameters = {p.name: p.value for p in node.get_parameters(names)}
        executor.shutdown()
        node.destroy_node()          # finalises the recording
        tester.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    _LIVE['run'] = got
    return got


def topic_messages(path, topic):
    return [(m, t) for _, _, m, t in BagReader(path).messages(topic)]


def poses_by_stamp(path, topic='/segment_poses'):
    return {stamp_ns(m.header.stamp): m for m, _ in topic_messages(path, topic)}
