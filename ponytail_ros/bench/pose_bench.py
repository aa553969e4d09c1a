"""The head estimation's accuracy, live and look-ahead, and the tip error it causes.

    ponytail_bench pose [--quick|--full|--tiny] [--out DIR]
    python -m ponytail_ros.bench.pose_bench [--quick|--tiny] [--out DIR]

The head follows the reference's moving head (``SwayYawMotion``: sway 5 cm at 1.5 Hz along
world X, yaw 0.6 rad at 0.8 Hz about world Z, at 1.6 m; exact derivatives). Its poses are
sampled at 30, 60, 120, 250 and 1000 Hz, with regular stamps or with ±20 % stamp jitter (the
stamps are exact but irregular; each pose is the head at its stamp).

1. Estimation errors (``pose_estimation.csv/json``): RMS over random tick times in
   [1, 5.95] s of the error of the head origin's position p (m), velocity ṗ (m/s),
   acceleration p̈ (m/s²), and of the angular velocity ω (rad/s) and acceleration α (rad/s²),
   world frame, against the exact head at the time the estimate is for:

   Stamps are rounded to whole ns, as in a bag (the poses are the head at the unrounded
   times: a ≤ 0.5 ns inconsistency, which an interpolating fit at 1 kHz amplifies).

   * ``live``: as the node does it: causal (only poses stamped before the tick), the node's
     default estimator (cubic over ``head.window`` 0.1 s) at ``t - delay`` with the default
     delay of 2 input periods (the latency, 2/rate, is listed, not counted as error);
   * ``live_interp``: the same, but the cubic interpolates the 4 nearest poses
     (``LIVE_INTERP``: for exact animation poses; it amplifies noise);
   * ``look_ahead``: as ``ponytail_replay --look-ahead``: every pose known, the estimator
     of ``LOOK_AHEAD_VALUES`` (degree 9 over ±0.05 s, at least the 10 nearest poses; where
     at most 10 poses are within ±0.05 s, the degree-11 global spline of
     ``core/head_spline.py``) at the tick itself.

2. Tip error (``pose_tip.csv/json``): the reference's 10-segment chain (0.4 m, 0.1 kg, no
   damping) on that head for 3 s, replayed by ``ponytail_replay`` from a ``PoseStamped`` bag
   of the sampled poses (ticks at 100 Hz, outputs stamped with their simulated time) against
   the same chain driven by the exact head formulas at every integrator stage, same RK4 step;
   RMS and max tip distance (m) at the outputs' times. The chain starts at the first pose, at
   rest relative to the head, in both.

3. Against the reference (``--reference``; needs ``../shared/reference/``): the poses of
   ``ponytail_N10_moving_hanging``'s head at 30, 60, 120 and 1000 Hz (regular, each at its
   ns stamp, 3.2 s) replayed look-ahead (RK4 1/2000 s) and live with the node's defaults
   (RK4 1/1000 s, simulated stamps); tip RMS / max against the file over its valid window,
   and the largest RMS / max tip distance between two rates (the figures
   ``test/test_pose_accuracy.py`` asserts, there from bags written by ``rosbags``).

   With ``--epoch SECONDS`` (repeatable, e.g. ``--epoch 100 --epoch 1.7e9``): the bags are
   written by ``rosbags`` with stamps from that epoch, the look-ahead replays use RK4 1/8000 s
   and ticks at 1000 Hz, and the tip RMS against the file is printed per epoch at 1000 and
   120 Hz beside the bounds of ``REFERENCE_BOUNDS`` (the runner differences integer-ns times
   from its origin, so the figures do not depend on the epoch); live replays likewise.

4. Start-up whip (``--whip``): a head running at 2 m/s and turning at 3 rad/s (``RunAndTurn``),
   the node's defaults; the largest speed of the tip relative to the head (in the head frame)
   in the first 100 ms after the node's start, a teleport (1 m jump) and a rebuild, at 30, 120
   and 1000 Hz input (the figures ``test/test_pose_accuracy.py`` bounds by ``WHIP_BOUND``).

Not timed; the tip part runs the NumPy core for minutes.
"""
import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from ponytail_ros.bench.head_estimation_bench import sample_stream
from ponytail_ros.core import ChainSpec, Scene, Simulator, SolverSpec
from ponytail_ros.core.head import HeadMotion, KinematicState, SwayYawMotion
from ponytail_ros.core.head_estimation import HeadEstimator
from ponytail_ros.core.rotations import quat_axis_x, quat_conjugate, quat_from_rotvec, quat_rotate

