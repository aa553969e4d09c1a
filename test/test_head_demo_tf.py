"""The head demo's TF mode: its head as a TF tree (world -> base_link -> neck -> head), the
static edge on /tf_static for late joiners, the moving ones on /tf, composed to the head pose it
publishes on ``head_pose`` at the same stamp (to rounding). Heard by a plain subscriber in
another process, as RViz would hear them."""
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('tf2_msgs', reason='tf2_msgs is not importable (the set-up builds it)')

from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from ponytail_ros.app.head_tree import Transform, compose, head_tree, yaw_quat  # noqa: E402
from ponytail_ros.core.rotations import quat_from_rotvec, quat_rotate  # noqa: E402
from ponytail_ros.ros.head_demo import namespace_prefix  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def test_tree_composes_to_the_head_pose_and_base_link_stays_upright_on_the_ground():
    rng = np.random.default_rng(3)
    for _ in range(50):
        p = rng.normal(size=3) + [0.0, 0.0, 1.6]
        q = quat_from_rotvec(rng.normal(size=3))
        tree = head_tree(p, q, 1.5)
        world_head = compose(compose(tree.base, tree.neck), tree.head)
        assert np.abs(world_head.translation - p).max() < 1e-12
        assert min(np.abs(world_head.rotation - q).max(),
                   np.abs(world_head.rotation + q).max()) < 1e-12
        assert tree.base.translation[2] == 0.0 and tree.base.translation[:2].tolist() == \
            p[:2].tolist()
        z_up = quat_rotate(tree.base.rotation, np.array([0.0, 0.0, 1.0]))
        assert np.abs(z_up - [0, 0, 1]).max() < 1e-15                # yaw only
        # base_link's X is the head's X on the ground plane
        hx = quat_rotate(q, np.array([1.0, 0.0, 0.0]))
        bx = quat_rotate(tree.base.rotation, np.array([1.0, 0.0, 0.0]))
        assert np.abs(bx[:2] * math.hypot(*hx[:2]) - hx[:2]).max() < 1e-12
        assert tree.neck.translation.tolist() == [0.0, 0.0, 1.5]


def test_yaw_of_a_pure_yaw_is_itself():
    q = quat_from_rotvec(np.array([0.0, 0.0, 2.5]))
    assert np.abs(yaw_quat(q) - q).max() < 1e-15


def test_namespace_prefix():
    assert [namespace_prefix(n) for n in ('/', '/alice', '/crowd/a')] == ['', 'alice/',
                                                                          'crowd/a/']


def _tf(msg):
    t, r = msg.transform.translation, msg.transform.rotation
    return Transform(np.array([t.x, t.y, t.z]), np.array([r.x, r.y, r.z, r.w]))


def _stamp(header):
    return header.stamp.sec, header.stamp.nanosec


@pytest.mark.ros
@pytest.mark.parametrize('namespace', ['/', '/alice'])
def test_head_demo_tf_mode_publishes_the_tree_that_composes_to_head_pose(ros_context,
                                                                          namespace):
    prefix = namespace_prefix(namespace)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    proc = subprocess.Popen(
        [sys.executable, '-m', 'ponytail_ros.ros.head_demo', '--ros-args', '-p', 'output:=both',
         '-p', 'rate:=50.0', '-r', f'__ns:={namespace}'],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    node = rclpy.create_node('tf_listener', context=ros_context)
    dynamic, static, heads = [], [], {}
    try:
        time.sleep(1.0)      # the static edge was published before we subscribed: latched
        node.create_subscription(TFMessage, '/tf', dynamic.append, 100)
        node.create_subscription(TFMessage, '/tf_static', static.append, QoSProfile(
            depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL,
            reliability=ReliabilityPolicy.RELIABLE))
        node.create_subscription(PoseStamped, f'{namespace.rstrip("/")}/head_pose',
                                 lambda m: heads.__setitem__(_stamp(m.header), m), 10)
        executor = SingleThreadedExecutor(context=ros_context)
        executor.add_node(node)
        deadline = time.monotonic() + 30
        while (len(dynamic) < 20 or not static) and time.monotonic() < deadline \
                and proc.poll() is None:
            executor.spin_once(timeout_sec=0.1)
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=10)
        node.destroy_node()
    assert static and len(dynamic) >= 20, err
    (neck,) = static[0].transforms
    assert (neck.header.frame_id, neck.child_frame_id) == (prefix + 'base_link', prefix + 'neck')
    matched = 0
    for msg in dynamic:
        base, head = msg.transforms
        assert (base.header.frame_id, base.child_frame_id) == ('world', prefix + 'base_link')
        assert (head.header.frame_id, head.child_frame_id) == (prefix + 'neck', prefix + 'head')
        assert _stamp(base.header) == _stamp(head.header)
        pose = heads.get(_stamp(base.header))
        if pose is None:
            continue
        matched += 1
        world_head = compose(compose(_tf(base), _tf(neck)), _tf(head))
        p, o = pose.pose.position, pose.pose.orientation
        assert np.abs(world_head.translation - [p.x, p.y, p.z]).max() < 1e-12
        q = np.array([o.x, o.y, o.z, o.w])
        assert min(np.abs(world_head.rotation - q).max(),
                   np.abs(world_head.rotation + q).max()) < 1e-12
    assert matched >= 10


def test_tf_output_without_tf2_msgs_is_refused_naming_output(monkeypatch):
    from ponytail_ros.ros import head_demo
    monkeypatch.setitem(sys.modules, 'tf2_msgs.msg', None)     # import fails
    with pytest.raises(ValueError, match=r'^output needs tf2_msgs.*output:=pose'):
        head_demo._tf_types()


def test_demo_tf_without_tf2_msgs_exits_2_naming_the_option(monkeypatch, capsys):
    from ponytail_ros import demo
    monkeypatch.setitem(sys.modules, 'tf2_msgs.msg', None)
    assert demo.main(['--tf', '--duration', '1']) == 2
    err = capsys.readouterr().err
    assert err.startswith('ponytail_demo: error: --tf needs tf2_msgs') and err.count('\n') == 1


@pytest.mark.ros
def test_demo_tf_the_node_swings_from_the_head_it_reads_from_tf():
    """End to end: the head demo's tree (output: tf, no head_pose) -> the node with
    head_frame: head -> segment poses whose root follows the head. Needs the node's TF input
    (``head_frame``); skipped where the node lacks it."""
    from ponytail_ros.app.parameters import GLOBAL_PARAMS
    from ponytail_ros.demo import TF_NODE_PARAMS, run_demo, summarize
    from ponytail_ros.resources import config_path
    if not set(TF_NODE_PARAMS) <= {p.name for p in GLOBAL_PARAMS}:
        pytest.skip('this node has no head_frame / fixed_frame parameters (TF input)')
    from conftest import TEST_DOMAIN_ID
    data = run_demo(8.0, config_path('ponytail.yaml'), domain_id=TEST_DOMAIN_ID, tf=True)
    assert len(data['t']) > 100          # segments came, so the head came over TF
    assert len(data['head_t']) == 0      # and not over head_pose (output: tf)
    _, gap = summarize(data)
    assert gap < 1e-9
