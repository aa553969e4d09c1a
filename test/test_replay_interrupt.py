"""An interrupted replay (SIGINT, SIGTERM) ends with a finalised output that says it is partial:
rosbags opens it as it is, its metadata names the signal and the log time up to which it holds
the run, one line on the terminal says so, the exit status is 130 / 143, and a rerun needs
``--overwrite`` (and says the existing output is partial)."""
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

pytest.importorskip('rclpy')
rosbag2 = pytest.importorskip('rosbags.rosbag2')

import ponytail_ros  # noqa: E402
from ponytail_ros.recording.bag import BagReader  # noqa: E402

from ros_helpers import HEAD, head_samples, run  # noqa: E402

PACKAGE_ROOT = str(Path(ponytail_ros.__file__).resolve().parents[1])
#: 300 s of head poses: far longer than the time it takes to interrupt the replay.
LONG_POSES = 30_000


@pytest.fixture(scope='module')
def long_bag(tmp_path_factory):
    from rosbags.typesys import Stores, get_typestore
    folder = tmp_path_factory.mktemp('interrupt') / 'long'
    store = get_typestore(Stores.ROS2_KILTED)
    with rosbag2.Writer(folder, version=9, storage_plugin=rosbag2.StoragePlugin.MCAP) as bag:
        conn = bag.add_connection(HEAD, 'geometry_msgs/msg/PoseStamped', typestore=store)
        for log_ns, data in head_samples(LONG_POSES):
            bag.write(conn, log_ns, data)
    return folder


def _interrupted(bag, out, params, signum, *more, outputs=None):
    """Run ``ponytail_replay BAG... -o OUT``, signal it once every output holds a few chunks
    of ticks (the loop is running); ``(exit status, stdout, stderr lines)``."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [PACKAGE_ROOT] + [p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p]))
    outputs = outputs or [out]
    proc = subprocess.Popen([sys.executable, '-m', 'ponytail_ros.recording.cli', str(bag),
                             *map(str, more), '-o', str(out), '--params', str(params)],
                            env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 300
        while not all(o.exists() and o.stat().st_size > 300_000 for o in outputs):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, 'the replay wrote nothing'
            time.sleep(0.05)
        proc.send_signal(signum)
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, stdout, [line for line in stderr.splitlines() if line.strip()]


@pytest.mark.parametrize('signum, code', [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_an_interrupted_replay_is_finalised_marked_partial_and_said(long_bag, tmp_path, params,
                                                                   capsys, signum, code):
    out = tmp_path / 'out.mcap'
    status, stdout, err = _interrupted(long_bag, out, params, signum)
    name = signal.Signals(signum).name
    assert status == code, err
    said = [e for e in err if 'interrupted' in e]
    assert len(said) == 1 and f'interrupted by {name}' in said[0] and str(out) in said[0]
    assert 'partial' in said[0] and '--overwrite' in said[0]
    assert not any('Traceback' in e for e in err)
    # rosbags opens the file as it is (no repair) and reads every tick written.
    with rosbag2.Reader(out) as reader:
        stamps = [t for c, t, _ in reader.messages() if c.topic == '/segment_poses']
    assert 50 < len(stamps) < LONG_POSES - 100
    reader = BagReader(out)
    assert reader.finished and reader.check() is None
    record = reader.metadata()['ponytail_ros/recording']
    assert record['partial'] == 'true' and record['partial_reason'] == f'interrupted by {name}'
    assert int(record['complete_until_ns']) == stamps[-1]
    bag = yaml.safe_load(reader.metadata()['rosbag2']['serialized_metadata'])
    assert bag['custom_data']['ponytail_ros.partial'] == 'true'
    # Not replaced without --overwrite, and the refusal says what is there.
    code2, _, err2 = run([long_bag, '-o', out, '--params', params], capsys)
    assert code2 == 2 and len(err2) == 1 and 'already exists' in err2[0]
    assert 'is partial' in err2[0] and '--overwrite' in err2[0]
    # Replaying the partial output says it is partial.
    code3, _, err3 = run([out, '-o', tmp_path / 'again.mcap'], capsys)
    assert code3 == 0 and any(f'{out} is partial: interrupted by {name}' in e for e in err3)


def test_an_interrupted_run_of_many_bags_finalises_every_running_one(long_bag, tmp_path,
                                                                     params):
    """SIGTERM to ``ponytail_replay A B -o DIR -j 2``: both running replays end, each output
    finalised and marked partial, one line each, exit 143."""
    other = tmp_path / 'other'
    shutil.copytree(long_bag, other)
    out = tmp_path / 'out'
    outputs = [out / 'long.mcap', out / 'other.mcap']
    status, _, err = _interrupted(long_bag, out, params, signal.SIGTERM, other, '-j', '2',
                                  outputs=outputs)
    assert status == 143, err
    said = [e for e in err if 'interrupted by SIGTERM' in e]
    assert len(said) == 2 and all(any(str(o) in e for e in said) for o in outputs)
    for o in outputs:
        with rosbag2.Reader(o) as reader:
            assert reader.message_count > 100
        assert BagReader(o).metadata()['ponytail_ros/recording']['partial'] == 'true'