RATES = (30.0, 60.0, 120.0, 250.0, 1000.0)
JITTERS = (0.0, 0.2)
MODES = ('live', 'live_interp', 'look_ahead')
#: ``live_interp``: the live node with an interpolating cubic (exact animation poses).
LIVE_INTERP = {'head.window': 0.005, 'head.degree': 3, 'head.min_samples': 4}
#: The node's default delay, in input periods (``interpolation_delay_periods``).
LIVE_DELAY_PERIODS = 2.0
TICK_RATE = 100.0
BAG_T0_NS = 100_000_000_000
KEYS = (('p', 'position'), ('v', 'linear_velocity'), ('a', 'linear_acceleration'),
        ('w', 'angular_velocity'), ('alpha', 'angular_acceleration'))


def _look_ahead_estimator():
    from ponytail_ros.core.head_spline import SplineHeadEstimator
    from ponytail_ros.recording.offline import LOOK_AHEAD_SPLINE_DEGREE, LOOK_AHEAD_VALUES as L
    return SplineHeadEstimator(spline_degree=LOOK_AHEAD_SPLINE_DEGREE,
                               degree=L['head.degree'], min_samples=L['head.min_samples'],
                               window=L['head.window'], max_samples=100000)


def estimation_errors(rate, jitter, mode, duration=6.0, n_ticks=400, seed=0, motion=None):
    """RMS errors ``{'p', 'v', 'a', 'w', 'alpha'}`` (SI, world frame) and the latency (s)."""
    motion = motion or SwayYawMotion()
    ts, ps, qs = sample_stream(motion, rate, duration, jitter=jitter, seed=seed)
    ts = np.round(ts * 1e9) * 1e-9
    ticks = np.sort(np.random.default_rng(seed + 1).uniform(1.0, duration - 0.05, n_ticks))
    err = {k: [] for k, _ in KEYS}
    if mode == 'look_ahead':
        est, delay = _look_ahead_estimator(), 0.0
        for t, p, q in zip(ts, ps, qs, strict=True):
            est.add(t, p, q)
    else:
        kw = {} if mode == 'live' else dict(window=LIVE_INTERP['head.window'],
                                            degree=LIVE_INTERP['head.degree'],
                                            min_samples=LIVE_INTERP['head.min_samples'])
        est = HeadEstimator(delay=0.0, **kw)     # else the node's defaults (RunnerSettings)
        delay = LIVE_DELAY_PERIODS / rate
    i = 0
    for tick in ticks:
        if mode != 'look_ahead':
            while i < len(ts) and ts[i] <= tick:
                est.add(ts[i], ps[i], qs[i])
                i += 1
        got, true = est.state_at(tick - delay), motion.state_at(tick - delay)
        for k, name in KEYS:
            err[k].append(getattr(got, name)[0] - getattr(true, name)[0])
    rms = {k: float(np.sqrt(np.mean(np.sum(np.square(v), axis=1)))) for k, v in err.items()}
    return rms, delay


def chain_values(dt):
    """Node parameters of the reference's 10-segment scene, RK4 at ``dt``, ticks at 100 Hz,
    outputs stamped with their simulated time."""
    return {'rate': TICK_RATE, 'head': {'max_samples': 128},
            'chains': ['ponytail'], 'colliders': [],
            'gravity': [0.0, 0.0, -9.81], 'markers': {'style': 'off'},
            'output_stamp': 'simulated',
            'solver': {'integrator': 'rk4', 'dt': dt, 'max_steps_per_call': 100000},
            'ponytail': {'n_segments': 10, 'length': 0.4, 'mass': 0.1, 'radius': 0.01,
                         'attach': [-0.1, 0.0, 0.05], 'rest_direction': [0.0, 0.0, -1.0],
                         'damping': 0.0, 'stiffness': 0.0, 'drag_linear': 0.0,
                         'drag_quadratic': 0.0}}


