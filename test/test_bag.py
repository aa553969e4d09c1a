"""Tests of ponytail_ros.recording.bag: rosbag2's MCAP layout, round trips, crash recovery.

Needs rclpy (serialisation goes through the RMW) and the message packages, but no ROS graph.
The rosbags checks decode our files with an independent implementation, once with the schemas
stored in the file -- the real check that the schema texts are right -- and once with rosbags'
built-in Kilted type store.
"""
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

pytest.importorskip('rclpy', reason='rclpy (ROS 2 wheels or a sourced workspace) is not installed')

import yaml  # noqa: E402
from builtin_interfaces.msg import Duration, Time  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue  # noqa: E402
from geometry_msgs.msg import Point, Pose, PoseArray, PoseStamped  # noqa: E402
from mcap.reader import make_reader  # noqa: E402
from rclpy.qos import QoSDurabilityPolicy, QoSProfile  # noqa: E402
from std_msgs.msg import ColorRGBA  # noqa: E402
from visualization_msgs.msg import Marker, MarkerArray  # noqa: E402

from ponytail_ros.recording.bag import (  # noqa: E402
    PARAMETERS_METADATA,
    BagError,
    BagReader,
    BagWriter,
)

from ros_helpers import plain  # noqa: E402

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[1]
SHARE = Path(sys.prefix) / 'share'
ROS_DISTRO = os.environ.get('ROS_DISTRO') or 'kilted'
# Float values exactly representable in float32, so float32 fields compare exactly.
F = [0.5, -1.25, 2.0, 0.125, 3.75, -0.0625]


def header(i, frame='world'):
    msg = PoseStamped().header
    msg.stamp = Time(sec=100 + i, nanosec=1000 * i)
    msg.frame_id = frame
    return msg


def pose(i):
    p = Pose()
    p.position.x, p.position.y, p.position.z = F[i % 6], F[(i + 1) % 6], F[(i + 2) % 6] + i
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = 0.0, 0.0, 0.6, 0.8
    return p


def pose_stamped(i):
    return PoseStamped(header=header(i), pose=pose(i))


def pose_array(i):
    return PoseArray(header=header(i, 'head'), poses=[pose(i + k) for k in range(4)])


def marker_array(i):
    markers = []
    for k, kind in enumerate((Marker.LINE_STRIP, Marker.SPHERE_LIST, Marker.TEXT_VIEW_FACING)):
        m = Marker(header=header(i), ns=f'strand{k}', id=k, type=kind, action=Marker.ADD)
        m.pose = pose(k)
        m.scale.x, m.scale.y, m.scale.z = 0.5, 0.25, 0.125
        m.color = ColorRGBA(r=1.0, g=0.5, b=0.25, a=1.0)
        m.lifetime = Duration(sec=1, nanosec=500)
        m.frame_locked = bool(k % 2)
        m.points = [Point(x=F[j], y=-F[j], z=float(j + i)) for j in range(5)]
        m.colors = [ColorRGBA(r=0.0, g=F[j] % 1, b=1.0, a=0.5) for j in range(5)]
        m.text = f'marker {k} of {i}'
        markers.append(m)
    return MarkerArray(markers=markers)


def diagnostic_array(i):
    status = [
        DiagnosticStatus(level=DiagnosticStatus.OK, name='ponytail/solver', message='ok',
                         hardware_id='sim', values=[KeyValue(key='iterations', value=str(i)),
                                                   KeyValue(key='residual', value='1e-9')]),
        DiagnosticStatus(level=DiagnosticStatus.WARN, name='ponytail/clock',
                         message='behind real time', hardware_id='sim', values=[]),
    ]
    return DiagnosticArray(header=header(i), status=status)


TOPICS = {
    '/ponytail/head_pose': (PoseStamped, pose_stamped),
    '/ponytail/poses': (PoseArray, pose_array),
    '/ponytail/markers': (MarkerArray, marker_array),
    '/diagnostics': (DiagnosticArray, diagnostic_array),
}
TYPE_NAMES = {
    '/ponytail/head_pose': 'geometry_msgs/msg/PoseStamped',
    '/ponytail/poses': 'geometry_msgs/msg/PoseArray',
    '/ponytail/markers': 'visualization_msgs/msg/MarkerArray',
    '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray',
}


