"""The ponytail node in its own process, real DDS between processes: two characters side by side
in their own namespaces, the head demo as a third process, clean shutdown on SIGINT/SIGTERM, and
a bad params file rejected at start-up.

Isolation: the children inherit this test run's ``ROS_DOMAIN_ID`` (set in conftest.py) and
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, so parallel runs on one machine never meet.
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

from geometry_msgs.msg import PoseArray, PoseStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402

from ponytail_ros.app.param_values import values_from_params_file  # noqa: E402

from ros_helpers import attach_point, check_geometry, pose_msg  # noqa: E402

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / 'config' / 'ponytail.yaml'
N_SEG = 12          # config/ponytail.yaml
LENGTH = 0.35
ATTACH = values_from_params_file(CONFIG)['ponytail.attach']     # as the nodes read it


def child_env():
    env = dict(os.environ)
    env['PYTHONPATH'] = str(ROOT) + os.pathsep + env.get('PYTHONPATH', '')
    env['PYTHONUNBUFFERED'] = '1'
    return env


def spawn(module, *ros_args):
    return subprocess.Popen(
        [sys.executable, '-m', module, '--ros-args', *ros_args],
        env=child_env(), cwd=str(ROOT), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)


def stop(proc, sig):
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        out, err = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    return proc.returncode, out, err


@pytest.fixture
def processes():
    procs = []
    yield procs
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.communicate()


def test_two_namespaced_nodes_side_by_side_and_clean_shutdown(ros_context, processes):
    alice = spawn('ponytail_ros.node', '--params-file', str(CONFIG), '-r', '__ns:=/alice',
                  '-p', 'diagnostics_period:=0.5')
    bob = spawn('ponytail_ros.node', '--params-file', str(CONFIG), '-r', '__ns:=/bob',
                '-p', 'ponytail.n_segments:=5')
    demo = spawn('ponytail_ros.ros.head_demo', '-r', '__ns:=/alice', '-p', 'motion:=still',
                 '-p', 'origin:=[1.0, 2.0, 1.6]', '-p', 'frame_id:=map')
    processes.extend([alice, bob, demo])

    # Bob's head comes from this process; Alice's from the demo process.
    node = rclpy.create_node('observer', context=ros_context)
    bob_head = node.create_publisher(PoseStamped, '/bob/head_pose', 10)
    p_bob, q_bob = np.array([-3.0, 0.5, 1.2]), np.array([0.0, 0.0, 0.0, 1.0])
    node.create_timer(0.01, lambda: bob_head.publish(
        pose_msg(node.get_clock().now().nanoseconds * 1e-9, p_bob, q_bob, 'odom')))
    got = {'alice': [], 'bob': [], 'unqualified': []}
    node.create_subscription(PoseArray, '/alice/segment_poses', got['alice'].append, 50)
    node.create_subscription(PoseArray, '/bob/segment_poses', got['bob'].append, 50)
    node.create_subscription(PoseArray, '/segment_poses', got['unqualified'].append, 50)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    end = time.monotonic() + 20.0
    while time.monotonic() < end and not (len(got['alice']) >= 10 and len(got['bob']) >= 10):
        ex.spin_once(timeout_sec=0.01)
        for p in (alice, bob, demo):
            assert p.poll() is None, p.communicate()
    assert len(got['alice']) >= 10 and len(got['bob']) >= 10
    a = got['alice'][-1]
    b = got['bob'][-1]
    oa, _ = check_geometry(a, N_SEG, LENGTH)
    ob, _ = check_geometry(b, 5, LENGTH)
    # Each character's chain hangs from its own head, in its own head's frame.
    assert np.linalg.norm(oa[0] - attach_point([1.0, 2.0, 1.6], [0, 0, 0, 1], ATTACH)) < 1e-6
    assert np.linalg.norm(ob[0] - attach_point(p_bob, q_bob, ATTACH)) < 1e-6
    assert a.header.frame_id == 'map' and b.header.frame_id == 'odom'
    assert got['unqualified'] == []          # relative names: nothing outside the namespaces
    # The graph is eventually consistent: a node's name may reach us after its messages.
    want = {('ponytail', '/alice'), ('ponytail', '/bob')}
    end = time.monotonic() + 10.0
    while not want <= set(node.get_node_names_and_namespaces()) and time.monotonic() < end:
        ex.spin_once(timeout_sec=0.05)
    assert want <= set(node.get_node_names_and_namespaces())
    ex.shutdown()
    node.destroy_node()

    # Ctrl-C and an external shutdown (SIGTERM) end the nodes cleanly, without a traceback.
    for proc, sig in ((alice, signal.SIGINT), (bob, signal.SIGTERM), (demo, signal.SIGINT)):
        code, out, err = stop(proc, sig)
        assert code == 0, err
        assert 'Traceback' not in err and 'Traceback' not in out, err


def test_invalid_parameters_rejected_at_start_up_with_the_name(processes):
    proc = spawn('ponytail_ros.node', '--params-file', str(CONFIG),
                 '-p', 'ponytail.attach:=[0.1, 0.2]')
    processes.append(proc)
    out, err = proc.communicate(timeout=20)
    assert proc.returncode == 2
    assert 'ponytail.attach' in err and 'Traceback' not in err


def test_unknown_executor_refused_at_start_up_with_the_allowed_values(processes):
    env = dict(child_env(), PONYTAIL_EXECUTOR='multi')
    proc = subprocess.Popen([sys.executable, '-m', 'ponytail_ros.node', '--ros-args',
                             '--params-file', str(CONFIG)], env=env, cwd=str(ROOT),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    processes.append(proc)
    out, err = proc.communicate(timeout=20)
    assert proc.returncode == 2
    assert "PONYTAIL_EXECUTOR = 'multi'" in err and 'events or single' in err
    assert 'Traceback' not in err