def write_bag(path, ts, ps, qs):
    """A ``PoseStamped`` bag (``/head_pose``, frame ``world``) of the samples, stamps and log
    times ``BAG_T0_NS + t``."""
    from geometry_msgs.msg import PoseStamped

    from ponytail_ros.recording.bag import BagWriter
    with BagWriter(path) as writer:
        writer.add_topic('/head_pose', PoseStamped)
        for t, p, q in zip(ts, ps, qs, strict=True):
            ns = BAG_T0_NS + int(round(t * 1e9))
            m = PoseStamped()
            m.header.frame_id = 'world'
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(ns, 1_000_000_000)
            m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(x) for x in p)
            (m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
             m.pose.orientation.w) = (float(x) for x in q)
            writer.write('/head_pose', m, ns)
    return path


def _exact_tips(times, dt, motion):
    """Tips of the chain driven by the exact head, at ``times`` (s, increasing)."""
    values = chain_values(dt)['ponytail']
    scene = Scene(chains=(ChainSpec(name='ponytail', n_segments=10, length=values['length'],
                                    mass=values['mass'], radius=values['radius'],
                                    attach=tuple(values['attach']),
                                    rest_direction=tuple(values['rest_direction']),
                                    damping=0.0),),
                  solver=SolverSpec(integrator='rk4', dt=dt, max_steps_per_call=1_000_000))
    sim = Simulator(scene, motion, t0=0.0)
    tips = []
    for t in times:
        sim.advance_to(t, motion)
        _, distal = sim.joint_positions(t)
        tips.append(distal[-1])
    return np.array(tips)


def tip_errors(rate, jitter, mode, dt, duration=3.0, seed=0, workdir=None, motion=None,
               exact_cache=None):
    """RMS and max tip distance (m) of the replayed chain to the exactly driven one."""
    import yaml

    from ponytail_ros.recording.compare import load_chain_runs
    from ponytail_ros.recording.offline import replay
    motion = motion or SwayYawMotion()
    # 0.4 s of poses beyond the compared span: the look-ahead fit is centred up to its end.
    ts, ps, qs = sample_stream(motion, rate, duration + 0.4, jitter=jitter, seed=seed)
    ts, ps, qs = np.concatenate([[0.0], ts]), np.vstack([motion.state_at(0.0).position, ps]), \
        np.vstack([motion.state_at(0.0).orientation, qs])
    with tempfile.TemporaryDirectory(dir=workdir) as d:
        d = Path(d)
        bag = write_bag(d / 'head.mcap', ts, ps, qs)
        params = d / 'params.yaml'
        values = chain_values(dt)
        if mode == 'live_interp':
            values['head'].update({k.split('.')[1]: v for k, v in LIVE_INTERP.items()})
        params.write_text(yaml.safe_dump({'/**': {'ros__parameters': values}}))
        out = d / 'out.mcap'
        replay(bag, out, params_file=params, look_ahead=mode == 'look_ahead')
        runs, _ = load_chain_runs(out)
    run = runs['ponytail']
    t = (run.stamps - BAG_T0_NS) * 1e-9
    keep = (t > 0.0) & (t <= duration + 1e-9)
    t, tips = t[keep], run.tips[keep]
    key = (tuple(np.round(t, 9)), dt)
    if exact_cache is not None and key in exact_cache:
        exact = exact_cache[key]
    else:
        exact = _exact_tips(t, dt, motion)
        if exact_cache is not None:
            exact_cache[key] = exact
    d = np.linalg.norm(tips - exact, axis=1)
    return float(np.sqrt(np.mean(d * d))), float(d.max())