@pytest.fixture(params=[True, False], ids=['background', 'foreground'])
def recorded(tmp_path, request):
    """A finished bag with 5 messages on each topic; returns (path, [(topic, msg, t_ns)]).
    Written on the writer thread and in the caller's (``background=False``, the offline
    replay's): the same file either way."""
    path = tmp_path / 'run.mcap'
    written = []
    with BagWriter(path, background=request.param) as writer:
        for name, (cls, _) in TOPICS.items():
            qos = (QoSProfile(depth=1, durability=QoSDurabilityPolicy.TRANSIENT_LOCAL)
                   if cls is MarkerArray else 10)
            # Declared by class, except one by type string to cover both forms.
            msg_type = TYPE_NAMES[name] if name == '/diagnostics' else cls
            writer.add_topic(name, msg_type, qos=qos)
        for i in range(5):
            for k, (name, (_, make)) in enumerate(TOPICS.items()):
                t_ns = 1_700_000_000_000_000_000 + i * 10_000_000 + k
                msg = make(i)
                writer.write(name, msg, t_ns)
                written.append((name, msg, t_ns))
    return path, written


# -- round trips -------------------------------------------------------------------------------


def test_round_trip_with_bag_reader(recorded):
    path, written = recorded
    reader = BagReader(path)
    assert reader.topics() == TYPE_NAMES
    got = list(reader.messages())
    assert [(name, TYPE_NAMES[name], msg, t) for name, msg, t in written] == got
    only = list(reader.messages(topics={'/ponytail/poses': PoseArray}))
    assert [m for _, _, m, _ in only] == [m for n, m, _ in written if n == '/ponytail/poses']
    assert len(only[0][2].poses) == 4


def test_rosbags_decodes_with_the_schemas_in_the_file(recorded):
    """rosbags builds its types from our schema texts; their RIHS01 hashes must be rosidl's."""
    highlevel = pytest.importorskip('rosbags.highlevel')
    path, written = recorded
    with highlevel.AnyReader([path]) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == TYPE_NAMES
        got = [(c.topic, plain(reader.deserialize(raw, c.msgtype)), t)
               for c, t, raw in reader.messages()]
        hashes = {c.msgtype: reader.typestore.hash_rihs01(c.msgtype) for c in reader.connections}
    assert got == [(name, plain(msg), t) for name, msg, t in written]
    with open(path, 'rb') as f:
        summary = make_reader(f).get_summary()
    for channel in summary.channels.values():
        type_name = summary.schemas[channel.schema_id].name
        assert channel.metadata['topic_type_hash'] == hashes[type_name]


def test_rosbags_decodes_with_its_kilted_typestore(recorded):
    highlevel = pytest.importorskip('rosbags.highlevel')
    typesys = pytest.importorskip('rosbags.typesys')
    store = getattr(typesys.Stores, 'ROS2_KILTED', typesys.Stores.LATEST)
    typestore = typesys.get_typestore(store)
    path, written = recorded
    with highlevel.AnyReader([path], default_typestore=typestore) as reader:
        got = [(c.topic, plain(typestore.deserialize_cdr(raw, c.msgtype)), t)
               for c, t, raw in reader.messages()]
    assert got == [(name, plain(msg), t) for name, msg, t in written]
    for type_name in TYPE_NAMES.values():
        assert typestore.hash_rihs01(type_name) == type_hash_from_share(type_name)


# -- rosbag2 layout ----------------------------------------------------------------------------


def type_hash_from_share(type_name):
    package, _, name = type_name.split('/')
    description = json.loads((SHARE / package / 'msg' / f'{name}.json').read_text())
    return next(h['hash_string'] for h in description['type_hashes']
                if h['type_name'] == type_name)


def msg_text(type_name):
    package, name = type_name.split('/')
    return (SHARE / package / 'msg' / f'{name}.msg').read_text()


