"""Driven by head poses as accurately as by the head's formulas.

The moving head of ``../shared/reference/`` (sway 5 cm at 1.5 Hz, yaw 0.6 rad at 0.8 Hz) is
written as ``geometry_msgs/PoseStamped`` bags by a third-party writer (``rosbags``) at several
rates, replayed with ``ponytail_replay`` on the reference's 10-segment scene, and the tip (far
end of the last segment, world frame, m) compared with the reference trajectory
``ponytail_N10_moving_hanging`` over its valid window. The chain starts at the first pose, at
rest relative to the head (moving with it), as the reference does.

Internal step RK4 at 1/2000 s in look-ahead mode (the core's own error on this file is then
below the bounds asserted; a finer step only moves the figures towards the estimation error),
1/1000 s in live mode: ``docs/performance.md`` has the figures and the command.
"""
from pathlib import Path

import numpy as np
import pytest
import yaml

from ponytail_ros.bench.pose_bench import WHIP_BOUND, start_whip
from ponytail_ros.core.head import SwayYawMotion
from ponytail_ros.core.reference import default_reference_dir, load_reference

REFERENCE = default_reference_dir() / 'ponytail_N10_moving_hanging.json'
#: Bag time of the reference's t = 0 (a zero stamp means "unstamped" to the node).
T0_NS = 100_000_000_000
DT = 1.0 / 2000
RATES = (30, 60, 120, 1000)
TICK_RATE = 100.0           # the reference's sample period: outputs at its times
#: Largest RMS tip distance between live replays of 30/60/120/1000 Hz bags, m
#: (``pose_bench --reference`` prints it).
LIVE_PAIRWISE_RMS = 0.08


def _need_reference():
    if not REFERENCE.exists():
        pytest.skip(f'{REFERENCE} not found: the shared reference trajectories '
                    '(../shared/reference/) are not checked out next to the repository')


def write_pose_bag(directory, rate, duration=3.2, motion=None):
    """A rosbag2 MCAP bag (written by ``rosbags``) of ``motion``'s poses on ``/head_pose`` at
    ``rate`` Hz from bag time ``T0_NS``; each pose is the motion at its own (ns) stamp, log
    time = stamp. Returns the ``.mcap`` file."""
    rosbag2 = pytest.importorskip('rosbags.rosbag2')
    typesys = pytest.importorskip('rosbags.typesys')
    store = typesys.get_typestore(getattr(typesys.Stores, 'ROS2_KILTED',
                                          typesys.Stores.LATEST))
    T = store.types
    motion = motion or SwayYawMotion()
    directory = Path(directory)
    with rosbag2.Writer(directory, version=9,
                        storage_plugin=rosbag2.StoragePlugin.MCAP) as writer:
        msgtype = 'geometry_msgs/msg/PoseStamped'
        conn = writer.add_connection('/head_pose', msgtype, typestore=store)
        for k in range(int(round(duration * rate)) + 1):
            ns = T0_NS + int(round(k * 1e9 / rate))
            s = motion.state_at((ns - T0_NS) * 1e-9)
            p, q = s.position[0].tolist(), s.orientation[0].tolist()
            msg = T[msgtype](
                header=T['std_msgs/msg/Header'](
                    stamp=T['builtin_interfaces/msg/Time'](sec=ns // 10**9,
                                                          nanosec=ns % 10**9),
                    frame_id='world'),
                pose=T['geometry_msgs/msg/Pose'](
                    position=T['geometry_msgs/msg/Point'](x=p[0], y=p[1], z=p[2]),
                    orientation=T['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2],
                                                                  w=q[3])))
            writer.write(conn, ns, store.serialize_cdr(msg, msgtype))
    return next(directory.glob('*.mcap'))


def reference_params(path, dt=DT, **extra):
    """A node params file of the reference scene (10 segments, no damping, stiffness or
    drag), RK4 at ``dt``, ticks at ``TICK_RATE``."""
    values = {'rate': TICK_RATE, 'chains': ['ponytail'], 'colliders': [],
              'gravity': [0.0, 0.0, -9.81], 'markers': {'style': 'off'},
              'solver': {'integrator': 'rk4', 'dt': dt, 'max_steps_per_call': 100000},
              'ponytail': {'n_segments': 10, 'length': 0.4, 'mass': 0.1, 'radius': 0.01,
                           'attach': [-0.1, 0.0, 0.05], 'rest_direction': [0.0, 0.0, -1.0],
                           'damping': 0.0, 'stiffness': 0.0, 'drag_linear': 0.0,
                           'drag_quadratic': 0.0}}
    values.update(extra)
    Path(path).write_text(yaml.safe_dump({'/**': {'ros__parameters': values}}))
    return path