def run(profile='quick', out=None, log=print, meta=None):
    """Both tables; returns ``(estimation_rows, tip_rows)``; writes them into ``out``."""
    tiny = profile == 'tiny'
    rates = (30.0, 1000.0) if tiny else RATES
    jitters = (0.0,) if tiny else JITTERS
    dt = {'tiny': 1 / 500, 'quick': 1 / 1000, 'full': 1 / 2000}[profile]
    duration = 0.3 if tiny else 3.0
    est_rows, tip_rows = [], []
    log('head estimation: RMS error vs the exact head (world frame, SI); live = the node '
        f'(cubic, 0.1 s window, delay {LIVE_DELAY_PERIODS:g} periods), look_ahead = '
        'ponytail_replay --look-ahead')
    log(f"{'mode':>10} {'rate':>6} {'jitter':>6} {'latency ms':>10} {'p m':>9} {'ṗ m/s':>9} "
        f"{'p̈ m/s²':>9} {'ω rad/s':>9} {'α rad/s²':>9}")
    for mode in MODES:
        for jitter in jitters:
            for rate in rates:
                e, delay = estimation_errors(rate, jitter, mode, n_ticks=60 if tiny else 400)
                est_rows.append(dict(mode=mode, rate_hz=rate, jitter=jitter,
                                     latency_ms=1e3 * delay, **{f'{k}_rms': v
                                                                 for k, v in e.items()}))
                log(f'{mode:>10} {rate:6.0f} {jitter:6.1f} {1e3 * delay:10.1f} '
                    + ' '.join(f'{e[k]:9.2e}' for k, _ in KEYS))
    log(f'\ntip error vs the exactly driven chain (10 segments, RK4 1/{1 / dt:.0f} s, '
        f'{duration:g} s, ticks {TICK_RATE:g} Hz)')
    log(f"{'mode':>10} {'rate':>6} {'jitter':>6} {'tip RMS m':>10} {'tip max m':>10} "
        f"{'wall s':>7}")
    cache = {}
    for mode in MODES:
        for jitter in jitters:
            for rate in rates:
                w0 = time.perf_counter()
                rms, mx = tip_errors(rate, jitter, mode, dt, duration=duration,
                                     exact_cache=cache)
                tip_rows.append(dict(mode=mode, rate_hz=rate, jitter=jitter, dt=dt,
                                     duration_s=duration, tip_rms_m=rms, tip_max_m=mx))
                log(f'{mode:>10} {rate:6.0f} {jitter:6.1f} {rms:10.2e} {mx:10.2e} '
                    f'{time.perf_counter() - w0:7.1f}')
    if out is not None:
        from ponytail_ros.bench.tables import make_meta, write_table
        os.makedirs(out, exist_ok=True)
        meta = meta or make_meta(profile, 'pose')
        write_table(out, 'pose_estimation', est_rows, meta)
        write_table(out, 'pose_tip', tip_rows, meta)
    return est_rows, tip_rows


#: ``--reference``: the look-ahead replays' step and tick rate (``--epoch`` figures), fine
#: enough that the core's own error on the file is below the estimation's at 120 Hz.
REFERENCE_DT = 1.0 / 8000
REFERENCE_TICK_RATE = 1000.0
#: Bounds of ``--reference``'s look-ahead tip RMS against the file (m), by head rate: what
#: ``test/test_pose_accuracy.py`` asserts (on a shortened case).
REFERENCE_BOUNDS = {1000: 1e-6, 120: 5e-5}


def epoch_ns(text):
    """Integer ns of an epoch given in seconds (``'1.7e9'``, ``'100'``), exactly."""
    from decimal import Decimal
    return int(Decimal(str(text)) * 1_000_000_000)