def test_layout_matches_rosbag2(recorded):
    path, written = recorded
    with open(path, 'rb') as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
        records = list(reader.iter_messages(log_time_order=False))
    assert header.profile == 'ros2'
    assert header.library

    assert sorted(s.name for s in summary.schemas.values()) == sorted(TYPE_NAMES.values())
    for schema in summary.schemas.values():
        assert schema.encoding == 'ros2msg'
        text = schema.data.decode()
        assert text.startswith(msg_text(schema.name.replace('/msg/', '/')))
        sections = text.split('\n' + '=' * 80 + '\n')
        names = [s.split('\n', 1)[0] for s in sections[1:]]
        assert all(n.startswith('MSG: ') for n in names)
        assert len(names) == len(set(names)), 'each dependency is written once'
    # rosbag2's order: depth first, the dependencies of each message sorted by name.
    pose_array_schema = next(s for s in summary.schemas.values()
                             if s.name == 'geometry_msgs/msg/PoseArray')
    order = ['geometry_msgs/Pose', 'geometry_msgs/Point', 'geometry_msgs/Quaternion',
             'std_msgs/Header', 'builtin_interfaces/Time']
    expected = msg_text('geometry_msgs/PoseArray') + ''.join(
        f'\n{"=" * 80}\nMSG: {n}\n{msg_text(n)}' for n in order)
    assert pose_array_schema.data.decode() == expected

    for channel in summary.channels.values():
        type_name = summary.schemas[channel.schema_id].name
        assert channel.message_encoding == 'cdr'
        assert set(channel.metadata) == {'offered_qos_profiles', 'topic_type_hash'}
        assert channel.metadata['topic_type_hash'].startswith('RIHS01_')
        assert channel.metadata['topic_type_hash'] == type_hash_from_share(type_name)
        (qos,) = yaml.safe_load(channel.metadata['offered_qos_profiles'])
        assert qos['history'] == 'keep_last' and qos['reliability'] == 'reliable'
        assert set(qos) == {'history', 'depth', 'reliability', 'durability', 'deadline',
                            'lifespan', 'liveliness', 'liveliness_lease_duration',
                            'avoid_ros_namespace_conventions'}
        if channel.topic == '/ponytail/markers':
            assert (qos['depth'], qos['durability']) == (1, 'transient_local')
        else:
            assert (qos['depth'], qos['durability']) == (10, 'volatile')

    assert summary.statistics.message_count == len(written)
    assert [(m.log_time, m.publish_time) for _, _, m in records] == [(t, t) for *_, t in written]

    metadata = BagReader(path).metadata()
    assert metadata['rosbag2']['ROS_DISTRO'] == ROS_DISTRO
    bag = yaml.safe_load(metadata['rosbag2']['serialized_metadata'])
    assert bag['version'] == 9 and bag['storage_identifier'] == 'mcap'
    assert bag['ros_distro'] == ROS_DISTRO
    assert bag['message_count'] == len(written)
    assert bag['starting_time']['nanoseconds_since_epoch'] == written[0][2]
    assert bag['duration']['nanoseconds'] == written[-1][2] - written[0][2]
    assert bag['relative_file_paths'] == [path.name]
    assert {t['topic_metadata']['name']: (t['topic_metadata']['type'], t['message_count'])
            for t in bag['topics_with_message_count']} == {
                name: (type_name, 5) for name, type_name in TYPE_NAMES.items()}


def test_parameters_metadata_round_trip(tmp_path):
    path = tmp_path / 'params.mcap'
    parameters = {'chain.segments': '24', 'chain.damping': '0.3', 'solver': 'xpbd'}
    with BagWriter(path) as writer:
        writer.write_metadata(PARAMETERS_METADATA, parameters)
        with pytest.raises(BagError, match='str'):
            writer.write_metadata('bad', {'n': 3})
        with pytest.raises(BagError, match='reserved'):
            writer.write_metadata('rosbag2', {})
    assert BagReader(path).metadata()[PARAMETERS_METADATA] == parameters


# -- errors ------------------------------------------------------------------------------------


def test_existing_file_is_not_overwritten(tmp_path):
    path = tmp_path / 'keep.mcap'
    path.write_bytes(b'precious')
    with pytest.raises(BagError, match='already exists') as info:
        BagWriter(path)
    assert str(path) in str(info.value)
    assert path.read_bytes() == b'precious'
    with BagWriter(path, overwrite=True):
        pass
    assert BagReader(path).topics() == {}


def test_missing_folder_is_a_clear_error(tmp_path):
    path = tmp_path / 'no' / 'such' / 'folder' / 'run.mcap'
    with pytest.raises(BagError, match='does not exist') as info:
        BagWriter(path)
    assert str(path) in str(info.value)


@pytest.mark.skipif(os.geteuid() == 0, reason='root ignores file permissions')
def test_unwritable_folder_is_a_clear_error(tmp_path):
    folder = tmp_path / 'ro'
    folder.mkdir(mode=0o500)
    with pytest.raises(BagError, match='permission denied'):
        BagWriter(folder / 'run.mcap')


