"""Recording a real node run (``record_path``): what is in the file, read back with our reader and
with ``rosbags`` (with the schemas in the file and with its own Kilted type store); never
overwriting; and durability -- a SIGKILLed node leaves every message of its written chunks
readable, SIGTERM/SIGINT finalise the file.

The in-process run (node + test publisher/subscribers in one executor, on this test run's own
ROS domain) is shared with ``test_replay.py`` through :func:`live_recording` (made once per
pytest process).
"""
import io
import math
import os
import signal
import subprocess
import sys
import time
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

import yaml  # noqa: E402
from geometry_msgs.msg import PoseArray, PoseStamped  # noqa: E402
from mcap.exceptions import EndOfFile  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from mcap.records import Chunk, Message  # noqa: E402
from mcap.stream_reader import StreamReader, breakup_chunk  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from ponytail_ros.app.param_values import values_from_metadata  # noqa: E402
from ponytail_ros.node import PonytailNode  # noqa: E402
from ponytail_ros.recording.bag import PARAMETERS_METADATA, BagReader  # noqa: E402
from ponytail_ros.recording.recorder import RECORDING_METADATA, stamp_ns  # noqa: E402

from ros_helpers import CHANGES, P_HEAD, TIMEOUT_SCALE, TYPES, head_at, overrides, plain, pose_msg  # noqa: E402

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / 'config' / 'ponytail.yaml'


def by_topic(path):
    """Every topic's messages deserialised, but ``/tf`` (deserialised only where tf2_msgs is
    installed: read as bytes by the tests that check it)."""
    out = {}
    for topic, _, msg, log_ns in BagReader(path).messages():
        if topic != '/tf':
            out.setdefault(topic, []).append((msg, log_ns))
    return out


# -- what is recorded --------------------------------------------------------------------------

def test_node_recording_holds_what_the_node_published_and_received(live_run):
    reader = BagReader(live_run.path)
    assert reader.topics() == TYPES
    rec = by_topic(live_run.path)

    # Head input as received: an in-order subsequence of what was sent (best effort may drop);
    # compared by repr, as a NaN field is never == itself.
    sent = iter(repr(m) for m in live_run.sent)
    heads = [m for m, _ in rec['/head_pose']]
    assert all(any(repr(h) == s for s in sent) for h in heads)
    assert len(heads) >= 0.8 * len(live_run.sent) - 5
    assert any(math.isnan(h.pose.position.x) for h in heads)
    assert any(h.header.stamp.sec == 0 for h in heads)

    # Outputs: every message the subscriber got is in the recording, equal in every field.
    recorded = {stamp_ns(m.header.stamp): m for m, _ in rec['/segment_poses']}
    assert len(recorded) == len(rec['/segment_poses'])      # one PoseArray per tick
    assert live_run.poses and all(recorded[stamp_ns(m.header.stamp)] == m
                                  for m in live_run.poses)
    assert {len(m.poses) for m in recorded.values()} == {6, 8}   # the live rebuild
    markers = [m for m, _ in rec['/segment_markers']]
    assert live_run.markers and all(m in markers for m in live_run.markers)
    diags = [m for m, _ in rec['/diagnostics']]
    assert live_run.diags and all(m in diags for m in live_run.diags)

    # Live parameter changes, in order, at their times.
    events = rec['/parameter_events']
    assert [(e.node, [(p.name, Parameter.from_parameter_msg(p).value)
                      for p in e.changed_parameters]) for e, _ in events] == [
        ('/ponytail', list(change.items())) for _, change in CHANGES]

    # Every parameter of the node at start-up (the changes above came later).
    meta = reader.metadata()
    values = values_from_metadata(meta[PARAMETERS_METADATA])
    expected = {k: (list(v) if isinstance(v, (list, tuple)) or hasattr(v, 'tolist') else v)
                for k, v in live_run.parameters.items()}
    expected.update({'ponytail.damping': 1e-3, 'ponytail.n_segments': 6})
    assert values == expected
    assert meta[RECORDING_METADATA]['source'] == 'ponytail_node'
    assert meta[RECORDING_METADATA]['tick_topic'] == '/segment_poses'
    bag = yaml.safe_load(meta['rosbag2']['serialized_metadata'])
    # every message, /tf too (one per tick: as many as PoseArrays)
    assert bag['message_count'] == sum(len(v) for v in rec.values()) + len(rec['/segment_poses'])
    assert bag['message_count'] == sum(1 for _ in BagReader(live_run.path).messages(raw=True))


