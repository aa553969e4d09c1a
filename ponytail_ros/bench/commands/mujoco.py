"""``mujoco``: the same chain in MuJoCo (RK4, head driven exactly) side by side with this core.

Several segment counts and steps, cross-checks of the reference at a tiny step, and a long
undamped run of both engines at game steps: ``mujoco.csv/json``, ``mujoco.png``. Skipped (an
empty table saying so) when the optional ``mujoco`` package is not installed.
"""
import os
import time
import warnings

import numpy as np

from ponytail_ros.core.simulator import Simulator

from .. import measure as M, mujoco_chain as MJ, plots
from ..profiles import RK4, Profile, S
from ..scenes import REFERENCE_DIR, BenchScene, make_scene
from ..tables import Column, Log, Meta, Row, print_table, write_table
from .trade import draw_pareto

HELP = 'the same chain in MuJoCo side by side (optional mujoco package)'


def _vs_shared(b: BenchScene, ts: np.ndarray,
               tips: np.ndarray) -> tuple[float | None, float | None]:
    """Tip RMS/max (mm) against the shared file over its whole run, at the common sample times
    (every 10 ms when dt divides it; 1/240 s meets the 10 ms grid every 50 ms)."""
    if not b.shared:
        return None, None
    shared = M.load_shared(b.shared, REFERENCE_DIR)
    if shared is None:
        return None, None
    idx = np.round(ts / 0.01).astype(int)
    on = (np.abs(idx * 0.01 - ts) < 1e-9) & (idx < len(shared['t'])) & (ts > 0)
    if not on.any():
        return None, None
    tip = np.asarray(shared['points'])[b.n_segments - 1]
    e = np.linalg.norm(tips[on] - tip[idx[on]], axis=1)
    return float(np.sqrt(np.mean(e ** 2))) * 1e3, float(e.max()) * 1e3


def _our_tip_run(b: BenchScene, dt: float, T: float) -> tuple[np.ndarray, np.ndarray]:
    """This core's tip every 10 ms (RK4 at ``dt``, head exact): (times, tips)."""
    sim = Simulator(b.scene.replace(solver=S(RK4, dt).solver()), b.motion, 0.0)
    ts, tips = [0.0], [M._tip(sim)[0]]
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)
        for k in range(1, int(round(T / 0.01)) + 1):
            sim.advance_to(k * 0.01, b.motion)
            ts.append(sim.t)
            tips.append(M._tip(sim)[0])
    return np.array(ts), np.array(tips)


