"""``ponytail_replay``: offline replay reproduces a live node run bit for bit and is byte-for-byte
deterministic; replays a ``ros2 bag record``-style file (TransformStamped head, nominal ticks);
``--params`` and ``compare`` show what a parameter change did; bad input is one clear line and
exit code 2; a truncated file replays what can be read; ``--live`` publishes the head poses and
``/clock`` into a graph.

The live run is the one recorded by ``test_recording.py`` (a real ``PonytailNode`` in-process,
moving head, NaN and zero-stamp samples, a live tunable and a live structural parameter change).
"""
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import PoseStamped, TransformStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402

from ponytail_ros.app.param_values import (  # noqa: E402
    complete_values,
    values_from_metadata,
    values_from_params_file,
)
from ponytail_ros.app.runner import START_SAMPLES  # noqa: E402
from ponytail_ros.bench import head_bag  # noqa: E402
from ponytail_ros.core.rotations import quat_rotate  # noqa: E402
from ponytail_ros.recording.bag import PARAMETERS_METADATA, BagReader, BagWriter  # noqa: E402
from ponytail_ros.recording.cli import main  # noqa: E402
from ponytail_ros.recording.live import live_replay  # noqa: E402
from ponytail_ros.recording.offline import replay  # noqa: E402
from ponytail_ros.recording.recorder import RECORDING_METADATA, stamp_ns  # noqa: E402
from ponytail_ros.resources import config_path  # noqa: E402

from ros_helpers import TIMEOUT_SCALE, TYPES, poses_by_stamp, topic_messages  # noqa: E402

pytestmark = pytest.mark.ros


def pose_array(msg):
    return np.array([[p.position.x, p.position.y, p.position.z, p.orientation.x,
                      p.orientation.y, p.orientation.z, p.orientation.w] for p in msg.poses])


def one_line_error(capsys, code):
    out, err = capsys.readouterr()
    assert code == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('ponytail_replay: error: '), err
    return lines[0]


# -- reproduction and determinism ----------------------------------------------------------------

def test_replay_reproduces_the_live_run_bit_for_bit_and_is_byte_deterministic(live_run, tmp_path):
    out = tmp_path / 'replayed.mcap'
    result = replay(live_run.path, out)
    assert result.tick_mode == 'recorded' and result.parameters_from == 'the recording'
    assert result.parameter_changes == 2
    # The compiled step's share of the time is counted, and is a part of it.
    assert 0.0 < result.step_seconds < result.wall_seconds

    # Every tick of the live node, replayed at the same stamp with the same poses, exactly:
    # same samples in the same order relative to the ticks, same tick times, same parameter
    # changes at the same points -- the ChainRunner is fed identical floats.
    live, again = poses_by_stamp(live_run.path), poses_by_stamp(out)
    assert list(again) == list(live) and len(live) >= 140
    worst = max(float(np.max(np.abs(pose_array(live[s]) - pose_array(again[s])))) for s in live)
    assert worst == 0.0
    assert all(again[s] == live[s] for s in live)                    # frame_id, stamps too
    assert [m for m, _ in topic_messages(out, '/segment_markers')] == \
        [m for m, _ in topic_messages(live_run.path, '/segment_markers')]
    # The head input is carried over as recorded (times included).
    assert [(repr(m), t) for m, t in topic_messages(out, '/head_pose')] == \
        [(repr(m), t) for m, t in topic_messages(live_run.path, '/head_pose')]

    # Written like the node's recording: same topics and types, same metadata records.
    assert BagReader(out).topics() == TYPES
    meta, live_meta = BagReader(out).metadata(), BagReader(live_run.path).metadata()
    assert set(meta[PARAMETERS_METADATA]) == set(live_meta[PARAMETERS_METADATA])
    assert set(meta[RECORDING_METADATA]) >= set(live_meta[RECORDING_METADATA])
    assert meta[RECORDING_METADATA]['source'] == 'ponytail_replay'

    # Deterministic: the same input and parameters give the same bytes.
    first = out.read_bytes()
    replay(live_run.path, out, overwrite=True)
    assert out.read_bytes() == first