def test_log_time_is_the_node_clock_receive_time_and_publish_time_the_stamp(live_run):
    ticks = []
    with open(live_run.path, 'rb') as f:
        reader = make_reader(f)
        for _schema, channel, message in reader.iter_messages():
            if channel.topic == '/segment_poses':
                stamp = int.from_bytes(message.data[4:8], 'little') * 10**9 + \
                    int.from_bytes(message.data[8:12], 'little')
                assert message.publish_time == stamp <= message.log_time
                ticks.append((stamp, message.log_time))
            elif channel.topic == '/head_pose':
                stamp = int.from_bytes(message.data[4:8], 'little') * 10**9 + \
                    int.from_bytes(message.data[8:12], 'little')
                if stamp:                                      # received after it was sent
                    assert message.publish_time == stamp <= message.log_time
    # Each tick is recorded within its own callback, from the node's clock: after its stamp and
    # before the next tick's (no wall-time bound: a loaded machine may take long over a tick).
    ticks.sort()
    assert len(ticks) > 10
    assert all(log_ns <= next_stamp for (_, log_ns), (next_stamp, _) in pairwise(ticks))


def test_rosbags_decodes_the_node_recording_with_and_without_a_typestore(live_run):
    highlevel = pytest.importorskip('rosbags.highlevel')
    typesys = pytest.importorskip('rosbags.typesys')
    ours = {t: sorted(((log_ns, plain(m)) for m, log_ns in v), key=lambda x: x[0])
            for t, v in by_topic(live_run.path).items()}
    store = typesys.get_typestore(getattr(typesys.Stores, 'ROS2_KILTED', typesys.Stores.LATEST))
    for kwargs in ({}, {'default_typestore': store}):
        with highlevel.AnyReader([live_run.path], **kwargs) as reader:
            assert {c.topic: c.msgtype for c in reader.connections} == TYPES
            theirs = {}
            for c, log_ns, raw in reader.messages():
                msg = (store.deserialize_cdr(raw, c.msgtype) if kwargs
                       else reader.deserialize(raw, c.msgtype))
                theirs.setdefault(c.topic, []).append((log_ns, plain(msg)))
        # /tf (by rosbags, whether or not tf2_msgs is installed): every segment of every
        # PoseArray as a frame <chain>/<i> of the array's frame, at its stamp, to 1e-12.
        tf = theirs.pop('/tf')
        arrays = ours['/segment_poses']
        assert [log for log, _ in tf] == [log for log, _ in arrays]
        for (_, frames), (_, array) in zip(tf, arrays, strict=True):
            assert len(frames['transforms']) == len(array['poses']) > 0
            for i, (tr, pose) in enumerate(zip(frames['transforms'], array['poses'], strict=True)):
                assert tr['header'] == array['header']
                assert tr['child_frame_id'] == f'ponytail/{i}'
                got = [tr['transform']['translation'][k] for k in 'xyz'] + \
                      [tr['transform']['rotation'][k] for k in 'xyzw']
                want = [pose['position'][k] for k in 'xyz'] + \
                       [pose['orientation'][k] for k in 'xyzw']
                assert np.max(np.abs(np.subtract(got, want))) <= 1e-12
        assert repr(theirs) == repr(ours)      # repr: NaN fields compare equal


# -- never overwritten, clear errors ------------------------------------------------------------

