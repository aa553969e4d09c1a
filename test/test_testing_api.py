"""The public testing API (``ponytail_ros.testing``): the offline path imports no rclpy, the
in-process harness is driven by sim time and publishes exactly what the offline path computes,
parallel harnesses do not hear each other, and every check fails with a message naming the
quantity, the bound, where and when."""
import dataclasses
import json
import math
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import ponytail_ros
from ponytail_ros.app.runner import START_SAMPLES
from ponytail_ros.testing import (
    CheckFailed,
    PoseSample,
    assert_energy_does_not_grow,
    assert_joints_closed,
    assert_no_penetration,
    assert_no_resets,
    assert_tips_close,
    assert_within_joint_limits,
    joint_gaps,
    load_config,
    n_ticks,
    run_offline,
    still,
    tick_period_ns,
)
from ponytail_ros.testing.motion import stamp_ns

ROOT = Path(__file__).resolve().parents[1]
PARAMS = ROOT / 'examples' / 'my_character.yaml'
sys.path.insert(0, str(ROOT / 'examples'))
from walk_cycle import walk, walk_then_stop  # noqa: E402

#: The package under test's import root, for subprocesses.
PACKAGE_ROOT = str(Path(ponytail_ros.__file__).resolve().parents[1])
#: |attach| of the example's ponytail root from the skull centre, m.
ROOT_RADIUS = math.hypot(-0.1034, 0.0377)


def _env(**extra):
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([PACKAGE_ROOT] + [p for p in
                                        env.get('PYTHONPATH', '').split(os.pathsep) if p])
    env.update(extra)
    return env


def published(duration, rate, input_rate=100.0):
    """Ticks that publish in ``duration`` s at ``rate`` Hz with head poses at ``input_rate``
    from t = 0: all but those before the chain starts, which waits for ``START_SAMPLES`` poses
    (so that it starts moving with the head)."""
    start_ns = stamp_ns((START_SAMPLES - 1) / input_rate)
    period = tick_period_ns(rate)
    return sum(k * period >= start_ns for k in range(1, n_ticks(duration, rate) + 1))


# -- offline ---------------------------------------------------------------------------------

