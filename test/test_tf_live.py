"""TF in and out, live, between processes: a body on TF published by a plain rclpy process
(``_tf_publisher.py``: world -> base_link moving, base_link -> neck static, neck -> head
moving), one node taking its head from TF (``/alice``, ``head_frame: head``), another taking
the same head composed by hand as a ``PoseStamped`` (``/bob``); this process subscribes the
nodes' segment poses and their live ``/tf``.

Skipped (with the reason) when tf2_msgs is not importable: the node can neither subscribe nor
publish TF then.
"""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('tf2_msgs.msg', reason='tf2_msgs is not installed: no live TF')

from geometry_msgs.msg import PoseArray  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from ponytail_ros.app.param_values import values_from_params_file  # noqa: E402
from ponytail_ros.app.wire import tf_message_fields  # noqa: E402
from ponytail_ros.recording.bag import BagReader  # noqa: E402
from ponytail_ros.recording.offline import replay  # noqa: E402

from ros_helpers import TIMEOUT_SCALE, attach_point, check_geometry  # noqa: E402

pytestmark = pytest.mark.ros

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
CONFIG = ROOT / 'config' / 'ponytail.yaml'
N_SEG = 12          # config/ponytail.yaml
LENGTH = 0.35
ATTACH = values_from_params_file(CONFIG)['ponytail.attach']
sys.path.insert(0, str(HERE))
import _tf_publisher as body  # noqa: E402


def child_env():
    env = dict(os.environ)
    env['PYTHONPATH'] = str(ROOT) + os.pathsep + env.get('PYTHONPATH', '')
    env['PYTHONUNBUFFERED'] = '1'
    return env


def spawn(*argv):
    return subprocess.Popen([sys.executable, *argv], env=child_env(), cwd=str(ROOT),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def stop(proc):
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        return proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.communicate()


@pytest.fixture
def processes():
    procs = []
    yield procs
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.communicate()


def _stamp_ns(msg):
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def _live_tf(tf_raw):
    """Children of each namespace's transforms (checking their parent), and alice's messages
    by stamp."""
    children = {'alice': set(), 'bob': set()}
    by_stamp = {}
    for data in tf_raw:
        transforms = tf_message_fields(data)
        for _, _, parent, child, _, _ in transforms:
            ns = child.split('/')[0]
            if ns in children:
                assert parent == 'world'
                children[ns].add(child)
        if transforms and transforms[0][3].startswith('alice/'):
            by_stamp[transforms[0][0] * 10**9 + transforms[0][1]] = data
    return children, by_stamp


def _recorded_tf(path):
    recorded = {}
    for _, _, data, _ in BagReader(path).messages({'/tf': 'tf2_msgs/msg/TFMessage'}, raw=True):
        (sec, nanosec, *_), *_ = tf_message_fields(data)
        recorded[sec * 10**9 + nanosec] = data
    return recorded


def test_head_from_tf_and_segments_on_tf_between_processes(ros_context, processes, tmp_path):
    publisher = spawn(str(HERE / '_tf_publisher.py'))
    processes.append(publisher)
    record = tmp_path / 'alice.mcap'
    # output_stamp simulated: each pose is the chain at its stamp, the head interpolated there
    common = ('-m', 'ponytail_ros.node', '--ros-args', '--params-file', str(CONFIG), '-p',
              'output_stamp:=simulated')
    alice = spawn(*common, '-r', '__ns:=/alice', '-p', 'head_frame:=head',
                  '-p', f'record_path:={record}')
    bob = spawn(*common, '-r', '__ns:=/bob')
    processes.extend([alice, bob])
    line = publisher.stdout.readline()
    assert line.startswith('T0 '), publisher.communicate()
    t0 = int(line.split()[1])

    node = rclpy.create_node('observer', context=ros_context)
    got = {'alice': [], 'bob': []}
    node.create_subscription(PoseArray, '/alice/segment_poses', got['alice'].append, 100)
    node.create_subscription(PoseArray, '/bob/segment_poses', got['bob'].append, 100)
    tf_raw = []
    node.create_subscription(TFMessage, '/tf', tf_raw.append, QoSProfile(
        depth=100, reliability=ReliabilityPolicy.RELIABLE), raw=True)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    end = time.monotonic() + 30.0 * TIMEOUT_SCALE
    # Alice runs until 80 of its 120 Hz ticks are out: its recording then spans the 60 head
    # poses (TF at 100 Hz) checked below, whatever the two nodes' start-up order.
    while time.monotonic() < end and (len(got['alice']) < 80 or len(got['bob']) < 60):
        ex.spin_once(timeout_sec=0.01)
        for p in (publisher, alice, bob):
            assert p.poll() is None, p.communicate()
    assert min(len(v) for v in got.values()) >= 60

    # Each root on its head's attachment point, the head composed by hand from the motion.
    for name in ('alice', 'bob'):
        for msg in got[name][-40:]:
            origins, _ = check_geometry(msg, N_SEG, LENGTH)
            p, q = body.head_in_world((_stamp_ns(msg) - t0) * 1e-9)
            assert msg.header.frame_id == 'world'
            assert np.linalg.norm(origins[0] - attach_point(p, q, ATTACH)) <= 1e-6, name

    # Live /tf: every segment as <namespace>/<chain>/<i>, child of fixed_frame; disjoint.
    children, by_stamp = _live_tf(tf_raw)
    assert children == {ns: {f'{ns}/ponytail/{i}' for i in range(N_SEG)}
                        for ns in ('alice', 'bob')}
    ex.shutdown()
    node.destroy_node()
    for proc in (alice, bob, publisher):
        out, err = stop(proc)
        assert 'Traceback' not in err, err

    # What alice recorded on /tf is, byte for byte, what it published live.
    recorded = _recorded_tf(record)
    common_stamps = set(recorded) & set(by_stamp)
    assert len(common_stamps) >= 50
    assert all(recorded[s] == by_stamp[s] for s in common_stamps)
    # the head it composed is recorded on its head_pose (replayed from there)
    heads = [m for _, _, m, _ in BagReader(record).messages('/alice/head_pose')]
    assert len(heads) >= 60 and heads[-1].header.frame_id == 'world'
    # ... and ponytail_replay replays the recording from them, not from its /tf (the node's
    # own segments)
    result = replay(record, tmp_path / 'again.mcap')
    assert result.head_samples == len(heads) and result.ticks >= 60