def test_existing_file_kept_unwritable_path_reported_and_the_simulation_goes_on(
        ros_context, tmp_path, capfd):
    existing = tmp_path / 'exists.mcap'
    existing.write_bytes(b'precious')
    paths = {'a': str(existing), 'b': str(tmp_path / 'missing' / 'run.mcap'),
             'c': str(tmp_path / 'run_%Y.mcap')}
    nodes = {ns: PonytailNode(context=ros_context, namespace=ns,
                              parameter_overrides=overrides(record_path=path))
             for ns, path in paths.items()}
    tester = rclpy.create_node('tester', context=ros_context)
    pubs = {ns: tester.create_publisher(PoseStamped, f'/{ns}/head_pose', 10) for ns in nodes}
    got = {ns: [] for ns in nodes}
    for ns in nodes:
        tester.create_subscription(PoseArray, f'/{ns}/segment_poses', got[ns].append, 10)
    tester.create_timer(0.01, lambda: [p.publish(pose_msg(
        tester.get_clock().now().nanoseconds * 1e-9, P_HEAD)) for p in pubs.values()])
    executor = SingleThreadedExecutor(context=ros_context)
    for n in (*nodes.values(), tester):
        executor.add_node(n)
    try:
        deadline = time.monotonic() + 10.0 * TIMEOUT_SCALE
        while time.monotonic() < deadline and min(len(v) for v in got.values()) < 5:
            executor.spin_once(timeout_sec=0.005)
        assert min(len(v) for v in got.values()) >= 5    # all three simulate
    finally:
        executor.shutdown()
        for n in (*nodes.values(), tester):
            n.destroy_node()
    assert existing.read_bytes() == b'precious'
    log = ''.join(capfd.readouterr())
    assert f'Not recording: {existing} already exists' in log
    assert f'folder {tmp_path / "missing"} does not exist' in log
    assert log.count('the simulation goes on without recording') == 2
    dated = tmp_path / time.strftime('run_%Y.mcap')
    assert len(list(BagReader(dated).messages('/c/segment_poses'))) >= 5


# -- durability: SIGKILL, SIGTERM, SIGINT --------------------------------------------------------

class _WholeReads:
    def __init__(self, f):
        self.f = f

    def read(self, n=-1):
        data = self.f.read(n)
        return data if n < 0 or len(data) == n else b''


def messages_in_complete_chunks(path):
    """Messages in every chunk fully written (CRC checked), read independently of BagReader."""
    n = 0
    reader = StreamReader(_WholeReads(io.BytesIO(Path(path).read_bytes())), emit_chunks=True)
    try:
        for record in reader.records:
            if isinstance(record, Chunk):
                n += sum(isinstance(r, Message) for r in breakup_chunk(record, validate_crc=True))
            elif isinstance(record, Message):
                n += 1
    except EndOfFile:
        pass
    return n


def child_env():
    env = dict(os.environ)
    env['PYTHONPATH'] = str(ROOT) + os.pathsep + env.get('PYTHONPATH', '')
    env['PYTHONUNBUFFERED'] = '1'
    return env


#: The signal each recording node of the durability test gets, by namespace.
SIGNALS = {'kill': signal.SIGKILL, 'term': signal.SIGTERM, 'int': signal.SIGINT}


def test_sigkill_keeps_every_written_chunk_sigterm_and_sigint_finalise(ros_context, tmp_path):
    files = {ns: tmp_path / f'{ns}.mcap' for ns in SIGNALS}
    procs = {ns: start_recording_node(ns, path) for ns, path in files.items()}
    try:
        got, results = record_then_signal(ros_context, procs)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.communicate()
    check_killed_recording(files['kill'], procs['kill'], got['kill'])
    for ns in ('term', 'int'):
        check_finalised_recording(files[ns], ns, procs[ns], results[ns], got[ns])


def start_recording_node(ns, path):
    """A node process in namespace ``ns`` recording to ``path``."""
    return subprocess.Popen(
        [sys.executable, '-m', 'ponytail_ros.node', '--ros-args', '--params-file',
         str(CONFIG), '-r', f'__ns:=/{ns}', '-p', f'record_path:={path}',
         # a light chain: three nodes share a (possibly loaded) test machine
         '-p', 'ponytail.n_segments:=4', '-p', 'markers.style:=line'],
        env=child_env(), cwd=str(ROOT), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)