@pytest.mark.skipif(not os.path.exists('/dev/full'), reason='needs /dev/full')
def test_full_disk_at_open_is_a_clear_error():
    with pytest.raises(BagError, match='No space left'):
        BagWriter('/dev/full', overwrite=True)


def test_misuse_raises_clear_errors(recorded, tmp_path):
    path, _ = recorded
    reader = BagReader(path)
    with pytest.raises(BagError, match='no topic /nope'):
        list(reader.messages(topics=['/nope']))
    with pytest.raises(BagError, match='holds geometry_msgs/msg/PoseStamped'):
        list(reader.messages(topics={'/ponytail/head_pose': PoseArray}))
    (tmp_path / 'notes.mcap').write_text('not a bag at all')
    with pytest.raises(BagError, match='not an MCAP file'):
        BagReader(tmp_path / 'notes.mcap')
    with pytest.raises(BagError, match='No such file'):
        BagReader(tmp_path / 'missing.mcap')

    writer = BagWriter(tmp_path / 'w.mcap')
    writer.add_topic('/pose', PoseStamped)
    with pytest.raises(BagError, match='not added'):
        writer.write('/other', PoseStamped(), 0)
    with pytest.raises(BagError, match='records geometry_msgs/msg/PoseStamped'):
        writer.write('/pose', PoseArray(), 0)
    with pytest.raises(BagError, match='already added'):
        writer.add_topic('/pose', PoseStamped)
    writer.close()
    writer.close()  # idempotent
    with pytest.raises(BagError, match='closed'):
        writer.write('/pose', PoseStamped(), 0)
    assert writer.error is None


# -- crash recovery ----------------------------------------------------------------------------


def test_truncated_file_yields_the_complete_chunks(tmp_path):
    path = tmp_path / 'full.mcap'
    with BagWriter(path, chunk_size=2048) as writer:
        writer.add_topic('/pose', PoseStamped)
        for i in range(200):
            writer.write('/pose', pose_stamped(i), i * 1_000_000)
    with open(path, 'rb') as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) >= 5
    data = path.read_bytes()
    cut_path = tmp_path / 'cut.mcap'
    for index in (1, 3, len(chunks) - 1):
        chunk = chunks[index]
        previous_end_time = chunks[index - 1].message_end_time
        start, end = chunk.chunk_start_offset, chunk.chunk_start_offset + chunk.chunk_length
        for cut in (start + 5, end - 1):
            cut_path.write_bytes(data[:cut])
            reader = BagReader(cut_path)
            assert reader.topics() == {'/pose': 'geometry_msgs/msg/PoseStamped'}
            got = list(reader.messages())
            assert [t for *_, t in got] == list(range(0, previous_end_time + 1, 1_000_000))
            assert got[-1][2] == pose_stamped(len(got) - 1)
        cut_path.write_bytes(data[:end])
        assert [t for *_, t in BagReader(cut_path).messages()][-1] == chunk.message_end_time
    # The rosbag2 record written at open survives any cut after it.
    assert BagReader(cut_path).metadata()['rosbag2']['ROS_DISTRO'] == ROS_DISTRO


def test_idle_writer_flushes_its_partial_chunk(tmp_path):
    path = tmp_path / 'idle.mcap'
    with BagWriter(path, chunk_duration_ns=50_000_000) as writer:
        writer.add_topic('/pose', PoseStamped)
        for i in range(3):
            writer.write('/pose', pose_stamped(i), i)
        # No further message comes; the writer must write the partial chunk out on its own
        # (after ~50 ms idle). Poll rather than sleep a fixed time: CI machines are loaded.
        snapshot = tmp_path / 'snapshot.mcap'
        deadline = time.monotonic() + 20
        recovered = []
        while not recovered and time.monotonic() < deadline:
            time.sleep(0.05)
            shutil.copyfile(path, snapshot)  # what a SIGKILL at this moment would leave
            recovered = [m for _, _, m, _ in BagReader(snapshot).messages()]
        assert recovered == [pose_stamped(i) for i in range(3)]


