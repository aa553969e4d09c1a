"""Replay never loses data silently: damaged, cut-short, out-of-order and foreign-clock bags.

The inputs are built by third-party writers (``rosbags``, and the ``mcap`` library's own writer,
which writes chunk CRCs as rosbag2's C++ storage does), then damaged the way files get damaged
(bytes changed, cut short, a writer SIGKILLed). The rule checked for each: a non-zero exit with
one line naming the file and the problem, or exit 0 with a warning on the terminal naming it --
never exit 0 in silence with partial output.
"""
import os
import signal
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip('rclpy')
rosbags_highlevel = pytest.importorskip('rosbags.highlevel')

from mcap.reader import make_reader  # noqa: E402
from mcap.writer import CompressionType, Writer as McapWriter  # noqa: E402

from ponytail_ros.recording.bag import BagError, BagReader, message_definition  # noqa: E402

from ros_helpers import HEAD, N_POSES, PERIOD_NS, T0_NS, head_samples, rosbags_bag, run  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
def mcap_bag(path, samples, chunk_size=4096):
    """The same, written by the mcap library's writer (ros2 profile, chunk CRCs), several
    chunks."""
    with open(path, 'wb') as f:
        w = McapWriter(f, chunk_size=chunk_size, compression=CompressionType.NONE)
        w.start(profile='ros2', library='mcap-python test')
        sid = w.register_schema('geometry_msgs/msg/PoseStamped', 'ros2msg',
                                message_definition('geometry_msgs/msg/PoseStamped').encode())
        cid = w.register_channel(HEAD, 'cdr', sid)
        for k, (log_ns, data) in enumerate(samples):
            w.add_message(cid, log_ns, data, log_ns, k)
        w.finish()
    return path


def replayed(path):
    """topic -> [(log time, message)] of a replay output, in file order."""
    out = {}
    for topic, _, msg, log_ns in BagReader(path).messages(order='file'):
        out.setdefault(topic, []).append((log_ns, msg))
    return out


def pose_arrays(path):
    return [(log, np.array([[p.position.x, p.position.y, p.position.z, p.orientation.x,
                             p.orientation.y, p.orientation.z, p.orientation.w]
                            for p in m.poses]))
            for log, m in replayed(path)['/segment_poses']]


def last_diagnostics(path):
    log, msg = replayed(path)['/diagnostics'][-1]
    return log, {kv.key: kv.value for kv in msg.status[0].values}


# -- damaged in the middle -------------------------------------------------------------------