def write_rosbags_bag(directory, t0_ns, ns, ps, qs):
    """A rosbag2 MCAP bag written by ``rosbags`` (``rosbag2.Writer``, the ROS 2 typestore) of
    ``PoseStamped`` poses on ``/head_pose`` (frame ``world``): pose ``k`` stamped and logged at
    ``t0_ns + ns[k]`` (integers). Returns the ``.mcap`` file."""
    from rosbags import rosbag2, typesys
    store = typesys.get_typestore(getattr(typesys.Stores, 'ROS2_KILTED', typesys.Stores.LATEST))
    T = store.types
    directory = Path(directory)
    msgtype = 'geometry_msgs/msg/PoseStamped'
    with rosbag2.Writer(directory, version=9,
                        storage_plugin=rosbag2.StoragePlugin.MCAP) as writer:
        conn = writer.add_connection('/head_pose', msgtype, typestore=store)
        for k, p, q in zip(ns, np.asarray(ps).tolist(), np.asarray(qs).tolist(), strict=True):
            stamp = int(t0_ns) + int(k)
            msg = T[msgtype](
                header=T['std_msgs/msg/Header'](
                    stamp=T['builtin_interfaces/msg/Time'](sec=stamp // 10**9,
                                                          nanosec=stamp % 10**9),
                    frame_id='world'),
                pose=T['geometry_msgs/msg/Pose'](
                    position=T['geometry_msgs/msg/Point'](x=p[0], y=p[1], z=p[2]),
                    orientation=T['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2],
                                                                  w=q[3])))
            writer.write(conn, stamp, store.serialize_cdr(msg, msgtype))
    return next(directory.glob('*.mcap'))


def reference_tip_errors(rate, t0_ns, workdir, *, look_ahead=True, dt=REFERENCE_DT,
                         tick_rate=REFERENCE_TICK_RATE, duration=3.2, t_end=None):
    """Tip distances (m) to ``ponytail_N10_moving_hanging`` at its valid sample times (up to
    ``t_end`` s) of a replay of its head's poses at ``rate`` Hz (each the motion at its
    integer-ns stamp, for ``duration`` s) stamped from ``t0_ns``, written by ``rosbags``; and
    the output track ``(t, tips)``."""
    import yaml
    from scipy.interpolate import CubicSpline

    from ponytail_ros.core.reference import default_reference_dir, load_reference
    from ponytail_ros.recording.compare import load_chain_runs
    from ponytail_ros.recording.offline import replay
    ref = load_reference(default_reference_dir() / 'ponytail_N10_moving_hanging.json')
    ok = ref.t <= ref.window() + 1e-9
    if t_end is not None:
        ok &= ref.t <= t_end + 1e-9
    t_ref, tip_ref = ref.t[ok], ref.points[-1][ok]
    motion = SwayYawMotion()
    ns = [int(round(k * 1e9 / rate)) for k in range(int(round(duration * rate)) + 1)]
    states = motion.states_at(np.array(ns) * 1e-9)
    d = Path(tempfile.mkdtemp(dir=workdir))
    bag = write_rosbags_bag(d / 'head', t0_ns, ns, states.position[:, 0],
                            states.orientation[:, 0])
    values = chain_values(dt)
    values['rate'] = tick_rate
    params = d / 'params.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': values}}))
    out = d / 'out.mcap'
    replay(bag, out, params_file=params, look_ahead=look_ahead)
    run = load_chain_runs(out)[0]['ponytail']
    t = (run.stamps - t0_ns) * 1e-9
    sel = (t_ref >= t[0] - 1e-9) & (t_ref <= t[-1] + 1e-9)
    e = np.linalg.norm(CubicSpline(t, run.tips)(t_ref[sel]) - tip_ref[sel], axis=1)
    return e, (t, run.tips)


