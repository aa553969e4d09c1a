"""Latency versus smoothness of ``HeadEstimator``: RMS errors against an exact head motion.

The head follows ``SwayYawMotion`` (sway 5 cm at 1.5 Hz, yaw 0.6 rad at 0.8 Hz, exact
derivatives). Pose samples are taken at 30/60/120/1000 Hz with ±20 % timing jitter (the stamps are
exact but irregular), optionally with Gaussian noise; each sample becomes available at its own
stamp. At random tick times the estimator is evaluated causally (only samples stamped before the
tick) with delays of 0, 1 and 2 sample periods, and compared with the exact state at
``tick - delay`` (the estimation error; the latency itself is the delay). Errors are RMS
relative to the RMS of the true signal, in %:

    v: linear velocity   a: linear acceleration   ω: angular velocity   α: angular acceleration

Then, at 120 Hz with a delay of one period, the same for polynomial degrees 2–4 and windows
0.05–0.2 s, exact and noisy: the bias/noise trade behind the defaults.

Run: ``python -m ponytail_ros.bench.head_estimation_bench [--quick]``; ``--cost``: instead,
the CPU time of one pose fit at each rate.
"""
import argparse

import numpy as np

from ponytail_ros.core.head import SwayYawMotion
from ponytail_ros.core.head_estimation import HeadEstimator
from ponytail_ros.core.rotations import quat_from_rotvec, quat_multiply

RATES = (30.0, 60.0, 120.0, 1000.0)
DELAY_PERIODS = (0, 1, 2)


def sample_stream(motion, rate, duration, jitter=0.2, pos_noise=0.0, rot_noise=0.0, seed=0):
    """Sample stamps (s), positions ``(n, 3)`` and orientations ``(n, 4)`` of ``motion``."""
    rng = np.random.default_rng(seed)
    period = 1.0 / rate
    n = int(duration * rate * 1.3) + 2
    dts = period * (1.0 + jitter * rng.uniform(-1.0, 1.0, n))
    ts = np.cumsum(dts)
    ts = ts[ts < duration]
    ps = np.empty((len(ts), 3))
    qs = np.empty((len(ts), 4))
    for i, t in enumerate(ts):
        s = motion.state_at(t)
        ps[i], qs[i] = s.position[0], s.orientation[0]
    ps += pos_noise * rng.standard_normal(ps.shape)
    if rot_noise > 0.0:
        qs = quat_multiply(quat_from_rotvec(rot_noise * rng.standard_normal((len(ts), 3))), qs)
    return ts, ps, qs


def measure(rate, delay, duration=6.0, warmup=1.0, n_ticks=600, jitter=0.2, pos_noise=0.0,
            rot_noise=0.0, seed=0, motion=None, **estimator_kwargs):
    """Relative RMS errors (fractions) ``{'v', 'a', 'w', 'alpha'}`` of the estimate."""
    motion = motion or SwayYawMotion()
    ts, ps, qs = sample_stream(motion, rate, duration, jitter, pos_noise, rot_noise, seed)
    est = HeadEstimator(delay=delay, **estimator_kwargs)
    rng = np.random.default_rng(seed + 1)
    ticks = np.sort(rng.uniform(warmup, duration - 0.05, n_ticks))
    keys = ('linear_velocity', 'linear_acceleration', 'angular_velocity', 'angular_acceleration')
    err = {k: [] for k in keys}
    ref = {k: [] for k in keys}
    i = 0
    for tick in ticks:
        while i < len(ts) and ts[i] <= tick:
            est.add(ts[i], ps[i], qs[i])
            i += 1
        got = est.state_at(tick)
        true = motion.state_at(tick - delay)
        for k in keys:
            err[k].append(getattr(got, k)[0] - getattr(true, k)[0])
            ref[k].append(getattr(true, k)[0])
    rel = {k: np.sqrt(np.mean(np.sum(np.square(err[k]), axis=1))
                      / np.mean(np.sum(np.square(ref[k]), axis=1))) for k in keys}
    return dict(zip(('v', 'a', 'w', 'alpha'), (rel[k] for k in keys), strict=True))