def tip_track(path):
    """(t from the reference's start, s; tips ``(k, 3)``) of a replay's output, by stamp."""
    from ponytail_ros.recording.compare import load_chain_runs
    runs, values = load_chain_runs(path)
    run = runs['ponytail']
    return (run.stamps - T0_NS) * 1e-9, run.tips, values


@pytest.fixture(scope='module')
def replays(tmp_path_factory):
    """Look-ahead and live replays of the reference head at every rate in ``RATES``."""
    _need_reference()
    from ponytail_ros.recording.offline import replay
    d = tmp_path_factory.mktemp('pose_bags')
    params_la = reference_params(d / 'look_ahead.yaml')
    # Live: the node's defaults (2 input periods of delay, cubic fit over 0.1 s), stamped
    # with the simulated time so that the comparison is at the chain's own time; RK4 at
    # 1/1000 s (the core's error there, ~1e-3 m, is far below the live estimate's).
    params_live = reference_params(d / 'live.yaml', dt=1 / 1000, output_stamp='simulated')
    out = {}
    for rate in RATES:
        bag = write_pose_bag(d / f'head_{rate}', rate)
        for mode, params in (('look_ahead', params_la), ('live', params_live)):
            path = d / f'{mode}_{rate}.mcap'
            replay(bag, path, params_file=params, look_ahead=mode == 'look_ahead')
            out[mode, rate] = tip_track(path)
    return out


def reference_tip():
    ref = load_reference(REFERENCE)
    ok = ref.t <= ref.window() + 1e-9
    return ref.t[ok], ref.points[-1][ok]


def errors_against_reference(track):
    """Tip distance (m) to the reference at its sample times within the run's span (a cubic
    spline through the run's outputs: exact at look-ahead outputs, which are at those times;
    live outputs are stamped t - delay)."""
    from scipy.interpolate import CubicSpline
    t, tips, _ = track
    t_ref, tip_ref = reference_tip()
    ok = (t_ref >= t[0] - 1e-9) & (t_ref <= t[-1] + 1e-9)
    assert ok.sum() >= len(t_ref) - 8           # from the first output (≤ 70 ms)
    return np.linalg.norm(CubicSpline(t, tips)(t_ref[ok]) - tip_ref[ok], axis=1)


@pytest.mark.parametrize('rate, bound', [(1000, 1e-4), (120, 1e-3), (30, 5e-3)])
def test_look_ahead_replay_of_a_rosbags_pose_bag_matches_the_reference(replays, rate, bound):
    t, _, values = replays['look_ahead', rate]
    assert values['output_stamp'] == 'simulated'       # the stamp says what it shows
    d = errors_against_reference(replays['look_ahead', rate])
    assert np.sqrt(np.mean(d * d)) <= bound


def _pairwise(replays, mode, t_end=3.0):
    """Largest RMS and max tip distance (m) between two rates' runs over the common span up
    to ``t_end`` (cubic splines through each run's outputs at their own stamps: live outputs
    are stamped t - delay, a different delay per rate)."""
    from scipy.interpolate import CubicSpline
    t_lo = max(replays[mode, rate][0][0] for rate in RATES)
    grid = np.arange(np.ceil(t_lo * TICK_RATE), np.floor(t_end * TICK_RATE) + 1) / TICK_RATE
    tracks = {rate: CubicSpline(*replays[mode, rate][:2])(grid) for rate in RATES}
    worst_rms = worst_max = 0.0
    for i, a in enumerate(RATES):
        for b in RATES[i + 1:]:
            d = np.linalg.norm(tracks[a] - tracks[b], axis=1)
            worst_rms = max(worst_rms, float(np.sqrt(np.mean(d * d))))
            worst_max = max(worst_max, float(d.max()))
    return worst_rms, worst_max


def test_look_ahead_replay_is_frame_rate_independent(replays):
    """30, 60, 120 and 1000 Hz bags of one motion: tip tracks within 1 mm of each other at
    every output over 3 s (the largest distance of any two rates; the whip near 2.8 s
    amplifies early differences ~1000x, so this bounds the estimate at the first poses too)."""
    _, worst = _pairwise(replays, 'look_ahead')
    assert worst <= 1e-3