def epoch_figures(epochs=('100', '1.7e9'), rates=(1000, 120), log=print, workdir=None,
                  modes=('look_ahead', 'live')):
    """Look-ahead (RK4 ``REFERENCE_DT``, ticks ``REFERENCE_TICK_RATE``) and live (the node's
    defaults, RK4 1/1000 s, ticks 100 Hz) replays of the reference head at ``rates``, its bags
    stamped from each of ``epochs`` (s); tip RMS / max against the file over its valid window.
    Rows of dicts."""
    rows = []
    log(f"{'mode':>10} {'epoch s':>8} {'rate':>6} {'RK4 dt':>8} {'ticks Hz':>8} "
        f"{'tip RMS m':>10} {'tip max m':>10} {'bound':>8}")
    with tempfile.TemporaryDirectory(dir=workdir) as d:
        for mode in modes:
            for epoch in epochs:
                for rate in rates:
                    la = mode == 'look_ahead'
                    dt, ticks = (REFERENCE_DT, REFERENCE_TICK_RATE) if la else (1 / 1000,
                                                                                TICK_RATE)
                    e, _ = reference_tip_errors(rate, epoch_ns(epoch), d, look_ahead=la,
                                                dt=dt, tick_rate=ticks)
                    rms = float(np.sqrt(np.mean(e * e)))
                    bound = REFERENCE_BOUNDS.get(rate) if la else None
                    rows.append(dict(mode=mode, epoch_s=str(epoch), rate_hz=rate, dt=dt,
                                     tick_hz=ticks, tip_rms_m=rms, tip_max_m=float(e.max()),
                                     bound_m=bound))
                    log(f'{mode:>10} {epoch:>8} {rate:6.0f} {"1/" + format(1 / dt, ".0f"):>8} '
                        f'{ticks:8.0f} {rms:10.2e} {e.max():10.2e} '
                        f'{"" if bound is None else format(bound, ".0e"):>8}')
    return rows


def reference_figures(log=print, rates=(30, 60, 120, 1000), workdir=None):
    """Part 3 of the module docstring; returns rows of dicts."""
    import yaml
    from scipy.interpolate import CubicSpline

    from ponytail_ros.core.reference import default_reference_dir, load_reference
    from ponytail_ros.recording.compare import load_chain_runs
    from ponytail_ros.recording.offline import replay
    ref = load_reference(default_reference_dir() / 'ponytail_N10_moving_hanging.json')
    ok = ref.t <= ref.window() + 1e-9
    t_ref, tip_ref = ref.t[ok], ref.points[-1][ok]
    motion = SwayYawMotion()
    rows, tracks = [], {}
    log(f"{'mode':>10} {'rate':>6} {'RK4 dt':>8} {'tip RMS m':>10} {'tip max m':>10}")
    with tempfile.TemporaryDirectory(dir=workdir) as d:
        d = Path(d)
        for rate in rates:
            ns = [int(round(k * 1e9 / rate)) for k in range(int(round(3.2 * rate)) + 1)]
            ts = np.array(ns) * 1e-9
            states = [motion.state_at(t) for t in ts]
            bag = write_bag(d / f'head_{rate}.mcap', ts,
                            np.array([s.position[0] for s in states]),
                            np.array([s.orientation[0] for s in states]))
            for mode, dt in (('look_ahead', 1 / 2000), ('live', 1 / 1000)):
                params = d / f'{mode}.yaml'
                params.write_text(yaml.safe_dump({'/**': {'ros__parameters': chain_values(dt)}}))
                out = d / f'{mode}_{rate}.mcap'
                replay(bag, out, params_file=params, look_ahead=mode == 'look_ahead')
                run = load_chain_runs(out)[0]['ponytail']
                t = (run.stamps - BAG_T0_NS) * 1e-9
                spline = CubicSpline(t, run.tips)
                sel = (t_ref >= t[0] - 1e-9) & (t_ref <= t[-1] + 1e-9)
                e = np.linalg.norm(spline(t_ref[sel]) - tip_ref[sel], axis=1)
                tracks[mode, rate] = spline, t[0]
                rows.append(dict(mode=mode, rate_hz=rate, dt=dt,
                                 tip_rms_m=float(np.sqrt(np.mean(e * e))),
                                 tip_max_m=float(e.max())))
                log(f'{mode:>10} {rate:6.0f} {"1/" + format(1 / dt, ".0f"):>8} '
                    f'{rows[-1]["tip_rms_m"]:10.2e} {rows[-1]["tip_max_m"]:10.2e}')
    for mode in ('look_ahead', 'live'):
        t_lo = max(tracks[mode, r][1] for r in rates)
        grid = np.arange(np.ceil(t_lo * TICK_RATE), 3.0 * TICK_RATE + 1) / TICK_RATE
        worst = [0.0, 0.0]
        for i, a in enumerate(rates):
            for b in rates[i + 1:]:
                dist = np.linalg.norm(tracks[mode, a][0](grid) - tracks[mode, b][0](grid), axis=1)
                worst = [max(worst[0], float(np.sqrt(np.mean(dist * dist)))),
                         max(worst[1], float(dist.max()))]
        rows.append(dict(mode=mode, rate_hz='pairwise', tip_rms_m=worst[0], tip_max_m=worst[1]))
        log(f'{mode:>10} between rates, over 3 s: largest RMS {worst[0]:.2e} m, '
            f'largest max {worst[1]:.2e} m')
    return rows