def table(title, pos_noise=0.0, rot_noise=0.0, n_ticks=600, **estimator_kwargs):
    lines = [title,
             f"{'rate Hz':>8} {'delay':>9} {'v %':>7} {'a %':>7} {'ω %':>7} {'α %':>7}"]
    for rate in RATES:
        for k in DELAY_PERIODS:
            r = measure(rate, k / rate, pos_noise=pos_noise, rot_noise=rot_noise,
                        n_ticks=n_ticks, **estimator_kwargs)
            delay_txt = f'{k}T={1e3 * k / rate:.1f}ms' if k else '0'
            lines.append(f"{rate:8.0f} {delay_txt:>9} {100 * r['v']:7.2f} {100 * r['a']:7.2f} "
                         f"{100 * r['w']:7.2f} {100 * r['alpha']:7.2f}")
    return '\n'.join(lines)


def design_table(rate=120.0, delay_periods=1, pos_noise=0.0, rot_noise=0.0, n_ticks=600):
    """Errors at one rate and delay for several degrees and windows (how the defaults were
    chosen)."""
    lines = [f"{'degree':>6} {'window':>7} {'v %':>7} {'a %':>7} {'ω %':>7} {'α %':>7}"]
    for degree in (2, 3, 4):
        for window in (0.05, 0.1, 0.15, 0.2):
            r = measure(rate, delay_periods / rate, pos_noise=pos_noise, rot_noise=rot_noise,
                        n_ticks=n_ticks, degree=degree, window=window)
            lines.append(f"{degree:6d} {window:7.2f} {100 * r['v']:7.2f} {100 * r['a']:7.2f} "
                         f"{100 * r['w']:7.2f} {100 * r['alpha']:7.2f}")
    return '\n'.join(lines)


def fit_cost(rates=RATES, repeats=2000, **kw):
    """CPU µs per ``state_at`` (one pose fit, the memo bypassed) with a full history at each
    rate, best of five rounds: what each of a tick's three fits costs."""
    import time
    out = {}
    motion = SwayYawMotion()
    for rate in rates:
        e = HeadEstimator(**kw)
        for t, p, q in zip(*sample_stream(motion, rate, 1.5), strict=True):
            e.add(t, p, q)
        t_eval = e.last_stamp - 0.5 / rate
        e._state_at(t_eval)
        best = np.inf
        for _ in range(5):
            t0 = time.process_time()
            for _ in range(repeats):
                e._state_at(t_eval)
            best = min(best, (time.process_time() - t0) / repeats)
        out[rate] = 1e6 * best
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--quick', action='store_true', help='fewer ticks, no design table')
    parser.add_argument('--cost', action='store_true',
                        help='only the CPU time of one pose fit at each rate')
    parser.add_argument('--window', type=float, default=None)
    parser.add_argument('--degree', type=int, default=None)
    parser.add_argument('--min-samples', type=int, default=None)
    args = parser.parse_args(argv)
    kw = {k: v for k, v in (('window', args.window), ('degree', args.degree),
                            ('min_samples', args.min_samples)) if v is not None}
    if args.cost:
        e = HeadEstimator(**kw)
        for rate, us in fit_cost(**kw).items():
            stored = min(e.max_samples, int(rate * 1.5))
            print(f'{rate:6.0f} Hz: {us:6.2f} µs per pose fit (~{stored} samples stored, '
                  f'window {e.window} s)')
        return
    n = 200 if args.quick else 600
    e = HeadEstimator(**kw)
    print(f'HeadEstimator(window={e.window}, degree={e.degree}, min_samples={e.min_samples}, '
          f'max_samples={e.max_samples}); relative RMS errors vs the exact state at '
          'tick - delay, ±20 % stamp jitter')
    print(table('\nexact samples', n_ticks=n, **kw))
    print(table('\nnoisy samples: 0.1 mm position, 1 mrad orientation (Gaussian, per axis)',
                pos_noise=1e-4, rot_noise=1e-3, n_ticks=n, **kw))
    if not args.quick:
        print('\ndegree and window at 120 Hz, delay 1 period: exact samples')
        print(design_table(n_ticks=300))
        print('\ndegree and window at 120 Hz, delay 1 period: noisy samples (0.1 mm, 1 mrad)')
        print(design_table(pos_noise=1e-4, rot_noise=1e-3, n_ticks=300))


if __name__ == '__main__':
    main()