def record_then_signal(ros_context, procs):
    """Drive every node of ``procs`` (namespace -> process) with head poses until each has
    published for 1.5 s (several chunks written), then send each its ``SIGNALS`` signal;
    ``(got, results)``: the stamps (ns) of the segment poses each namespace's subscriber
    received, and each process's ``(stdout, stderr)``."""
    node = rclpy.create_node('driver', context=ros_context)
    pubs = {ns: node.create_publisher(PoseStamped, f'/{ns}/head_pose', 10) for ns in procs}
    got = {ns: [] for ns in procs}
    for ns in procs:
        node.create_subscription(PoseArray, f'/{ns}/segment_poses',
                                 lambda m, ns=ns: got[ns].append(stamp_ns(m.header.stamp)),
                                 100)

    def publish():
        t = node.get_clock().now().nanoseconds * 1e-9
        p, q = head_at(t)
        for pub in pubs.values():
            pub.publish(pose_msg(t, p, q, 'world'))
    node.create_timer(0.01, publish)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    deadline = time.monotonic() + 30.0 * TIMEOUT_SCALE

    def ran():
        return all(v and v[-1] - v[0] >= 1_500_000_000 for v in got.values())
    while time.monotonic() < deadline and not ran():
        executor.spin_once(timeout_sec=0.005)
        for ns, p in procs.items():
            assert p.poll() is None, (ns, p.communicate())
    assert ran()
    for ns, sig in SIGNALS.items():
        procs[ns].send_signal(sig)
    results = {ns: p.communicate(timeout=20) for ns, p in procs.items()}
    executor.shutdown()
    node.destroy_node()
    return got, results


def check_killed_recording(killed, proc, got):
    """SIGKILL: no summary, but every message of every complete chunk is there and decodes,
    and nothing older than the documented bound (0.5 s of log time, + 0.5 s for a loaded
    machine's writer queue) of what the subscriber ``got`` (stamps, ns) is lost."""
    assert proc.returncode == -signal.SIGKILL
    with open(killed, 'rb') as f:
        assert f.read()[-8:] != b'\x89MCAP0\r\n'          # not finalised
    recovered = list(BagReader(killed).messages())       # every message deserialises
    every = list(BagReader(killed).messages(raw=True))   # /tf too (without tf2_msgs)
    assert len(every) == messages_in_complete_chunks(killed) > 0
    from ponytail_ros.recording.tf import tf2_msgs_available
    assert len(recovered) == (len(every) if tf2_msgs_available()
                              else sum(t != '/tf' for t, *_ in every))
    ticks = {stamp_ns(m.header.stamp) for t, _, m, _ in recovered if t == '/kill/segment_poses'}
    last_seen = max(got)
    assert {s for s in got if s <= last_seen - 1_000_000_000} <= ticks
    assert PARAMETERS_METADATA in BagReader(killed).metadata()


def check_finalised_recording(path, ns, proc, result, got):
    """SIGTERM / SIGINT: clean exit, finalised file (summary, final rosbag2 metadata), every
    tick the subscriber ``got`` (stamps, ns) is recorded."""
    out, err = result
    assert proc.returncode == 0, err
    assert 'Traceback' not in err, err
    with open(path, 'rb') as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    messages = [m for m in BagReader(path).messages() if m[0] != '/tf']
    every = sum(1 for _ in BagReader(path).messages(raw=True))   # /tf too
    assert summary.statistics.message_count == every
    assert every - len(messages) == sum(t == f'/{ns}/segment_poses' for t, *_ in messages)
    bag = yaml.safe_load(BagReader(path).metadata()['rosbag2']['serialized_metadata'])
    assert bag['message_count'] == every
    ticks = {stamp_ns(m.header.stamp) for t, _, m, _ in messages
             if t == f'/{ns}/segment_poses'}
    assert set(got) <= ticks