def test_offline_path_imports_no_rclpy_and_ticks_at_the_rate():
    code = textwrap.dedent(f'''
        import sys
        from ponytail_ros.testing import run_offline, still, assert_joints_closed
        run = run_offline({str(PARAMS)!r}, still(), 0.5)
        assert_joints_closed(run)
        print(run.n_ticks, 'rclpy' in sys.modules)
    ''')
    out = subprocess.run([sys.executable, '-c', code], env=_env(), capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == [str(published(0.5, 60.0)), 'False']  # no rclpy


def test_config_errors_name_the_parameter():
    with pytest.raises(ValueError, match='ponytail.length'):
        load_config(PARAMS, {'ponytail.length': -1.0})
    with pytest.raises(ValueError, match='ponytail.lenght'):
        load_config(PARAMS, {'ponytail.lenght': 0.3})       # a typo is not silently ignored


# -- the checks ------------------------------------------------------------------------------

@pytest.fixture(scope='module')
def walked():
    return run_offline(PARAMS, walk, 1.0)


def _number(pattern, text):
    m = re.search(pattern, text)
    assert m, text
    return float(m.group(1))


def test_penetration_check_passes_the_example_and_names_a_skull_grown_into_the_root(walked):
    # The example holds the whole capsule out to within the inner half's sag (0.2 mm) plus
    # dynamics; its own test bounds it by 1 mm.
    assert assert_no_penetration(walked, max_depth=1e-3, since=0.05) < 1e-3
    broken = run_offline(PARAMS, walk, 0.5, overrides={'skull.radius': 0.12})
    with pytest.raises(CheckFailed) as err:
        assert_no_penetration(broken, max_depth=1e-3, since=0.05)
    text = str(err.value)
    assert "collider 'skull'" in text and "chain 'ponytail' segment 1" in text
    assert 'max_depth 0.001 m' in text and re.search(r'at t = \d+\.\d{3} s \(tick \d+ of \d+\)',
                                                     text)
    # The root is fixed 0.11006 m from the centre: a 0.12 m skull (+ 0.02 m hair) holds it
    # 0.0299 m deep, and no part of the first segment can be deeper than its root there.
    depth = _number(r'penetration depth ([0-9.e-]+) m', text)
    assert depth == pytest.approx(0.12 + 0.02 - ROOT_RADIUS, abs=1e-4)


def test_joint_check_measures_every_joint_and_names_an_opened_one(walked):
    gaps = joint_gaps(walked)
    # rigid chain, root on the head
    assert gaps.shape == (published(1.0, 60.0), 8) and gaps.max() < 1e-12
    assert assert_joints_closed(walked, tolerance=1e-9) < 1e-12
    bad = dataclasses.replace(walked, origins=walked.origins.copy())
    bad.origins[20, 3] += [0.0, 0.0, 2e-3]                 # segment 4 lifted off, 21st tick
    with pytest.raises(CheckFailed) as err:
        assert_joints_closed(bad, tolerance=1e-6)
    text = str(err.value)
    assert _number(r'joint gap ([0-9.e-]+) m', text) == pytest.approx(2e-3, rel=1e-6)
    assert "chain 'ponytail', joint 4 (between segments 3 and 4)" in text
    n = published(1.0, 60.0)
    assert f't = {walked.t[20]:.3f} s (tick 21 of {n})' in text and f'1 of {n} ticks' in text


def test_limit_check_names_the_joint_and_the_excess(walked):
    limited = run_offline(PARAMS, walk, 1.0, overrides={'ponytail.swing_limit': 0.1})
    # Judged against a 0.1 rad cone, the free chain swings far out (joint 2 to 0.48 rad) ...
    judged = dataclasses.replace(walked, config=limited.config)
    with pytest.raises(CheckFailed) as err:
        assert_within_joint_limits(judged)
    text = str(err.value)
    k, j = np.unravel_index(np.argmax(walked.swing), walked.swing.shape)
    assert f"chain 'ponytail' joint {j + 1} at t = {walked.t[k]:.3f} s" in text
    assert _number(r'by ([0-9.e-]+) rad', text) == pytest.approx(walked.swing.max() - 0.1,
                                                                 rel=1e-3)
    # ... the limited one stays on its cone: its largest excess (published states are carried
    # forward by ω over up to one internal step past the solver's state) is a small fraction.
    excess = float(np.max(limited.swing - 0.1))
    assert excess < 0.01 * (walked.swing.max() - 0.1)


def test_tip_check_tells_a_small_tuning_change_from_a_large_one(walked):
    slightly = run_offline(PARAMS, walk, 1.0, overrides={'ponytail.damping': 0.0012})
    assert assert_tips_close(slightly, walked, max_distance=5e-3, rms=2e-3) < 5e-3
    much = run_offline(PARAMS, walk, 1.0, overrides={'ponytail.damping': 0.01})
    with pytest.raises(CheckFailed, match=r"tip distance [0-9.e-]+ m > max_distance 0.005 m: "
                                          r"chain 'ponytail' at t = "):
        assert_tips_close(much, walked, max_distance=5e-3)
    with pytest.raises(CheckFailed, match='same instants'):
        assert_tips_close(run_offline(PARAMS, walk, 0.5), walked, max_distance=1.0)


def test_energy_check_on_a_stopped_head_and_on_a_walking_one():
    run = run_offline(PARAMS, walk_then_stop, 3.0)
    # Held still from t = 2 s: energy only ever falls (damping, drag, contacts).
    assert assert_energy_does_not_grow(run, tolerance=1e-9, since=2.2) <= 0.0
    with pytest.raises(CheckFailed, match=r"energy rose by [0-9.e-]+ J > tolerance 1e-06 J on "
                                          r"a still head: chain 'ponytail', from "):
        assert_energy_does_not_grow(run, since=0.0)          # while walking it is driven


def test_reset_check_names_a_teleport_and_its_time():
    head = still((0.0, 0.0, 1.6))
    samples = [PoseSample(k / 100.0, tuple(head(0)[0]), tuple(head(0)[1])) for k in range(50)]
    jumped = samples + [PoseSample(k / 100.0, (3.0, 0.0, 1.6), (0.0, 0.0, 0.0, 1.0))
                        for k in range(50, 100)]
    assert_no_resets(run_offline(PARAMS, samples, 1.0))
    run = run_offline(PARAMS, jumped, 1.0)
    with pytest.raises(CheckFailed) as err:
        assert_no_resets(run)
    text = str(err.value)
    assert text.startswith('1 reset(s) of the chain at rest, expected none: teleport at t = ')
    t = _number(r'at t = ([0-9.]+) s', text)
    assert 0.5 <= t <= 0.5 + 2.0 / 60.0                      # the first tick that saw the jump
    assert_no_resets(run, reasons=['guard'])                 # not a guard reset


# -- the ROS harness -------------------------------------------------------------------------

@pytest.mark.ros
def test_harness_is_driven_by_sim_time_and_publishes_what_the_offline_path_computes(ponytail):
    pytest.importorskip('rclpy')
    import time

    def slow_walk(t):                      # a head source 20 ms slow per pose: wall time
        time.sleep(0.02)                   # must not matter
        return walk(t)
    h = ponytail(PARAMS)
    run = h.run(slow_walk, 1.0)
    period = tick_period_ns(60.0)
    # Every tick at a /clock time, one per period of sim time, as many as sim time gives.
    assert h.ticks == n_ticks(1.0, 60.0) == 60 and run.n_ticks == published(1.0, 60.0)
    first = 1 + n_ticks(1.0, 60.0) - published(1.0, 60.0)     # the first tick that publishes
    assert np.array_equal(np.round(run.t * 1e9), period * np.arange(first, 61))
    got = run.poses['segment_poses']
    assert [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in got] == \
        [period * k for k in range(first, 61)]
    assert len(run.markers) == 30                                       # markers.rate 30 Hz
    # Bit for bit what the node's logic gives offline, without ROS and without sleeping.
    offline = run_offline(PARAMS, walk, 1.0)
    assert np.array_equal(run.origins, offline.origins)
    assert np.array_equal(run.orientations, offline.orientations)
    assert all(a == b for a, b in zip(got, offline.poses['segment_poses'], strict=True))
    assert h.publish_diagnostics()['resets'] == '0'


PARALLEL = '''
import json, sys, time
import numpy as np
sys.path.insert(0, {examples!r})
from walk_cycle import walk
from ponytail_ros.testing import Harness, run_offline
offset = float(sys.argv[1])

def head(t):
    p, q = walk(t)
    return (p[0] + offset, p[1], p[2]), q
start = time.time()
with Harness({params!r}, discovery=sys.argv[2], domain_id=42) as h:
    error = None
    try:
        run = h.run(head, 1.0)
    except Exception as exc:          # HarnessError: a message this node did not publish
        error = f'{{type(exc).__name__}}: {{exc}}'
    if error is None:
        offline = run_offline({params!r}, head, 1.0)
        roots = [[m.poses[0].position.x, m.poses[0].position.y, m.poses[0].position.z]
                 for m in run.poses['segment_poses']]
        result = dict(n=len(roots), roots=roots, anchors=run.anchors[:, 0].tolist(),
                      same_as_offline=bool(np.array_equal(run.origins,  # shapes too
                                                          offline.origins)),
                      resets=[r.reason for r in run.resets])
    else:
        result = dict(error=error)
result.update(start=start, end=time.time())
print(json.dumps(result))
'''


def _parallel(tmp_path, discovery):
    script = tmp_path / 'parallel.py'
    script.write_text(PARALLEL.format(examples=str(ROOT / 'examples'), params=str(PARAMS)))
    procs = [subprocess.Popen([sys.executable, str(script), off, discovery], env=_env(),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for off in ('0.0', '5.0')]
    results = []
    for p in procs:
        out, err = p.communicate(timeout=600)
        assert p.returncode == 0, err
        results.append(json.loads(out.strip().splitlines()[-1]))
    a, b = results
    assert a['start'] < b['end'] and b['start'] < a['end']        # they did overlap
    return results


@pytest.mark.ros
def test_two_harnesses_in_parallel_on_one_domain_do_not_hear_each_other(tmp_path):
    pytest.importorskip('rclpy')
    for offset, r in zip((0.0, 5.0), _parallel(tmp_path, 'OFF'), strict=True):
        assert 'error' not in r, r['error']
        assert r['n'] == published(1.0, 60.0) and r['resets'] == []
        roots, anchors = np.array(r['roots']), np.array(r['anchors'])
        # Every PoseArray received is this run's: its root on this run's own head ...
        assert np.max(np.linalg.norm(roots - anchors, axis=1)) < 1e-12
        first = 1 + n_ticks(1.0, 60.0) - published(1.0, 60.0)
        assert np.all(np.abs(roots[:, 0] - offset - 1.2 * np.arange(first, 61) / 60.0) < 0.2)
        # ... and the physics is untouched: the same as this head offline.
        assert r['same_as_offline']


@pytest.mark.ros
def test_the_parallel_check_sees_interference_when_both_runs_share_a_localhost_graph(tmp_path):
    """The control: the same two runs on one domain with discovery LOCALHOST hear each other's
    /clock and outputs, and the harness says so (or the run's content shows it)."""
    pytest.importorskip('rclpy')
    disturbed = []
    for r in _parallel(tmp_path, 'LOCALHOST'):
        disturbed.append('error' in r or not r['same_as_offline'] or r['n'] != 60
                         or r['resets'] != [])
    assert any(disturbed)


@pytest.mark.ros
def test_a_recorded_take_feeds_the_harness_as_its_samples_do(ponytail, tmp_path):
    """Head poses from a rosbag2 bag folder written by rosbags, stamped on a wall clock
    (absolute times), come back from ``bag_samples`` rebased to the first pose, and drive the
    harness and ``run_offline`` exactly as the same poses given as a list from t = 0."""
    pytest.importorskip('rclpy')
    rosbag2 = pytest.importorskip('rosbags.rosbag2')
    from rclpy.serialization import serialize_message
    from rosbags.typesys import Stores, get_typestore

    from ponytail_ros.testing import bag_samples, sample_motion
    from ponytail_ros.testing.harness import HarnessError, pose_msg
    t0_ns = 1_700_000_000_123_456_789
    samples = sample_motion(walk, 0.5)
    store = get_typestore(Stores.ROS2_KILTED)
    folder = tmp_path / 'take'
    with rosbag2.Writer(folder, version=9, storage_plugin=rosbag2.StoragePlugin.MCAP) as bag:
        conn = bag.add_connection('/head_pose', 'geometry_msgs/msg/PoseStamped',
                                  typestore=store)
        for s in samples:
            t_ns = t0_ns + stamp_ns(s.t)
            msg = pose_msg(0.0, s.position, s.orientation)
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
            bag.write(conn, t_ns + 500_000, serialize_message(msg))
    read = bag_samples(folder)
    assert read.start_ns == t0_ns and read[0].t == 0.0
    assert [stamp_ns(s.t) for s in read] == [stamp_ns(s.t) for s in samples]
    run = ponytail(PARAMS).run(read, 0.5)
    reference = run_offline(PARAMS, samples, 0.5)
    assert run.n_ticks == published(0.5, 60.0)
    assert np.array_equal(run.origins, reference.origins)
    assert np.array_equal(run_offline(PARAMS, read, 0.5).origins, reference.origins)
    # The same poses at their absolute stamps: an error naming the cause, not 0 ticks.
    absolute = [s._replace(t=s.t + t0_ns * 1e-9) for s in read]
    with pytest.raises(HarnessError, match='absolute stamps'):
        ponytail(PARAMS).run(absolute, 0.5)
    with pytest.raises(ValueError, match='absolute stamps'):
        run_offline(PARAMS, absolute, 0.5)


def test_every_check_fails_on_a_run_without_ticks():
    """No head pose, no tick: every ``assert_*`` of ``ponytail_ros.testing`` fails saying so
    (an empty trace passes nothing)."""
    import ponytail_ros.testing as testing
    empty = run_offline(PARAMS, [], 0.3)
    assert empty.n_ticks == 0
    extra = {'assert_tips_close': (empty, 1.0)}
    checks = [name for name in testing.__all__ if name.startswith('assert_')]
    assert len(checks) >= 6
    for name in checks:
        with pytest.raises(CheckFailed, match='no published tick'):
            getattr(testing, name)(empty, *extra.get(name, ()))


@pytest.mark.ros
def test_extra_frames_are_fed_on_their_topics_as_offline(ponytail):
    """A scene with a forearm frame (``config/ponytail_arm.yaml``) publishes nothing without the
    forearm's poses, and with them the harness (on ``left_forearm_pose``) and the offline path
    give the same chain; the forearm capsule, held clear, is never touched."""
    pytest.importorskip('rclpy')
    arm_params = ROOT / 'config' / 'ponytail_arm.yaml'
    head = still((0.0, 0.0, 1.6))
    forearm = still((0.3, 0.4, 1.2))
    assert run_offline(arm_params, head, 0.2).n_ticks == 0
    run = ponytail(arm_params).run(head, 0.3, frames={'left_forearm': forearm})
    reference = run_offline(arm_params, head, 0.3, frames={'left_forearm': forearm})
    assert run.n_ticks == reference.n_ticks == published(0.3, 120.0)
    assert np.array_equal(run.origins, reference.origins)
    assert assert_no_penetration(run, max_depth=0.0, colliders=['left_forearm_capsule']) < -0.1
    with pytest.raises(ValueError, match="no frame 'right_forearm'"):
        run_offline(arm_params, head, 0.1, frames={'right_forearm': forearm})