def run(prof: Profile, out: str, meta: Meta, log: Log = print) -> list[Row]:
    """MuJoCo side by side."""
    if not MJ.available():
        print('\nMuJoCo side by side: skipped (mujoco not installed: pip install mujoco)')
        write_table(out, 'mujoco', [], meta, dict(skipped='mujoco not installed'))
        return []
    rows: list[Row] = []
    checks: list[Row] = []
    budget = prof['mujoco_budget_s']
    for n in prof['mujoco_n']:
        T = prof['mujoco_duration'] if n <= 50 else min(1.0, prof['mujoco_duration'])
        b = make_scene('moving', n_segments=n, duration=T)
        t0 = time.perf_counter()
        ref = M.reference(b, prof['mujoco_dt_ref'])
        checks.append(dict(n_segments=n, duration_s=T, dt=M.fmt_dt(prof['mujoco_dt_ref']),
                           ref_self_error_mm=ref.self_error * 1e3,
                           ref_valid_until_s=ref.valid_until))
        if n <= prof['mujoco_crosscheck_max']:
            # Independent check of the reference: MuJoCo at the same tiny step.
            mc = MJ.MujocoChain(b, prof['mujoco_dt_ref'])
            ts, tips, herr, unst = mc.run(T)
            e = np.linalg.norm(tips - ref.at(ts), axis=1)
            checks[-1].update(ours_vs_mujoco_max_mm=float(e.max()) * 1e3,
                              ours_vs_mujoco_rms_mm=float(np.sqrt(np.mean(e ** 2))) * 1e3)
            if b.shared:
                c = M.check_against_shared(ref, M.load_shared(b.shared, REFERENCE_DIR), n)
                checks[-1]['ours_vs_shared_max_mm'] = c['max_m'] * 1e3
                checks[-1]['mujoco_vs_shared_max_mm'] = _vs_shared(b, ts, tips)[1]
        mj_us = MJ.MujocoChain(b, 1e-3).time_steps(max(3, min(200, int(2e5 / (n * n + 50)))), 1)
        our_us = 700e-6 + 4e-6 * n          # rough, only to stay within the budget
        for dt in prof['mujoco_dts']:
            steps = int(round(T / dt))
            if mj_us * steps <= budget:
                mc = MJ.MujocoChain(b, dt)
                c0 = time.process_time()
                ts, tips, herr, unst = mc.run(T)
                run_cpu = time.process_time() - c0
                # each timing repeat ~0.2 s of CPU (or the whole run if shorter)
                k = max(5, min(steps, int(0.2 / max(mj_us, 1e-7))))
                us = mc.time_steps(k, prof['repeats'])
                inside = ts <= ref.valid_until + 1e-9
                e = np.linalg.norm(tips[inside] - ref.at(ts[inside]), axis=1)
                stable = (not unst) and bool(np.all(np.isfinite(e)))
                sh_rms, sh_max = _vs_shared(b, ts, tips) if stable else (None, None)
                rows.append(dict(engine='mujoco', scene='moving', n_segments=n, dt=dt,
                                 dt_label=M.fmt_dt(dt), duration_s=T, cpu_us_per_step=us * 1e6,
                                 cpu_s_per_sim_s=us / dt, run_cpu_s_per_sim_s=run_cpu / T,
                                 tip_rms_mm=(float(np.sqrt(np.mean(e ** 2))) * 1e3 if stable
                                             else float('nan')),
                                 tip_max_mm=float(np.max(e)) * 1e3 if stable else float('nan'),
                                 error_window_s=ref.valid_until, tip_rms_vs_shared_full_mm=sh_rms,
                                 stable=stable, head_error_m=herr, resets=int(unst)))
            if dt <= prof['mujoco_dt_ref'] * 1.0001 or our_us * steps * 2 > 3 * budget:
                continue            # the reference itself, or too costly for this profile
            ours = M.run_setting(b, S(RK4, dt), ref, repeats=prof['repeats'],
                                 timing_window=min(prof['timing_window'], T))
            sh_rms = None
            if b.shared and ours['stable']:
                sh_rms = _vs_shared(b, *_our_tip_run(b, dt, T))[0]
            rows.append(dict(engine='ours', scene='moving', n_segments=n, dt=dt,
                             dt_label=M.fmt_dt(dt), duration_s=T,
                             cpu_us_per_step=ours['cpu_us_per_step'],
                             cpu_s_per_sim_s=ours['cpu_s_per_sim_s'], run_cpu_s_per_sim_s=None,
                             tip_rms_mm=ours['tip_rms_mm'], tip_max_mm=ours['tip_max_mm'],
                             error_window_s=ref.valid_until, tip_rms_vs_shared_full_mm=sh_rms,
                             stable=ours['stable'], head_error_m=0.0, resets=ours['resets']))
        log(f'  mujoco N={n} done in {time.perf_counter() - t0:.1f} s')
    long_rows = _long_run(prof)
    cols: list[Column] = [
            ('engine', 'engine', ''), ('N', 'n_segments', 'd'), ('dt', 'dt_label', ''),
            ('µs/step', 'cpu_us_per_step', '.1f'),
            ('CPU ms/sim-s', lambda r: r['cpu_s_per_sim_s'] * 1e3, '.1f'),
            ('tip RMS mm', 'tip_rms_mm', '.3g'), ('tip max mm', 'tip_max_mm', '.3g'),
            ('window s', 'error_window_s', '.2f'),
            ('RMS vs shared, whole run, mm', 'tip_rms_vs_shared_full_mm', '.3g'),
            ('stable', 'stable', ''), ('head err m', 'head_error_m', '.1e')]
    print_table(rows, cols, title='This core vs MuJoCo 4 (RK4, head driven exactly), moving-head '
                                  'ponytail (MuJoCo README: 16, 0.89, 0.0018 mm RMS at 1/240, '
                                  '1/1000, 1/4000 s; unstable at 1/60 s)')
    print_table(checks, [('N', 'n_segments', 'd'), ('T s', 'duration_s', '.1f'), ('dt', 'dt', ''),
                         ('ref self-error mm', 'ref_self_error_mm', '.2e'),
                         ('valid until s', 'ref_valid_until_s', '.2f'),
                         ('ours vs MuJoCo max mm', 'ours_vs_mujoco_max_mm', '.2e'),
                         ('ours vs shared max mm', 'ours_vs_shared_max_mm', '.2e'),
                         ('MuJoCo vs shared max mm', 'mujoco_vs_shared_max_mm', '.2e')],
                title='Reference cross-checks (tiny step)')
    print_table(long_rows, [('engine', 'engine', ''), ('N', 'n_segments', 'd'),
                            ('dt', 'dt_label', ''), ('simulated s', 'duration_s', '.1f'),
                            ('first blow-up at s', 'first_failure_s', '.2f'),
                            ('blow-ups', 'failures', 'd')],
                title='Long run on the moving head, undamped (robustness at game steps)')
    _print_mujoco_verdict(rows)
    write_table(out, 'mujoco', rows, meta, dict(reference_checks=checks, long_run=long_rows,
                                                warnings=MJ.warnings_seen()[:20]))
    plots.mujoco_plot(rows, os.path.join(out, 'mujoco.png'))
    draw_pareto(out)
    return rows