# -- start-up whip -----------------------------------------------------------------------------

class RunAndTurn(HeadMotion):
    """The head running at ``speed`` m/s along world +X while turning at ``rate`` rad/s about
    world +Z (constant), at 1.6 m, jumping by ``jump`` (m) at ``t_jump`` (a teleport); exact
    derivatives."""

    def __init__(self, speed=2.0, rate=3.0, t_jump=None, jump=(1.0, 0.0, 0.0)):
        self.speed, self.rate = float(speed), float(rate)
        self.t_jump, self.jump = t_jump, np.asarray(jump, dtype=float)

    def state_at(self, t):
        p = np.array([self.speed * t, 0.0, 1.6])
        if self.t_jump is not None and t >= self.t_jump:
            p = p + self.jump
        return KinematicState(
            position=p[None],
            orientation=quat_from_rotvec(np.array([0.0, 0.0, self.rate * t]))[None],
            linear_velocity=np.array([[self.speed, 0.0, 0.0]]),
            angular_velocity=np.array([[0.0, 0.0, self.rate]]),
            linear_acceleration=np.zeros((1, 3)), angular_acceleration=np.zeros((1, 3)))


#: Bound on the tip's speed relative to the head in the first 100 ms after a (re)start on
#: ``RunAndTurn`` (m/s): the chain starts moving with the head, so only the physical response
#: to the turn (centrifugal swing-out, ω² r ≈ 0.8 m/s² at the attachment) moves it; a chain
#: started at rest in the world lags the head at ≈ |v + ω × r| ≈ 2 m/s instead.
WHIP_BOUND = 0.15
WHIP_SEGMENTS, WHIP_LENGTH = 8, 0.3


def whip_scene(radius=0.03):
    """A ponytail: 8 segments, 0.3 m, 0.1 kg, damping 1e-3, linear drag 0.02."""
    return Scene(chains=(ChainSpec(name='ponytail', n_segments=WHIP_SEGMENTS,
                                   length=WHIP_LENGTH, mass=0.1, radius=radius,
                                   attach=(-0.09, 0.0, 0.06), damping=1e-3,
                                   drag_linear=0.02),))


def relative_tip_speeds(outs, motion, t_from, window=0.1):
    """Speed (m/s) of the tip relative to the head (the rate of change of its position in the
    head frame) between consecutive outputs in ``[t_from, t_from + window]``, at the outputs'
    own (simulated) times ``TickOutput.t_state``."""
    seg = WHIP_LENGTH / WHIP_SEGMENTS
    pts = []
    for o in outs:
        if not (t_from - 1e-9 <= o.t_state <= t_from + window + 1e-9):
            continue
        tip = o.origins[-1] + quat_axis_x(o.orientations[-1:])[0] * seg
        s = motion.state_at(o.t_state)
        pts.append((o.t_state, quat_rotate(quat_conjugate(s.orientation[0]),
                                           tip - s.position[0])))
    t = np.array([p[0] for p in pts])
    x = np.array([p[1] for p in pts])
    return np.linalg.norm(np.diff(x, axis=0), axis=1) / np.diff(t)