def test_live_replay_frame_rate_dependence_is_bounded(replays):
    """The live estimate (causal, delayed, smoothed) depends on the input rate: bounded by
    ``LIVE_PAIRWISE_RMS``."""
    rms, _ = _pairwise(replays, 'live')
    assert rms <= LIVE_PAIRWISE_RMS



# -- start-up whip ---------------------------------------------------------------------------

@pytest.mark.parametrize('input_rate', [30.0, 120.0])
@pytest.mark.parametrize('case', ['start', 'teleport', 'rebuild'])
def test_no_start_up_whip_on_a_running_turning_head(case, input_rate):
    """A head running at 2 m/s and turning at 3 rad/s: at the node's start, after a teleport
    and after a rebuild, the chain starts moving with it, so the tip's speed relative to the
    head in the first 100 ms stays below ``WHIP_BOUND`` (``pose_bench.start_whip``)."""
    speeds, runner, t_from = start_whip(case, input_rate)
    if case == 'start':
        assert t_from <= 1.0 / input_rate             # from the first pose
    else:
        assert runner.resets[case] == 1
    assert runner.resets['guard'] == 0
    assert speeds.max() < WHIP_BOUND


# -- honest stamps through a recording ---------------------------------------------------------

def test_simulated_stamps_are_recorded_and_a_replay_of_the_replay_is_bit_exact(tmp_path):
    """A run with ``output_stamp: simulated`` (live estimation, stamps t - delay) records the
    setting; replaying that recording with its own parameters ticks at its log times (not its
    stamps) and reproduces it exactly; ``compare`` names the stamp modes."""
    pytest.importorskip('rosbags')
    from ponytail_ros.recording.compare import compare, format_comparison
    from ponytail_ros.recording.offline import replay
    bag = write_pose_bag(tmp_path / 'head', 120, duration=0.6)
    params = reference_params(tmp_path / 'p.yaml', dt=1 / 500, output_stamp='simulated')
    first = replay(bag, tmp_path / 'a.mcap', params_file=params)
    again = replay(tmp_path / 'a.mcap', tmp_path / 'b.mcap')
    assert again.tick_mode == 'recorded' and again.ticks == first.ticks > 0
    t_a, tips_a, values = tip_track(tmp_path / 'a.mcap')
    t_b, tips_b, _ = tip_track(tmp_path / 'b.mcap')
    assert values['output_stamp'] == 'simulated'
    assert np.array_equal(t_a, t_b) and np.array_equal(tips_a, tips_b)
    # The stamps are the simulated times: 2 input periods before the 100 Hz ticks.
    ticks = np.round(t_a + 2 / 120, 9)
    assert np.allclose(ticks * TICK_RATE, np.round(ticks * TICK_RATE), atol=1e-6)
    comps, *_, va, vb = compare(tmp_path / 'a.mcap', tmp_path / 'b.mcap')
    text = format_comparison('a', 'b', comps, va, vb)
    assert 'output stamps: A simulated, B simulated' in text and comps[0].max == 0.0


@pytest.mark.parametrize('rate', [1000, 120])
def test_look_ahead_from_a_wall_clock_bag_is_as_accurate_as_from_a_sim_clock_bag(tmp_path, rate):
    """Issue 37: head bags stamped from 1.7e9 s (recorded on a wall clock) and from 100 s,
    written by ``rosbags``, replayed look-ahead with RK4 1/8000 s and ticks at 1000 Hz: the
    same tip to 1e-9 m, within ``REFERENCE_BOUNDS`` of the reference (1e-6 m from a 1000 Hz
    head, 5e-5 m from 120 Hz). Shortened to the file's first second (the suite stays fast;
    ``pose_bench --reference --epoch 100 --epoch 1.7e9`` prints the full window's figures,
    the same bounds)."""
    _need_reference()
    pytest.importorskip('rosbags.rosbag2')
    from ponytail_ros.bench.pose_bench import REFERENCE_BOUNDS, reference_tip_errors
    runs = [reference_tip_errors(rate, t0, tmp_path, duration=1.4, t_end=1.0)
            for t0 in (T0_NS, 1_700_000_000_000_000_000)]
    (e_sim, (t_sim, tips_sim)), (e_wall, (t_wall, tips_wall)) = runs
    assert np.array_equal(t_sim, t_wall) and len(e_sim) >= 95
    assert np.abs(tips_sim - tips_wall).max() <= 1e-9
    for e in (e_sim, e_wall):
        assert np.sqrt(np.mean(e * e)) <= REFERENCE_BOUNDS[rate]