def test_changed_bytes_in_a_head_pose_fail_on_the_chunk_crc_naming_file_and_byte(
        tmp_path, params, capsys):
    samples = head_samples()
    bag = mcap_bag(tmp_path / 'in.mcap', samples)
    raw = bytearray(bag.read_bytes())
    at = raw.find(samples[N_POSES // 2][1])          # a head pose in the middle of the file
    assert at > 0
    raw[at + 40] ^= 0x55                              # inside its position
    bag.write_bytes(bytes(raw))
    out = tmp_path / 'out.mcap'
    code, _, err = run([bag, '-o', out, '--params', params], capsys)
    assert code == 2
    assert len(err) == 1 and str(bag) in err[0] and 'CRC mismatch' in err[0]
    assert 'damaged at byte' in err[0] and 'repair' in err[0]
    assert not out.exists()
    with pytest.raises(BagError, match='CRC mismatch'):
        list(BagReader(bag).messages())


def test_a_changed_record_length_in_a_rosbags_bag_is_damage_not_the_end(tmp_path, params,
                                                                        capsys):
    samples = head_samples()
    bag = rosbags_bag(tmp_path, 'in', samples)
    raw = bytearray(bag.read_bytes())
    at = raw.find(samples[N_POSES // 2][1])
    # The message record's header: opcode 0x05, u64 length, then channel/sequence/times (22).
    length_at = at - 22 - 8
    assert raw[length_at - 1] == 0x05
    struct.pack_into('<Q', raw, length_at, 10**6)
    bag.write_bytes(bytes(raw))
    code, _, err = run([bag, '-o', tmp_path / 'out.mcap', '--params', params], capsys)
    assert code == 2
    assert len(err) == 1 and str(bag) in err[0] and 'damaged at byte' in err[0]
    assert 'claims 1000000 bytes' in err[0]


# -- cut short ----------------------------------------------------------------------------------


def test_a_truncated_single_chunk_rosbags_bag_says_truncated(tmp_path, params, capsys):
    bag = rosbags_bag(tmp_path, 'in', head_samples())
    raw = bag.read_bytes()
    bag.write_bytes(raw[:int(len(raw) * 0.6)])        # inside its only chunk
    code, _, err = run([bag, '-o', tmp_path / 'out.mcap', '--params', params], capsys)
    assert code == 2
    assert len(err) == 1 and str(bag) in err[0]
    assert 'truncated at byte' in err[0] and 'cut short' in err[0]


# -- storage order --------------------------------------------------------------------------------


def test_messages_stored_out_of_log_time_order_replay_in_log_time_order(tmp_path, params,
                                                                       capsys):
    samples = head_samples()
    in_order = rosbags_bag(tmp_path, 'ordered', samples)
    shuffled = list(samples)
    np.random.default_rng(7).shuffle(shuffled)
    scrambled = rosbags_bag(tmp_path, 'scrambled', shuffled)
    code, _, err = run([in_order, '-o', tmp_path / 'a.mcap', '--params', params], capsys)
    assert code == 0 and err == []
    code, _, err = run([scrambled, '-o', tmp_path / 'b.mcap', '--params', params], capsys)
    assert code == 0
    assert any(str(scrambled) in e and 'out of log-time order' in e for e in err), err
    a, b = pose_arrays(tmp_path / 'a.mcap'), pose_arrays(tmp_path / 'b.mcap')
    assert len(a) >= 250 and [t for t, _ in a] == [t for t, _ in b]
    assert all(np.array_equal(x, y) for (_, x), (_, y) in zip(a, b, strict=True))


def test_several_chunks_out_of_order_across_chunks(tmp_path):
    """Chunks (mcap writer, 4 kB) stored in reverse: the reader still yields log-time order."""
    samples = head_samples(120)
    blocks = [samples[i:i + 30] for i in range(0, 120, 30)][::-1]
    bag = mcap_bag(tmp_path / 'rev.mcap', [s for block in blocks for s in block], chunk_size=512)
    reader = BagReader(bag)
    times = [log for _, _, _, log in reader.messages()]
    assert times == sorted(times) and len(times) == 120
    assert reader.out_of_order > 0


# -- clocks ---------------------------------------------------------------------------------------


def test_head_stamps_on_another_clock_are_refused_with_the_fix_which_works(tmp_path, params,
                                                                        capsys):
    good = rosbags_bag(tmp_path, 'good', head_samples())
    # A simulator clock from exactly 0: stamps T0 before the log times; the first stamp is 0.
    sim = rosbags_bag(tmp_path, 'sim', head_samples(stamp_offset_ns=-T0_NS))
    code, _, err = run([good, '-o', tmp_path / 'good.mcap', '--params', params], capsys)
    assert code == 0 and err == []
    # Refused (exit 2, nothing written) with the fix named ...
    code, _, err = run([sim, '-o', tmp_path / 'sim.mcap', '--params', params], capsys)
    assert code == 2 and len(err) == 1 and str(sim) in err[0] and 'another clock' in err[0]
    assert '--stamp-source receive' in err[0] and 'stamp_source: receive' in err[0]
    assert not (tmp_path / 'sim.mcap').exists()
    # ... unless header stamps are asked for: then replayed by them, with the warning.
    code, _, err = run([sim, '-o', tmp_path / 'sim.mcap', '--params', params,
                        '--stamp-source', 'header'], capsys)
    assert code == 0
    warning = [e for e in err if 'another clock' in e]
    assert len(warning) == 1 and str(sim) in warning[0] and '--stamp-source receive' in warning[0]
    # The first stamp, exactly 0, is a stamp: nothing is dropped as going backwards.
    _, diag = last_diagnostics(tmp_path / 'sim.mcap')
    assert diag['dropped inputs: stamp_backwards'] == '0'
    assert diag['head poses accepted'] == str(N_POSES)
    # The fix given replays it as the correctly stamped bag: bit for bit with the same
    # stamp_source, and within the rounding of a stamp near 1.7e9 s (ulp 2.4e-7 s; sec +
    # nanosec * 1e-9 and ns * 1e-9 round differently) of its header-stamped replay -- while
    # the unfixed replay is centimetres off. The chain starts moving with the head velocity
    # estimated from the first three poses (10 ms apart): a 2.4e-7 s rounding of their
    # spacing changes that start velocity by ~2e-5 relative, which the swing carries to
    # ~1e-5 m (measured 1.1e-5 m); 1e-4 m stays three orders below the unfixed error.
    for name, bag in (('fixed', sim), ('good_receive', good)):
        code, _, err = run([bag, '-o', tmp_path / f'{name}.mcap', '--params', params,
                            '--stamp-source', 'receive'], capsys)
        assert code == 0 and err == []
    fixed, same = pose_arrays(tmp_path / 'fixed.mcap'), pose_arrays(tmp_path / 'good_receive.mcap')
    assert len(fixed) == len(same) >= 250
    assert all(t == u and np.array_equal(x, y) for (t, x), (u, y) in zip(fixed, same, strict=True))
    good_run, wrong = pose_arrays(tmp_path / 'good.mcap'), pose_arrays(tmp_path / 'sim.mcap')
    assert [t for t, _ in good_run] == [t for t, _ in fixed]
    assert max(np.abs(x[:, :3] - y[:, :3]).max()
               for (_, x), (_, y) in zip(good_run, fixed, strict=True)) < 1e-4
    assert max(np.abs(x[:, :3] - y[:, :3]).max()
               for (_, x), (_, y) in zip(good_run, wrong, strict=True)) > 0.01


# -- diagnostics and drops -----------------------------------------------------------------------


def test_the_last_diagnostics_period_is_written(tmp_path, params, capsys):
    # 2.5 s of poses, 7 of them NaN in the last half second (after the last full period).
    nan = set(range(N_POSES - 60, N_POSES - 53))
    bag = rosbags_bag(tmp_path, 'in', head_samples(250, nan=nan))
    code, _, err = run([bag, '-o', tmp_path / 'out.mcap', '--params', params], capsys)
    assert code == 0
    assert any('7 of 250 input poses dropped (7 nonfinite)' in e for e in err), err
    log, diag = last_diagnostics(tmp_path / 'out.mcap')
    assert diag['dropped inputs: nonfinite'] == '7'
    assert log == pose_arrays(tmp_path / 'out.mcap')[-1][0]    # at the last tick


def test_a_run_where_every_pose_is_dropped_fails_saying_why(tmp_path, params, capsys):
    bag = rosbags_bag(tmp_path, 'in', head_samples(50, nan=set(range(50))))
    out = tmp_path / 'out.mcap'
    code, _, err = run([bag, '-o', out, '--params', params], capsys)
    assert code == 2
    assert len(err) == 1 and str(bag) in err[0]
    assert 'all 50 head poses were dropped (50 nonfinite)' in err[0]
    assert not out.exists()


# -- repair --------------------------------------------------------------------------------------

KILLED_WRITER = r'''
import sys, time
from pathlib import Path
from geometry_msgs.msg import PoseArray, PoseStamped, Pose
from ponytail_ros.recording.recorder import RunLayout, RunRecorder
path = Path(sys.argv[1])
layout = RunLayout.for_node('/ponytail', ['ponytail'])
rec = RunRecorder(path, layout, {'rate': 100.0}, chunk_size=2048)
i = 0
announced = False
while True:
    t = 1_700_000_000_000_000_000 + i * 10_000_000
    m = PoseStamped()
    m.header.frame_id = 'world'
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(t, 1_000_000_000)
    m.pose.position.x = i * 1e-3
    m.pose.orientation.w = 1.0
    rec.head(m, t)
    a = PoseArray()
    a.header = m.header
    a.poses = [Pose() for _ in range(3)]
    for k, p in enumerate(a.poses):
        p.position.x, p.orientation.w = i * 1e-3 + k * 0.1, 1.0
    rec.poses(0, a, t)
    i += 1
    if not announced and path.stat().st_size > 120_000:
        print('ready', flush=True)      # several chunks are on disk; keep writing
        announced = True
'''


def killed_recording(tmp_path):
    path = tmp_path / 'killed.mcap'
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    proc = subprocess.Popen([sys.executable, '-c', KILLED_WRITER, str(path)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.strip() == 'ready', proc.stderr.read()
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    return path


def raw_messages(reader_messages):
    return [(topic, log, bytes(data)) for topic, log, data in reader_messages]


def test_a_sigkilled_recording_is_repaired_into_a_file_rosbags_and_mcap_index_read(
        tmp_path, capsys):
    killed = killed_recording(tmp_path)
    assert killed.read_bytes()[-8:] != b'\x89MCAP0\r\n'
    with pytest.raises(rosbags_highlevel.AnyReaderError):   # rosbags refuses the cut file
        with rosbags_highlevel.AnyReader([killed]) as reader:
            list(reader.messages())
    ours = BagReader(killed)
    readable = [(t, log) for t, _, _, log in ours.messages(order='file', raw=True)]
    assert ours.truncation is not None and len(readable) > 100
    fixed = tmp_path / 'fixed.mcap'
    code, out, err = run(['repair', killed, fixed], capsys)
    assert code == 0 and err == []
    assert f'kept {len(readable)} messages' in out and 'truncated at byte' in out
    # rosbags' indexed reader: every readable message, same topics and times and bytes.
    with rosbags_highlevel.AnyReader([fixed]) as reader:
        theirs = [(c.topic, log, bytes(raw)) for c, log, raw in reader.messages()]
    # mcap's indexed (seeking) reader, summary and index present.
    with open(fixed, 'rb') as f:
        mreader = make_reader(f)
        summary = mreader.get_summary()
        indexed = [(ch.topic, m.log_time, bytes(m.data))
                   for _, ch, m in mreader.iter_messages(log_time_order=False)]
    assert summary is not None and summary.chunk_indexes
    assert summary.statistics.message_count == len(readable)
    ours_raw = []
    from mcap.records import Channel, Message

    from ponytail_ros.recording.mcap_scan import McapScan
    channels = {}
    for _, r in McapScan(killed).records():
        if isinstance(r, Channel):
            channels[r.id] = r.topic
        elif isinstance(r, Message):
            ours_raw.append((channels[r.channel_id], r.log_time, bytes(r.data)))
    assert indexed == ours_raw
    assert sorted(theirs) == sorted(ours_raw)
    # The final rosbag2 metadata counts what was kept (ros2 bag info).
    bag = yaml.safe_load(BagReader(fixed).metadata()['rosbag2']['serialized_metadata'])
    assert bag['message_count'] == len(readable)
    # ... and the repaired file is complete, and replays exactly as the cut one did, without
    # the truncation warning.
    assert BagReader(fixed).check() is None
    code, _, err_cut = run([killed, '-o', tmp_path / 'cut_replay.mcap'], capsys)
    assert code == 0 and any('truncated at byte' in e for e in err_cut)
    code, _, err_fixed = run([fixed, '-o', tmp_path / 'fixed_replay.mcap'], capsys)
    assert code == 0 and not any('truncated' in e for e in err_fixed)
    a = pose_arrays(tmp_path / 'cut_replay.mcap')
    b = pose_arrays(tmp_path / 'fixed_replay.mcap')
    assert len(a) > 20 and [t for t, _ in a] == [t for t, _ in b]
    assert all(np.array_equal(x, y) for (_, x), (_, y) in zip(a, b, strict=True))


def test_repair_skips_a_damaged_chunk_keeps_the_rest_and_says_so(tmp_path, capsys):
    samples = head_samples()
    bag = mcap_bag(tmp_path / 'in.mcap', samples)
    raw = bytearray(bag.read_bytes())
    raw[raw.find(samples[N_POSES // 2][1]) + 40] ^= 0x55
    bag.write_bytes(bytes(raw))
    fixed = tmp_path / 'fixed.mcap'
    code, out, err = run(['repair', bag, fixed], capsys)
    assert code == 0
    assert len(err) == 1 and str(bag) in err[0] and 'CRC mismatch' in err[0]
    kept = [log for _, _, _, log in BagReader(fixed).messages()]
    lost = sorted(set(log for log, _ in samples) - set(kept))
    # One chunk's messages, consecutive, including the damaged one; the rest all kept.
    assert 0 < len(lost) < 50 and T0_NS + (N_POSES // 2) * PERIOD_NS in lost
    assert lost == list(range(lost[0], lost[-1] + 1, PERIOD_NS))
    assert f'kept {N_POSES - len(lost)} messages' in out


def test_repair_refuses_to_overwrite_and_names_the_file(tmp_path, capsys):
    bag = mcap_bag(tmp_path / 'in.mcap', head_samples(10))
    out = tmp_path / 'exists.mcap'
    out.write_bytes(b'keep me')
    code, _, err = run(['repair', bag, out], capsys)
    assert code == 2 and len(err) == 1 and str(out) in err[0] and 'already exists' in err[0]
    assert out.read_bytes() == b'keep me'


def test_repair_finds_the_next_chunk_after_a_chunk_with_a_broken_length(tmp_path, capsys):
    samples = head_samples()
    bag = mcap_bag(tmp_path / 'in.mcap', samples)
    with open(bag, 'rb') as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) >= 4
    broken = chunks[1]
    raw = bytearray(bag.read_bytes())
    assert raw[broken.chunk_start_offset] == 0x06
    struct.pack_into('<Q', raw, broken.chunk_start_offset + 1, 2**40)
    bag.write_bytes(bytes(raw))
    code, _, err = run([bag, '-o', tmp_path / 'out.mcap'], capsys)
    assert code == 2 and len(err) == 1 and str(bag) in err[0]
    assert f'damaged at byte {broken.chunk_start_offset}' in err[0]
    fixed = tmp_path / 'fixed.mcap'
    code, out, err = run(['repair', bag, fixed], capsys)
    assert code == 0 and len(err) == 1
    assert f'skipped {chunks[2].chunk_start_offset - broken.chunk_start_offset} bytes' in err[0]
    kept = [log for _, _, _, log in BagReader(fixed).messages()]
    expected = [log for log, _ in samples
                if not broken.message_start_time <= log <= broken.message_end_time]
    assert kept == expected and len(kept) < N_POSES


@pytest.mark.parametrize('compression', [CompressionType.ZSTD, CompressionType.LZ4])
def test_compressed_chunks_are_read_whole_and_checked(tmp_path, compression):
    samples = head_samples(200)
    path = tmp_path / 'c.mcap'
    with open(path, 'wb') as f:
        w = McapWriter(f, chunk_size=2048, compression=compression)
        w.start(profile='ros2', library='test')
        sid = w.register_schema('geometry_msgs/msg/PoseStamped', 'ros2msg',
                                message_definition('geometry_msgs/msg/PoseStamped').encode())
        cid = w.register_channel(HEAD, 'cdr', sid)
        for k, (log_ns, data) in enumerate(samples):
            w.add_message(cid, log_ns, data, log_ns, k)
        w.finish()
    got = [(log, bytes(data)) for _, _, data, log in BagReader(path).messages(raw=True)]
    assert got == [(log, bytes(data)) for log, data in samples]
    with open(path, 'rb') as f:
        chunk = make_reader(f).get_summary().chunk_indexes[3]
    raw = bytearray(path.read_bytes())
    raw[chunk.chunk_start_offset + chunk.chunk_length - 5] ^= 0xFF   # inside its compressed data
    path.write_bytes(bytes(raw))
    with pytest.raises(BagError, match=f'damaged at byte {chunk.chunk_start_offset}'):
        list(BagReader(path).messages(raw=True))


def test_repair_of_a_bag_cut_inside_its_only_chunk_says_nothing_was_recoverable(tmp_path,
                                                                               capsys):
    bag = rosbags_bag(tmp_path, 'in', head_samples())
    raw = bag.read_bytes()
    bag.write_bytes(raw[:int(len(raw) * 0.6)])
    out = tmp_path / 'fixed.mcap'
    code, _, err = run(['repair', bag, out], capsys)
    assert code == 2 and len(err) == 1 and str(bag) in err[0]
    assert 'no message could be recovered' in err[0] and 'truncated at byte' in err[0]
    assert not out.exists()