def start_whip(case, input_rate, tick_rate=120.0, t_event=0.6):
    """Relative tip speeds (m/s) in the first 100 ms after ``case`` (``'start'``: the node's
    first output; ``'teleport'``: a 1 m jump of the running head at ``t_event``;
    ``'rebuild'``: a structural change at ``t_event``), the node's defaults with
    ``output_stamp: simulated``. Returns ``(speeds, runner, t_from)``."""
    from ponytail_ros.app.runner import ChainRunner, RunnerSettings
    t_event = 0.0 if case == 'start' else t_event
    motion = RunAndTurn(t_jump=t_event if case == 'teleport' else None)
    r = ChainRunner(whip_scene(), RunnerSettings(output_stamp='simulated'))
    outs, tp, tt, rebuilt = [], 0.0, 0.0, False
    while tt < t_event + 0.3:
        while tp <= tt + 1e-12:
            s = motion.state_at(tp)
            r.push(tp, s.position[0], s.orientation[0], 'world')
            tp += 1.0 / input_rate
        if case == 'rebuild' and not rebuilt and tt >= t_event:
            r.set_scene(whip_scene(radius=0.031))        # structural: rebuilt at rest
            rebuilt = True
        o = r.tick(tt)
        if o is not None:
            outs.append(o)
        tt += 1.0 / tick_rate
    if case == 'start':
        t_from = outs[0].t_state
    else:
        t_from = next(o.t_state for o in outs if o.reset_reason == case)
    return relative_tip_speeds(outs, motion, t_from), r, t_from


def whip_figures(log=print):
    rows = []
    log(f"{'case':>9} {'input Hz':>8} {'max relative tip speed m/s':>27}  (bound {WHIP_BOUND})")
    for case in ('start', 'teleport', 'rebuild'):
        for rate in (30.0, 120.0, 1000.0):
            v, r, _ = start_whip(case, rate)
            rows.append(dict(case=case, input_hz=rate, max_relative_tip_speed=float(v.max()),
                             guard_resets=r.resets['guard']))
            log(f'{case:>9} {rate:8.0f} {v.max():27.3f}')
    return rows


def cmd_pose(prof, out, meta, log=print):
    """``ponytail_bench pose``: the profile's name is in ``meta``."""
    return run(meta.get('profile', 'quick'), out, log, meta)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = parser.add_mutually_exclusive_group()
    g.add_argument('--quick', dest='profile', action='store_const', const='quick')
    g.add_argument('--full', dest='profile', action='store_const', const='full')
    g.add_argument('--tiny', dest='profile', action='store_const', const='tiny')
    parser.add_argument('--out', default=None, help='write pose_*.csv/json here')
    parser.add_argument('--reference', action='store_true',
                        help='only part 3: replays of the shared reference head')
    parser.add_argument('--epoch', action='append', default=None, metavar='SECONDS',
                        help='with --reference: stamp the head bags (written by rosbags) from '
                             'this epoch (s, e.g. 1.7e9; repeat for several) and print the '
                             'look-ahead (RK4 1/8000 s, ticks 1000 Hz) and live tip errors at '
                             '1000 and 120 Hz')
    parser.add_argument('--whip', action='store_true',
                        help='only part 4: start-up whip on a running, turning head')
    args = parser.parse_args(argv)
    log = lambda *a: print(*a, flush=True)  # noqa: E731
    if args.whip:
        whip_figures(log)
        return
    if args.reference and args.epoch:
        rows = epoch_figures(args.epoch, log=log)
        if args.out:
            from ponytail_ros.bench.tables import make_meta, write_table
            os.makedirs(args.out, exist_ok=True)
            write_table(args.out, 'pose_epoch', rows, make_meta('reference', 'pose'))
        return
    if args.reference:
        rows = reference_figures(log)
        if args.out:
            from ponytail_ros.bench.tables import make_meta, write_table
            os.makedirs(args.out, exist_ok=True)
            write_table(args.out, 'pose_reference', rows, make_meta('reference', 'pose'))
        return
    run(args.profile or 'quick', args.out, log)


if __name__ == '__main__':
    main()