def make_transform_recording(path, seconds=0.6, rate=100.0, t0_ns=1_800_000_000_000_000_000):
    """A head on /mocap/head as TransformStamped, plus an unrelated topic, as ``ros2 bag record``
    would store it (no ponytail metadata)."""
    period = int(1e9 / rate)
    with BagWriter(path) as writer:
        writer.add_topic('/mocap/head', TransformStamped)
        writer.add_topic('/other', PoseStamped)
        for k in range(int(seconds * rate)):
            t_ns = t0_ns + k * period
            m = TransformStamped()
            m.header.frame_id, m.child_frame_id = 'map', 'head'
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
            m.transform.translation.x = 0.2 * np.sin(3.0 * k / rate)
            m.transform.translation.z = 1.6
            m.transform.rotation.w = 1.0
            writer.write('/mocap/head', m, t_ns + 300_000)
            writer.write('/other', PoseStamped(), t_ns + 400_000)
    return path


def test_replay_of_a_ros2_bag_recording_ticks_at_the_nominal_rate(tmp_path, capsys):
    src = make_transform_recording(tmp_path / 'mocap.mcap')
    out = tmp_path / 'out.mcap'
    assert main([str(src), '--head-topic', '/mocap/head', '-o', str(out)]) == 0
    assert 'ticks (nominal)' in capsys.readouterr().out
    expected = {k: v for k, v in TYPES.items() if k != '/head_pose'}
    expected['/mocap/head'] = 'geometry_msgs/msg/TransformStamped'
    assert BagReader(out).topics() == expected

    # Parameters: the package config (nothing recorded), as a node started with it.
    meta = BagReader(out).metadata()
    values = values_from_metadata(meta[PARAMETERS_METADATA])
    default = complete_values(values_from_params_file(config_path('ponytail.yaml')))
    assert {k: values[k] for k in default} == {**default, 'record_path': str(out)}
    assert meta[RECORDING_METADATA]['ticks'] == 'nominal'

    # Ticks every 1/rate from the first head pose's log time, until the last one.
    heads = topic_messages(src, '/mocap/head')
    poses = topic_messages(out, '/segment_poses')
    stamps = np.array([stamp_ns(m.header.stamp) for m, _ in poses])
    period = round(1e9 / default['rate'])
    assert np.all(np.diff(stamps) == period)
    # The first output: the first tick with START_SAMPLES head poses in (a velocity estimate).
    first = heads[0][1] + period * -(-(heads[START_SAMPLES - 1][1] - heads[0][1]) // period)
    assert stamps[0] == first and stamps[-1] <= heads[-1][1] < stamps[-1] + period
    # The chain hangs from the head given by the transforms (root on the attachment point).
    last_head = [h for h, t in heads if t <= stamps[-1]][-1].transform
    attach = np.array(default['ponytail.attach'])
    root = pose_array(poses[-1][0])[0, :3]
    head_p = np.array([last_head.translation.x, last_head.translation.y,
                       last_head.translation.z])
    assert np.linalg.norm(root - (head_p + quat_rotate(np.array([0.0, 0.0, 0.0, 1.0]),
                                                       attach))) < 0.01
    assert poses[-1][0].header.frame_id == 'map'

    # Deterministic in this mode too, byte for byte.
    first = out.read_bytes()
    assert main([str(src), '--head-topic', '/mocap/head', '-o', str(out), '--overwrite',
                 '-q']) == 0
    assert out.read_bytes() == first


def test_params_override_and_compare_show_what_a_change_did(live_run, tmp_path, capsys):
    recorded = values_from_metadata(BagReader(live_run.path).metadata()[PARAMETERS_METADATA])
    params = {k: v for k, v in recorded.items()
              if k not in ('use_sim_time', 'start_type_description_service', 'record_path')}
    params['ponytail.damping'] = 0.05
    params_file = tmp_path / 'stiffer.yaml'
    params_file.write_text(yaml.safe_dump({'/**': {'ros__parameters': params}}))
    out = tmp_path / 'damped.mcap'
    result = replay(live_run.path, out, params_file=params_file)
    # Same rate: the node's own tick times; the live changes belong to the recorded parameter
    # set and are not applied over a --params file.
    assert result.tick_mode == 'recorded' and result.parameter_changes == 0

    png = tmp_path / 'diff.png'
    assert main(['compare', str(live_run.path), str(out), '--plot', str(png)]) == 0
    text = capsys.readouterr().out
    assert 'ponytail.damping: 0.001 -> 0.05' in text
    row = next(line for line in text.splitlines() if line.startswith('ponytail '))
    matched, rms, worst = row.split()[1:4]
    assert int(matched) == len(poses_by_stamp(live_run.path))
    assert 0.0 < float(rms) <= float(worst)
    assert png.stat().st_size > 10_000

    assert main(['--compare', str(live_run.path), str(live_run.path)]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines()
               if line.startswith('ponytail '))
    assert row.split()[2:4] == ['0', '0']


# -- bad input ---------------------------------------------------------------------------------

def test_bad_input_is_one_clear_line_and_exit_code_2(live_run, tmp_path, capsys):
    out = str(tmp_path / 'out.mcap')
    text = tmp_path / 'notes.mcap'
    text.write_text('not a bag')
    line = one_line_error(capsys, main([str(text), '-o', out]))
    assert str(text) in line and 'not an MCAP file' in line
    missing = tmp_path / 'missing.mcap'
    line = one_line_error(capsys, main([str(missing), '-o', out]))
    assert str(missing) in line
    line = one_line_error(capsys, main([str(live_run.path), '--head-topic', '/nope', '-o', out]))
    assert str(live_run.path) in line and '/nope' in line and '/head_pose' in line
    line = one_line_error(capsys, main([str(live_run.path), '--head-topic', '/segment_poses',
                                        '-o', out]))
    assert str(live_run.path) in line and '/segment_poses' in line and 'PoseArray' in line
    bad_params = tmp_path / 'bad.yaml'
    bad_params.write_text('/**:\n  ros__parameters:\n    ponytail:\n      n_segments: -3\n')
    line = one_line_error(capsys, main([str(live_run.path), '--params', str(bad_params),
                                        '-o', out]))
    assert str(bad_params) in line and 'ponytail.n_segments' in line
    exists = tmp_path / 'exists.mcap'
    exists.write_bytes(b'x')
    line = one_line_error(capsys, main([str(live_run.path), '-o', str(exists)]))
    assert str(exists) in line and '--overwrite' in line
    assert not Path(out).exists()


def test_truncated_input_replays_what_can_be_read(live_run, tmp_path, capsys):
    cut = tmp_path / 'cut.mcap'
    data = live_run.path.read_bytes()
    cut.write_bytes(data[:len(data) // 2])        # as a killed node leaves it
    out = tmp_path / 'out.mcap'
    assert main([str(cut), '-o', str(out)]) == 0
    err = capsys.readouterr().err
    assert 'warning' in err and 'truncated' in err and str(cut) in err
    replayed, live = poses_by_stamp(out), poses_by_stamp(live_run.path)
    assert 10 < len(replayed) < len(live)
    assert all(replayed[s] == live[s] for s in replayed)   # still exact, up to the cut


# -- live replay into a graph ------------------------------------------------------------------

def test_live_replay_publishes_the_head_poses_and_clock_at_recorded_pace(ros_context, tmp_path):
    src = head_bag.make_head_recording(tmp_path / 'head.mcap', seconds=0.4)
    recorded = topic_messages(src, '/head_pose')
    node = rclpy.create_node('viewer', context=ros_context)
    heads, clock = [], []
    node.create_subscription(PoseStamped, '/head_pose', heads.append, 100)
    node.create_subscription(Clock, '/clock', lambda m: clock.append(stamp_ns(m.clock)), 100)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    sent = []
    player = threading.Thread(target=lambda: sent.append(live_replay(
        src, context=ros_context, wait_for_subscribers=10.0 * TIMEOUT_SCALE)))
    wall0 = time.monotonic()
    player.start()
    while player.is_alive() or time.monotonic() < wall0 + 0.2:
        executor.spin_once(timeout_sec=0.01)
    log_times = [t for _, t in recorded]
    deadline = time.monotonic() + 2.0 * TIMEOUT_SCALE
    while (len(heads) < len(recorded) or not clock or clock[-1] < log_times[-1]) \
            and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.01)
    executor.shutdown()
    node.destroy_node()
    assert sent == [len(recorded)]
    assert [repr(m) for m in heads] == [repr(m) for m, _ in recorded]
    assert clock and clock == sorted(clock)                         # never backwards
    assert clock[0] >= log_times[0] and clock[-1] == log_times[-1]
    assert len(clock) >= len(recorded)                              # before each pose at least
