"""Every executable: ``--help``, one-line errors naming the cause, exit status 2 for bad input;
the node's start-up and live-parameter messages in words."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402

pytest.importorskip('rosbags')
from ponytail_ros.node import PonytailNode  # noqa: E402

from ros_helpers import TIMEOUT_SCALE, head_samples, rosbags_bag  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
EXECUTABLES = {
    'ponytail_node': 'ponytail_ros.node',
    'ponytail_head_demo': 'ponytail_ros.ros.head_demo',
    'ponytail_replay': 'ponytail_ros.recording.cli',
    'ponytail_demo': 'ponytail_ros.demo',
}


def run_module(module, *args, timeout=60):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    return subprocess.run([sys.executable, '-m', module, *map(str, args)], env=env,
                          cwd=str(ROOT), capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize('program', sorted(EXECUTABLES))
def test_every_executable_prints_help_and_exits_0(program):
    done = run_module(EXECUTABLES[program], '--help')
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith('usage:') and program.split('_', 1)[1] in done.stdout
    assert done.stderr == ''           # the node was not started (it logs to stderr)


def test_replay_repair_has_help_too():
    done = run_module(EXECUTABLES['ponytail_replay'], 'repair', '--help')
    assert done.returncode == 0 and 'ponytail_replay repair' in done.stdout


@pytest.mark.parametrize('program, args, words', [
    ('ponytail_head_demo', ['--ros-args', '-p', 'rate:=-1.0'],
     ['rate = -1.0', 'out of range', 'allowed 1.0 to 2000.0']),
    ('ponytail_head_demo', ['--ros-args', '-p', 'motion:=dance'],
     ["motion = 'dance'", 'script, sway, still']),
    ('ponytail_node', ['--ros-args', '-p', 'rate:=-1.0'], ['rate', '-1.0']),
    ('ponytail_replay', ['compare', 'a.mcap', 'b.mcap', '--plot', '/no/such/dir/x.png'],
     ['--plot /no/such/dir/x.png', 'folder /no/such/dir does not exist']),
    ('ponytail_replay', ['/no/such/in.mcap', '-o', '/tmp/never.mcap'],
     ['/no/such/in.mcap']),
    ('ponytail_demo', ['--config', '/no/such.yaml'], ['--config /no/such.yaml', 'no such file']),
    ('ponytail_demo', ['--duration', '-1'], ['--duration -1', 'must be > 0']),
])
def test_bad_input_is_one_line_naming_it_and_exit_2(program, args, words):
    done = run_module(EXECUTABLES[program], *args)
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2, done.stderr
    assert 'Traceback' not in done.stderr
    errors = [line for line in lines if 'error' in line or 'invalid' in line]
    assert len(errors) == 1, lines
    assert all(w in errors[0] for w in words), errors[0]


def test_compare_plot_into_a_missing_folder_checks_before_reading(tmp_path, capsys):
    from ponytail_ros.recording.cli import main
    bag = rosbags_bag(tmp_path, 'in', head_samples(20))
    code = main(['compare', str(bag), str(bag), '--plot', str(tmp_path / 'no' / 'x.png')])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and 'does not exist' in err[0]


# -- the node: start-up and live parameters ------------------------------------------------------


def spin_until(executor, pred, timeout=5.0):
    import time
    end = time.monotonic() + timeout * TIMEOUT_SCALE
    while time.monotonic() < end and not pred():
        executor.spin_once(timeout_sec=0.01)
    return pred()


def test_a_typo_in_the_params_file_is_warned_with_the_closest_name(ros_context, tmp_path):
    params = tmp_path / 'p.yaml'
    params.write_text('/**:\n  ros__parameters:\n    ponytail:\n      n_segmentz: 5\n'
                      '      damping: 0.002\n')
    node = PonytailNode(context=ros_context, cli_args=['--ros-args', '--params-file',
                                                       str(params)])
    try:
        assert [w for w in node.startup_warnings if 'tf2_msgs' not in w] == [
            "unknown parameter 'ponytail.n_segmentz' ignored (did you mean "
            "'ponytail.n_segments'?): not a parameter of /ponytail (params file or -p)"]
        assert node.get_parameter('ponytail.damping').value == 0.002
    finally:
        node.destroy_node()


def test_replay_warns_a_params_file_typo_with_the_closest_name(tmp_path, capsys):
    from ponytail_ros.recording.cli import main
    bag = rosbags_bag(tmp_path, 'in', head_samples(50))
    params = tmp_path / 'p.yaml'
    params.write_text('/**:\n  ros__parameters:\n    ponytail:\n      n_segmentz: 5\n')
    code = main([str(bag), '-o', str(tmp_path / 'out.mcap'), '--params', str(params)])
    err = capsys.readouterr().err
    assert code == 0
    assert (f"{params}: unknown parameter 'ponytail.n_segmentz' ignored (did you mean "
            f"'ponytail.n_segments'?)") in err


def test_live_parameter_refusals_name_the_parameter_and_the_types_in_words(ros_context):
    node = PonytailNode(context=ros_context)
    tester = rclpy.create_node('tester', context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(tester)
    try:
        client = AsyncParameterClient(tester, 'ponytail')
        assert spin_until(executor, lambda: client.services_are_ready())

        def set_remote(param):
            fut = client.set_parameters([param])
            assert spin_until(executor, fut.done)
            return fut.result().results[0]
        res = set_remote(Parameter('rate', value='fast'))
        assert not res.successful
        assert res.reason == "rate must be a number (double, e.g. 0.5), not a string ('fast')"
        res = set_remote(Parameter('ponytail.n_segmentz', value=5))
        assert not res.successful
        assert res.reason == ("'ponytail.n_segmentz' is not a parameter of /ponytail (did you "
                              "mean 'ponytail.n_segments'?)")
        res = set_remote(Parameter('ponytail.n_segments', value=5))
        assert res.successful and node.get_parameter('ponytail.n_segments').value == 5
        assert set_remote(Parameter('rate', value=60)).successful   # an int for a double
    finally:
        executor.shutdown()
        tester.destroy_node()
        node.destroy_node()


def test_two_nodes_with_one_name_are_warned_about(ros_context):
    a = PonytailNode(context=ros_context)
    b = PonytailNode(context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(a)
    executor.add_node(b)
    try:
        assert spin_until(executor, lambda: a.duplicate_name_warning is not None, 10.0)
        assert '2 nodes named /ponytail are running' in a.duplicate_name_warning
        assert '__ns:=' in a.duplicate_name_warning
    finally:
        executor.shutdown()
        a.destroy_node()
        b.destroy_node()


def test_live_tf_off_without_tf2_msgs_is_said_once(ros_context, monkeypatch):
    """Without tf2_msgs (made unimportable here) the node runs and says once that live TF is
    off and why, whether tf.publish was asked for or is the default; tf.publish false says
    nothing; the head from TF is refused naming head_frame."""
    import sys

    from ponytail_ros.app.parameters import ParameterError
    monkeypatch.setitem(sys.modules, 'tf2_msgs.msg', None)
    asked = PonytailNode(context=ros_context,
                         parameter_overrides=[Parameter('tf.publish', value=True)])
    default = PonytailNode('other', context=ros_context)
    off = PonytailNode('off', context=ros_context,
                       parameter_overrides=[Parameter('tf.publish', value=False)])
    try:
        for node in (asked, default):
            said = [w for w in node.startup_warnings if 'tf2_msgs' in w]
            assert len(said) == 1 and 'Live TF is off' in said[0] \
                and 'not published on /tf' in said[0]
            assert node._tf_pub is None
        assert not [w for w in off.startup_warnings if 'tf2_msgs' in w]
    finally:
        for node in (asked, default, off):
            node.destroy_node()
    with pytest.raises(ParameterError, match="head_frame = 'head' needs tf2_msgs"):
        PonytailNode('tf_head', context=ros_context,
                     parameter_overrides=[Parameter('head_frame', value='head')])


# -- progress -------------------------------------------------------------------------------------


class _Terminal:
    """A stderr that says it is a terminal and keeps what is written."""

    def __init__(self):
        self.text = ''

    def write(self, s):
        self.text += s
        return len(s)

    def flush(self):
        pass

    def isatty(self):
        return True


@pytest.mark.parametrize('quiet', [False, True])
def test_replay_shows_a_progress_bar_on_a_terminal_unless_quiet(tmp_path, monkeypatch, quiet):
    pytest.importorskip('tqdm')
    from ponytail_ros.recording.cli import main
    bag = rosbags_bag(tmp_path, 'in', head_samples(150))
    term = _Terminal()
    monkeypatch.setattr(sys, 'stderr', term)
    code = main([str(bag), '-o', str(tmp_path / 'out.mcap')] + (['--quiet'] if quiet else []))
    assert code == 0
    if quiet:
        assert term.text == ''
    else:
        final = term.text.replace('\r', '\n').strip().splitlines()[-1]
        assert final.startswith('replay (simulated s): 100%|') and '1.5/1.5' in final
        assert '<00:00' in final          # the ETA field


def test_no_progress_bar_when_not_a_terminal(tmp_path, capsys):
    from ponytail_ros.recording.cli import main
    bag = rosbags_bag(tmp_path, 'in', head_samples(150))
    assert main([str(bag), '-o', str(tmp_path / 'out.mcap')]) == 0
    assert 'replay (simulated s)' not in capsys.readouterr().err


def test_head_stamps_on_another_clock_are_said_on_the_terminal_with_the_fix(ros_context, capfd):
    from geometry_msgs.msg import PoseStamped

    from ros_helpers import overrides
    node = PonytailNode(context=ros_context, parameter_overrides=overrides())
    tester = rclpy.create_node('tester', context=ros_context)
    pub = tester.create_publisher(PoseStamped, 'head_pose', 10)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(tester)

    def publish():   # stamps from a simulator clock that started 1000 s ago
        m = PoseStamped()
        m.header.frame_id = 'world'
        t = tester.get_clock().now().nanoseconds - 1000 * 10**9
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t, 10**9)
        m.pose.orientation.w = 1.0
        pub.publish(m)
    tester.create_timer(0.01, publish)
    said = ''
    try:
        def warned():
            nonlocal said
            said += capfd.readouterr().err
            return 'off this node\'s clock' in said
        assert spin_until(executor, warned, 10.0)
    finally:
        executor.shutdown()
        tester.destroy_node()
        node.destroy_node()
    line = next(x for x in said.splitlines() if "off this node's clock" in x)
    assert '/head_pose' in line and 'stamp_source:=receive' in line and '1000.' in line