CHUNK_DURATION_NS = 500_000_000
PERIOD_NS = 1_000_000
CHILD = textwrap.dedent(f'''
    import sys, time
    from geometry_msgs.msg import PoseStamped
    from ponytail_ros.recording.bag import BagWriter

    path, mode = sys.argv[1], sys.argv[2]
    writer = BagWriter(path, chunk_duration_ns={CHUNK_DURATION_NS})
    if mode == 'term':
        writer.close_on_signals()
    writer.add_topic('/pose', PoseStamped)
    msg = PoseStamped()
    i = 0
    while True:
        log_time_ns = i * {PERIOD_NS}
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(log_time_ns, 10**9)
        msg.pose.position.x = float(i)
        writer.write('/pose', msg, log_time_ns)
        if i % 10 == 0:
            print(i, log_time_ns, flush=True)  # written (queued) up to here
        i += 1
        time.sleep(0.001)
''')


def run_child(path, mode, until_log_ns, signum):
    """Run CHILD until it has queued messages up to ``until_log_ns`` of log time, then send
    ``signum``; return (last index, last log time) the child reported as queued.

    The wait is on the child's own progress, not on wall time: on a loaded machine its 1 ms
    loop may run several times slower, and a fixed wait could end before a chunk is due.
    """
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(REPO)] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]))
    child = subprocess.Popen([sys.executable, '-c', CHILD, str(path), mode],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        lines = []
        while True:
            line = child.stdout.readline()  # blocks until the child writes
            assert line, child.stderr.read()
            lines.append(line)
            if int(line.split()[1]) >= until_log_ns:
                break
        child.send_signal(signum)
        out, err = child.communicate(timeout=60)
    finally:
        child.kill()
    assert child.returncode == -signum, err
    index, log_time_ns = map(int, (''.join(lines) + out).split('\n')[-2].split())
    return index, log_time_ns


def test_sigkill_loses_at_most_the_documented_bound(tmp_path):
    path = tmp_path / 'killed.mcap'
    _, last_written_ns = run_child(path, 'kill', 3 * CHUNK_DURATION_NS, signal.SIGKILL)
    got = list(BagReader(path).messages())
    assert got, 'nothing recovered'
    assert [m.pose.position.x for _, _, m, _ in got] == [float(i) for i in range(len(got))]
    last_recovered_ns = got[-1][3]
    # Lost: the chunk being built (< CHUNK_DURATION_NS of log time) and whatever was still
    # queued for the writer thread; allow 100 ms of log time for the latter.
    assert last_written_ns - last_recovered_ns <= CHUNK_DURATION_NS + 100_000_000


def test_sigterm_finalises_the_file(tmp_path):
    path = tmp_path / 'terminated.mcap'
    last_index, _ = run_child(path, 'term', CHUNK_DURATION_NS // 2, signal.SIGTERM)
    with open(path, 'rb') as f:
        summary = make_reader(f).get_summary()  # needs the footer and summary
    assert summary is not None
    got = list(BagReader(path).messages())
    assert summary.statistics.message_count == len(got) > last_index
    assert [m.pose.position.x for _, _, m, _ in got] == [float(i) for i in range(len(got))]
    bag = yaml.safe_load(BagReader(path).metadata()['rosbag2']['serialized_metadata'])
    assert bag['message_count'] == len(got)


DISK_FULL_CHILD = textwrap.dedent('''
    import resource, signal, sys, time
    from geometry_msgs.msg import PoseStamped
    from ponytail_ros.recording.bag import BagWriter

    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG
    resource.setrlimit(resource.RLIMIT_FSIZE, (32 * 1024, resource.RLIM_INFINITY))
    writer = BagWriter(sys.argv[1], chunk_size=4096)
    writer.add_topic('/pose', PoseStamped)
    for i in range(2000):
        writer.write('/pose', PoseStamped(), i * 1000000)  # must never raise
    deadline = time.monotonic() + 10
    while writer.error is None and time.monotonic() < deadline:
        time.sleep(0.01)
    writer.close()
    print('ERROR', writer.error)
''')


def test_disk_full_stops_recording_without_crashing_the_caller(tmp_path):
    path = tmp_path / 'full.mcap'
    env = dict(os.environ, PYTHONPATH=str(REPO))
    result = subprocess.run([sys.executable, '-c', DISK_FULL_CHILD, str(path)], env=env,
                            capture_output=True, text=True, timeout=30)
    assert result.returncode == 0, result.stderr
    assert 'ERROR' in result.stdout and 'File too large' in result.stdout, result.stdout
    assert str(path) in result.stdout
    recovered = list(BagReader(path).messages())
    assert 0 < len(recovered) < 2000