def _long_run(prof: Profile) -> list[Row]:
    """Both engines on the undamped moving-head ponytail (N = 10) for ``long_run_s`` at 1/240 and
    1/120 s: when (if ever) does each blow up? (MuJoCo resets itself on a bad qacc; the core's
    guard resets and reports.)"""
    T = prof.get('long_run_s', 0.0)
    rows: list[Row] = []
    if not T:
        return rows
    b = make_scene('moving', duration=T)
    for dt in (1 / 240, 1 / 120):
        mc = MJ.MujocoChain(b, dt)
        m, d = mc.model, mc.data
        first, fails = None, 0
        n_before = d.warning[MJ.mujoco.mjtWarning.mjWARN_BADQACC].number
        for k in range(int(round(T / dt))):
            MJ.mujoco.mj_step(m, d)
            n = d.warning[MJ.mujoco.mjtWarning.mjWARN_BADQACC].number
            if n > n_before:
                fails += n - n_before
                n_before = n
                if first is None:
                    first = (k + 1) * dt
                mc.reset()          # start over, as the core's guard does
                d.time = (k + 1) * dt
        rows.append(dict(engine='mujoco', n_segments=10, dt=dt, dt_label=M.fmt_dt(dt),
                         duration_s=T, first_failure_s=first, failures=fails))
        sim = Simulator(b.scene.replace(solver=S(RK4, dt).solver()), b.motion, 0.0)
        first, fails = None, 0
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', RuntimeWarning)
            for k in range(1, int(round(T * 10)) + 1):
                r = sim.advance_to(k / 10, b.motion)
                if r.reset_reason:
                    fails += 1
                    first = first if first is not None else sim.t
        rows.append(dict(engine='ours', n_segments=10, dt=dt, dt_label=M.fmt_dt(dt),
                         duration_s=T, first_failure_s=first, failures=fails))
    return rows


def _print_mujoco_verdict(rows: list[Row]) -> None:
    print('\nPer segment count, cost per step (ours / MuJoCo) and error at the same step:')
    for n in sorted({r['n_segments'] for r in rows}):
        for dt in sorted({r['dt'] for r in rows if r['n_segments'] == n}, reverse=True):
            here = [r for r in rows if r['n_segments'] == n and r['dt'] == dt]
            ours = [r for r in here if r['engine'] == 'ours']
            theirs = [r for r in here if r['engine'] == 'mujoco']
            if ours and theirs:
                o, m = ours[0], theirs[0]
                ratio = o['cpu_us_per_step'] / m['cpu_us_per_step']
                faster = 'MuJoCo' if ratio > 1 else 'ours'
                print(f'  N={n:4d} dt={o["dt_label"]:>7}: {faster} {max(ratio, 1 / ratio):.1f}x '
                      f'cheaper per step; tip RMS ours {o["tip_rms_mm"]:.3g} mm vs MuJoCo '
                      f'{m["tip_rms_mm"]:.3g} mm' + ('' if m['stable'] else ' (MuJoCo unstable)')
                      + ('' if o['stable'] else ' (ours reset)'))
