"""``ponytail_bench``: the speed/accuracy trade of the chain solver, measured.

Subcommands (default ``all``):

``trade``    sweep integrator, internal step, linear solver (banded/dense), stabilisation
             (projection, Baumgarte), head tick rate and segment count on the named scenes
             (``scenes``: moving, release, shake, rope); per setting the CPU cost per simulated
             second and per step, the tip error (RMS/max, mm) against a converged reference (this
             core's RK4 at a tiny step, itself checked against ``../shared/reference/`` and by
             Richardson), the joint gap and, on still heads, the energy drift. Writes
             ``trade.csv/json``, ``refcheck.csv/json``, ``pareto.png``; prints and stores the
             recommended default (``summary.json``).
``scaling``  cost per step vs segment count (1..1000), banded RK4 / symplectic Euler / RATTLE,
             dense, MuJoCo if installed: ``scaling.csv/json``, ``scaling.png``.
``mujoco``   the same chain in MuJoCo (RK4, head driven exactly) side by side with this core for
             several segment counts and steps: ``mujoco.csv/json``, ``mujoco.png``.
``batch``    C = 1, 10, 100, 1000 chains of 20 segments in one scene (one banded solve) vs one
             chain alone and vs C separate simulators: ``batch.csv/json``.
``energy``   still anchor, no damping, 5 segments released 45° from vertical, 10 s: relative
             energy drift per integrator and step: ``energy.csv/json``, ``energy.png``.
``terms``    what each force term, collider and joint limit costs on a 20-segment ponytail
             (each added in turn; switched-off terms against the plain scene), and what each
             ready-made scene (``config/*.yaml``) costs: ``terms.csv/json``,
             ``scenes.csv/json``.
``refcheck`` this core's RK4 against every file of ``../shared/reference/``.
``pose``     the head estimation's errors and the tip error they cause, live and look-ahead,
             30-1000 Hz input with and without jitter (``pose_bench.py``; not in ``all``).
``report``   ``results.md``: all tables of the JSON files in the output directory, as markdown
             (also written at the end of ``all``).

Profiles: ``--quick`` (the default; ~2–3 min on one core), ``--full`` (all of it; ~30–40 min),
``--tiny`` (seconds; for the tests). Timings are CPU seconds (``time.process_time``) with BLAS
pinned to one thread, median of repeats.
"""
import os
import sys

# One BLAS thread: reproducible timings, and the dense solve is not slowed by thread contention.
_PINNED = 'numpy' not in sys.modules
for _v in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_v, '1')

import argparse  # noqa: E402
import csv  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402

from ponytail_ros.core.head import HeadMotion, StillMotion  # noqa: E402
from ponytail_ros.core.scene import ChainSpec, Scene, SolverSpec  # noqa: E402
from ponytail_ros.core.simulator import Simulator  # noqa: E402

from . import measure as M  # noqa: E402
from . import mujoco_chain as MJ  # noqa: E402
from . import plots  # noqa: E402
from . import pose_bench  # noqa: E402
from .motions import crowd_motion, reference_motion  # noqa: E402
from .scenes import (EXTRA_SCENES, REFERENCE_DIR, SCENES, BenchScene, make_scene,  # noqa: E402
                     ponytail_chain)

RK4, SE, RATTLE = 'rk4', 'symplectic_euler', 'rattle'
S = M.Setting


def _settings_quick():
    return ([S(RK4, 1 / hz) for hz in (60, 120, 240, 480, 960)]
            + [S(SE, 1 / hz) for hz in (240, 960, 1920)]
            + [S(RATTLE, 1 / hz) for hz in (240, 480, 960)]
            + [S(RK4, 1 / 240, linear_solver='dense'),
               S(RK4, 1 / 240, projection=False),
               S(RK4, 1 / 240, projection=False, baumgarte_stiffness=1e4, baumgarte_damping=200.0),
               S(RK4, 1 / 240, tick_rate=30.0), S(RK4, 1 / 240, tick_rate=60.0)])


def _settings_full():
    return ([S(RK4, 1 / hz) for hz in (30, 60, 120, 240, 360, 480, 960, 2000)]
            + [S(SE, 1 / hz) for hz in (120, 240, 480, 960, 1920, 3840, 7680)]
            + [S(RATTLE, 1 / hz) for hz in (120, 240, 480, 960, 1920, 3840)]
            + [S(RK4, 1 / 240, linear_solver='dense'), S(SE, 1 / 960, linear_solver='dense'),
               S(RK4, 1 / 240, projection=False), S(SE, 1 / 960, projection=False),
               S(RK4, 1 / 240, projection=False, baumgarte_stiffness=1e4, baumgarte_damping=200.0),
               S(RK4, 1 / 240, baumgarte_stiffness=1e4, baumgarte_damping=200.0),
               S(SE, 1 / 960, projection=False, baumgarte_stiffness=1e4, baumgarte_damping=200.0),
               S(RK4, 1 / 240, tick_rate=30.0), S(RK4, 1 / 240, tick_rate=60.0),
               S(RK4, 1 / 240, tick_rate=120.0), S(SE, 1 / 960, tick_rate=60.0)])


def _settings_tiny():
    return [S(RK4, 1 / 240), S(SE, 1 / 480), S(RATTLE, 1 / 480),
            S(RK4, 1 / 240, linear_solver='dense'),
            S(RK4, 1 / 240, tick_rate=60.0)]


PROFILES = {
    'tiny': dict(
        scenes=SCENES, durations=dict(moving=0.1, release=0.1, shake=0.1, rope=0.1, damped=0.1),
        dt_ref=1 / 1920, repeats=1, timing_window=0.05, settings=_settings_tiny,
        seg_counts=(3,), seg_settings=[S(RK4, 1 / 240)],
        scaling_n=(1, 3, 10), dense_max=10, scaling_steps_budget=2e4, scaling_repeats=1,
        mujoco_n=(3,), mujoco_dts=(1 / 240, 1 / 960), mujoco_duration=0.1, mujoco_dt_ref=1 / 1920,
        mujoco_crosscheck_max=10, mujoco_scaling_max=10, mujoco_budget_s=5.0, long_run_s=0.5,
        batch_c=(1, 3), batch_segments=5, batch_steps=2, batch_loop_max=3, batch_repeats=1,
        energy_T=0.2, energy_settings=[S(RK4, 1 / 240), S(SE, 1 / 480), S(RATTLE, 1 / 480)],
        terms_seconds=0.05, terms_repeats=1),
    'quick': dict(
        scenes=SCENES, durations=dict(moving=3.0, release=1.5, shake=2.0, rope=1.5, damped=3.0),
        dt_ref=1 / 4000, repeats=3, timing_window=0.25, settings=_settings_quick,
        seg_counts=(), seg_settings=[],
        scaling_n=(1, 3, 10, 30, 100, 300, 1000), dense_max=100, scaling_steps_budget=3e4,
        scaling_repeats=3,
        mujoco_n=(10, 50), mujoco_dts=(1 / 60, 1 / 240, 1 / 1000, 1 / 4000), mujoco_duration=3.0,
        mujoco_dt_ref=1 / 4000, mujoco_crosscheck_max=20, mujoco_scaling_max=100,
        mujoco_budget_s=5.0, long_run_s=30.0,
        batch_c=(1, 10, 100, 1000), batch_segments=20, batch_steps=6, batch_loop_max=100,
        batch_repeats=3,
        energy_T=10.0, energy_settings=[S(RK4, 1 / hz) for hz in (60, 120, 240, 480)]
        + [S(SE, 1 / hz) for hz in (240, 480, 960, 1920)]
        + [S(RATTLE, 1 / hz) for hz in (240, 480, 960, 1920)],
        terms_seconds=2.0, terms_repeats=3),
    'full': dict(
        scenes=SCENES + ('damped',),
        durations=dict(moving=3.0, release=1.9, shake=2.0, rope=2.0, damped=3.0),
        dt_ref=1 / 8000, repeats=5, timing_window=1.0, settings=_settings_full,
        seg_counts=(2, 5, 20, 40),
        seg_settings=[S(RK4, 1 / 240), S(RK4, 1 / 480), S(RK4, 1 / 960), S(SE, 1 / 960),
                      S(SE, 1 / 3840), S(RATTLE, 1 / 960)],
        scaling_n=(1, 2, 5, 10, 20, 50, 100, 200, 500, 1000), dense_max=300,
        scaling_steps_budget=1e5, scaling_repeats=5,
        mujoco_n=(10, 20, 50, 100, 200), mujoco_dts=(1 / 60, 1 / 120, 1 / 240, 1 / 500, 1 / 1000,
                                                     1 / 2000, 1 / 4000),
        mujoco_duration=3.0, mujoco_dt_ref=1 / 8000, mujoco_crosscheck_max=50,
        mujoco_scaling_max=200, mujoco_budget_s=60.0, long_run_s=120.0,
        batch_c=(1, 10, 100, 1000), batch_segments=20, batch_steps=24, batch_loop_max=1000,
        batch_repeats=5,
        energy_T=10.0, energy_settings=[S(RK4, 1 / hz) for hz in (30, 60, 120, 240, 480, 960)]
        + [S(SE, 1 / hz) for hz in (120, 240, 480, 960, 1920, 3840)]
        + [S(RATTLE, 1 / hz) for hz in (120, 240, 480, 960, 1920, 3840)]
        + [S(RK4, 1 / 240, projection=False), S(SE, 1 / 960, projection=False)],
        terms_seconds=5.0, terms_repeats=5),
}

# What "good enough" means for the recommendation (see ``recommend``).
TARGET_TIP_RMS_MM = 10.0      # on the moving-head reference ponytail (2.5 % of its length)
TARGET_ENERGY_DRIFT = 0.10    # |ΔE| / (E0 - E_rest) on the still-head scenes
TARGET_GAP_M = 1e-6


# -- output helpers ---------------------------------------------------------------------------
def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        x = float(x)
        return x if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def write_table(out, name, rows, meta, extra=None):
    """``name.csv`` (one row per dict, union of keys) and ``name.json`` ({meta, rows, ...})."""
    keys = []
    for r in rows:
        for k in r:
            if k not in keys:
                keys.append(k)
    with open(os.path.join(out, name + '.csv'), 'w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: ('' if r.get(k) is None else r.get(k)) for k in keys})
    doc = dict(meta=meta, rows=rows)
    if extra:
        doc.update(extra)
    with open(os.path.join(out, name + '.json'), 'w') as f:
        json.dump(_jsonable(doc), f, indent=1, allow_nan=False)


def print_table(rows, cols, title=None, file=None):
    """Fixed-width table: ``cols`` = [(header, key or callable, format)]."""
    file = file or sys.stdout
    cells = [[h for h, _, _ in cols]]
    for r in rows:
        line = []
        for _, k, fmt in cols:
            v = k(r) if callable(k) else r.get(k)
            if v is None or (isinstance(v, float) and not math.isfinite(v)):
                line.append('-')
            else:
                line.append(format(v, fmt) if fmt else str(v))
        cells.append(line)
    widths = [max(len(c[i]) for c in cells) for i in range(len(cols))]
    if title:
        print(f'\n{title}', file=file)
    for j, c in enumerate(cells):
        print('  '.join(s.rjust(w) if j and i else s.ljust(w)
                        for i, (s, w) in enumerate(zip(c, widths))), file=file)
        if j == 0:
            print('  '.join('-' * w for w in widths), file=file)
    file.flush()


def _git_describe():
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        rev = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=root, capture_output=True,
                             text=True, timeout=5).stdout.strip()
        dirty = subprocess.run(['git', 'status', '--porcelain', '--', 'ponytail_ros/core'], cwd=root,
                               capture_output=True, text=True, timeout=5).stdout.strip()
        return rev + ('+core-modified' if dirty else '') if rev else None
    except Exception:  # pragma: no cover - no git
        return None


def make_meta(profile, command):
    import scipy
    meta = dict(command=command, profile=profile,
                date=datetime.datetime.now().isoformat(timespec='seconds'),
                python=platform.python_version(), numpy=np.__version__, scipy=scipy.__version__,
                mujoco=(MJ.mujoco.__version__ if MJ.available() else None),
                machine=platform.machine(), processor=_cpu_name(), cpus=os.cpu_count(),
                blas_threads_pinned=_PINNED, git=_git_describe(),
                timer='time.process_time (CPU s of this process), median of repeats')
    return meta


def _cpu_name():
    try:
        with open('/proc/cpuinfo') as f:
            for line in f:
                if line.startswith('model name'):
                    return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


# -- trade ------------------------------------------------------------------------------------
def _scene_list(prof):
    """(bench scene, settings) pairs: the four named scenes, then the segment-count sweep."""
    out = []
    for name in prof['scenes']:
        b = make_scene(name, duration=prof['durations'][name])
        sets = prof['settings']()
        if b.still:
            sets = [s for s in sets if not s.tick_rate]     # frames of a still head: no change
        out.append((b, sets))
    for n in prof['seg_counts']:
        b = make_scene('moving', n_segments=n, duration=prof['durations']['moving'])
        out.append((b, list(prof['seg_settings'])))
    return out


def _ref_check_rows(b, ref, prof):
    rows = [dict(scene=b.name, n_segments=b.n_segments, against='itself at 2x step (Richardson: /15)',
                 dt_ref=M.fmt_dt(prof['dt_ref']), max_mm=ref.self_error * 1e3, rms_mm=None,
                 window_s=ref.valid_until, max_all_mm=ref.self_error_all * 1e3)]
    if b.shared:
        shared = M.load_shared(b.shared, REFERENCE_DIR)
        if shared is not None:
            c = M.check_against_shared(ref, shared, b.n_segments)
            rows.append(dict(scene=b.name, n_segments=b.n_segments, against=b.shared,
                             dt_ref=M.fmt_dt(prof['dt_ref']), max_mm=c['max_m'] * 1e3,
                             rms_mm=c['rms_m'] * 1e3, window_s=c['window_s'], max_all_mm=None))
    return rows


def recommend(rows, required=('moving', 'release', 'shake', 'rope')):
    """The cheapest plain setting (banded, projection, exact head) good on every ``required`` scene.

    Good: no guard reset and joint gap ≤ ``TARGET_GAP_M`` on every scene, tip RMS ≤
    ``TARGET_TIP_RMS_MM`` on the moving-head reference and on the violent shake (there only
    within its valid window, before the chaos takes over: surviving a shake without a reset is
    not enough, the constrained steps do that 20+ mm off), |energy drift| ≤
    ``TARGET_ENERGY_DRIFT`` on the still-head scenes (release, rope). Cost: CPU per simulated
    second on the moving head. The release's trajectory error is reported but not required
    (chaotic from the start: it says where the chaos takes over, not how good the solver is).
    """
    main = [r for r in rows if (r['scene'], r['n_segments']) in
            (('moving', 10), ('release', 10), ('shake', 10), ('rope', 40))]
    plain = [r for r in main if not r['tick_rate'] and r['linear_solver'] == 'banded'
             and r['projection'] and not r['baumgarte_stiffness'] and not r['baumgarte_damping']]
    by_label = {}
    for r in plain:
        by_label.setdefault(r['setting'], {})[r['scene']] = r
    all_by_label = by_label
    by_label = {k: {s: r for s, r in v.items() if s in required} for k, v in by_label.items()}
    candidates = []
    for label, per in by_label.items():
        if 'moving' not in per:
            continue
        ok = all(r['stable'] and r['max_gap_m'] <= TARGET_GAP_M for r in per.values())
        ok = ok and all(per[s]['tip_rms_mm'] <= TARGET_TIP_RMS_MM
                        for s in ('moving', 'shake') if s in per)
        for s in ('release', 'rope'):
            if s in per:
                ok = ok and per[s]['energy_drift_max'] <= TARGET_ENERGY_DRIFT
        candidates.append((not ok, per['moving']['cpu_s_per_sim_s'], label, per))
    candidates.sort(key=lambda c: (c[0], c[1]))
    good = [c for c in candidates if not c[0]]
    best = good[0] if good else None
    if best:
        best = best[:3] + (all_by_label[best[2]],)
    current = all_by_label.get(S().label)
    return best, current


def _recommendation(rows):
    """The recommendation (a dict): strict (every scene), without the shake, and the current."""
    best, current = recommend(rows)
    gentle, _ = recommend(rows, required=('moving', 'release', 'rope'))
    rec = dict(criteria=dict(tip_rms_mm_moving_and_shake=TARGET_TIP_RMS_MM,
                             energy_drift_still=TARGET_ENERGY_DRIFT, max_gap_m=TARGET_GAP_M,
                             cost='CPU per simulated second on the moving head'),
               recommended=best[2] if best else None,
               recommended_rows=best[3] if best else None)
    if gentle and (not best or gentle[2] != best[2]):
        rec['recommended_without_shake'] = gentle[2]
        rec['recommended_without_shake_rows'] = gentle[3]
    if current:
        rec['current_default'] = S().label
        rec['current_rows'] = current
    return rec


def _summary_line(label, per):
    mv = per.get('moving')
    parts = []
    if mv:
        parts.append(f'moving-head tip RMS {mv["tip_rms_mm"]:.3g} mm (max {mv["tip_max_mm"]:.3g} mm), '
                     f'{mv["cpu_s_per_sim_s"] * 1e3:.0f} ms CPU per simulated s '
                     f'({mv["cpu_us_per_step"]:.0f} µs/step)')
    for s in ('release', 'shake', 'rope'):
        if s in per:
            r = per[s]
            e = ('' if r.get('energy_drift_max') is None or not math.isfinite(r['energy_drift_max'])
                 else f', |ΔE| {100 * r["energy_drift_max"]:.2g}%')
            parts.append(f'{s}: RMS {r["tip_rms_mm"]:.3g} mm{e}'
                         + ('' if r['stable'] else f' ({r["resets"]} guard resets)'))
    return f'{label}: ' + '; '.join(parts)


TRADE_COLS = [('scene', 'scene', ''), ('N', 'n_segments', 'd'), ('setting', 'setting', ''),
              ('CPU ms/sim-s', lambda r: r['cpu_s_per_sim_s'] * 1e3, '.1f'),
              ('µs/step', 'cpu_us_per_step', '.0f'),
              ('tip RMS mm', 'tip_rms_mm', '.3g'), ('tip max mm', 'tip_max_mm', '.3g'),
              ('max gap m', 'max_gap_m', '.1e'),
              ('|ΔE|/E_rel', 'energy_drift_max', '.2e'), ('resets', 'resets', 'd')]


def cmd_trade(prof, out, meta, log=print):
    rows, checks = [], []
    for b, sets in _scene_list(prof):
        t0 = time.perf_counter()
        ref = M.reference(b, prof['dt_ref'])
        e_rest = M.rest_energy(b) if b.still else None
        c_rows = _ref_check_rows(b, ref, prof)
        checks += c_rows
        for c in c_rows:
            log(f'  reference check {b.name} N={b.n_segments} (RK4 {c["dt_ref"]}) vs '
                f'{c["against"]}: max {c["max_mm"]:.2e} mm'
                + (f', RMS {c["rms_mm"]:.2e} mm' if c['rms_mm'] is not None else '')
                + f' over [0, {c["window_s"]:.2f}] s'
                + (f' (whole run {c["max_all_mm"]:.2e} mm)' if c.get('max_all_mm') else ''))
        for s in sets:
            row = M.run_setting(b, s, ref, repeats=prof['repeats'],
                                timing_window=prof['timing_window'], e_rest=e_rest)
            row['reference_dt'] = prof['dt_ref']
            row['duration_s'] = b.duration
            rows.append(row)
        log(f'  {b.name} N={b.n_segments}: {len(sets)} settings in {time.perf_counter() - t0:.1f} s')
    rec = _recommendation(rows)
    print_table(rows, TRADE_COLS, title='Speed/accuracy trade (CPU per simulated second; error '
                'against the converged reference)')
    print_table(checks, [('scene', 'scene', ''), ('N', 'n_segments', 'd'), ('reference', 'dt_ref', ''),
                         ('against', 'against', ''), ('max mm', 'max_mm', '.2e'),
                         ('RMS mm', 'rms_mm', '.2e'), ('window s', 'window_s', '.2f')],
                title='Reference checks (tip; errors of settings are compared inside the window)')
    print(f'\nRecommendation criteria: no resets and gap ≤ {TARGET_GAP_M:g} m on every scene, '
          f'tip RMS ≤ {TARGET_TIP_RMS_MM:g} mm on the moving head and the shake, |ΔE| ≤ '
          f'{100 * TARGET_ENERGY_DRIFT:g}% on still heads; cheapest on the moving head.')
    if rec.get('recommended'):
        print('RECOMMENDED DEFAULT  ' + _summary_line(rec['recommended'], rec['recommended_rows']))
    else:
        print('RECOMMENDED DEFAULT  none of the plain settings meets every criterion')
    if rec.get('recommended_without_shake'):
        print('WITHOUT THE SHAKE    ' + _summary_line(rec['recommended_without_shake'],
                                                      rec['recommended_without_shake_rows']))
    if rec.get('current_rows'):
        print('CURRENT DEFAULT      ' + _summary_line(rec['current_default'], rec['current_rows']))
    write_table(out, 'trade', rows, meta, dict(recommendation=rec))
    write_table(out, 'refcheck', checks, meta)
    draw_pareto(out)
    return rows, checks, rec


def _load_rows(out, name):
    path = os.path.join(out, name + '.json')
    if not os.path.exists(path):
        return None, None
    with open(path) as f:
        doc = json.load(f)
    rows = [{k: (float('nan') if v is None and k.endswith(('_mm', '_m', 'drift_max')) else v)
             for k, v in r.items()} for r in doc.get('rows', [])]
    return rows, doc


def draw_pareto(out):
    """``pareto.png`` from ``trade.json`` (+ MuJoCo's points from ``mujoco.json`` if there)."""
    rows, doc = _load_rows(out, 'trade')
    if not rows:
        return
    mj_rows, mj_doc = _load_rows(out, 'mujoco')
    if mj_doc and mj_doc['meta'].get('profile') != doc['meta'].get('profile'):
        mj_rows = None
    scenes = []
    for r in rows:
        key = (r['scene'], r['n_segments'])
        if key not in scenes:
            scenes.append(key)
    main = [k for k in scenes if k in (('moving', 10), ('release', 10), ('shake', 10), ('rope', 40),
                                       ('damped', 10))]
    rec = _recommendation(rows).get('recommended')
    plots.pareto_plot(rows, os.path.join(out, 'pareto.png'), main or scenes[:4],
                      mujoco_rows=mj_rows or (), recommended=rec,
                      title=f'Speed/accuracy trade ({doc["meta"].get("profile")} profile): one point '
                            f'per setting; ringed = recommended ({rec})')


# -- scaling ----------------------------------------------------------------------------------
SCALING_DT = 1e-4   # small enough that even 1000 segments of 0.4 mm are stable (cost per step
                    # does not depend on the step)


def _time_steps_core(scene, motion, n_steps, repeats):
    out = []
    resets = 0
    for _ in range(repeats):
        sim = Simulator(scene, motion, 0.0)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', RuntimeWarning)
            c0 = time.process_time()
            r = sim.advance_to(n_steps * scene.solver.dt + 0.5 * scene.solver.dt, motion)
            out.append((time.process_time() - c0) / max(r.steps, 1))
        resets += bool(r.reset_reason)
    return float(np.median(out)), resets


def cmd_scaling(prof, out, meta, log=print):
    rows = []
    motion = reference_motion()
    for n in prof['scaling_n']:
        chain = ponytail_chain(n)
        steps = int(max(5, min(400, prof['scaling_steps_budget'] / (30.0 * n + 300.0))))
        for series, integ, solver in (('RK4 banded', RK4, 'banded'), ('SE banded', SE, 'banded'),
                                      ('RATTLE banded', RATTLE, 'banded'),
                                      ('RK4 dense', RK4, 'dense')):
            if solver == 'dense' and n > prof['dense_max']:
                continue
            sc = Scene(chains=(chain,), solver=SolverSpec(integrator=integ, dt=SCALING_DT,
                                                          linear_solver=solver,
                                                          max_steps_per_call=10 ** 6))
            k = steps if solver == 'banded' else max(3, min(steps, int(2e6 / n ** 2.5)))
            us, resets = _time_steps_core(sc, motion, k, prof['scaling_repeats'])
            rows.append(dict(series=series, engine='ours', integrator=integ, linear_solver=solver,
                             n_segments=n, cpu_us_per_step=us * 1e6, steps_timed=k,
                             repeats=prof['scaling_repeats'], dt=SCALING_DT, resets=resets))
        if MJ.available() and n <= prof['mujoco_scaling_max']:
            mc = MJ.MujocoChain(make_scene('moving', n_segments=n), SCALING_DT)
            k = int(max(5, min(2000, 2e6 / (n ** 2.5 + 100))))
            rows.append(dict(series='MuJoCo RK4', engine='mujoco', integrator='rk4',
                             linear_solver='mujoco', n_segments=n,
                             cpu_us_per_step=mc.time_steps(k, prof['scaling_repeats']) * 1e6,
                             steps_timed=k, repeats=prof['scaling_repeats'], dt=SCALING_DT,
                             resets=int(mc.unstable())))
        log(f'  scaling N={n} done')
    print_table(rows, [('series', 'series', ''), ('N', 'n_segments', 'd'),
                       ('µs/step', 'cpu_us_per_step', '.1f'), ('µs/step/segment',
                       lambda r: r['cpu_us_per_step'] / r['n_segments'], '.2f'),
                       ('steps', 'steps_timed', 'd'), ('resets', 'resets', 'd')],
                title='Cost per step vs segment count')
    write_table(out, 'scaling', rows, meta)
    plots.scaling_plot(rows, os.path.join(out, 'scaling.png'))
    return rows


# -- MuJoCo -----------------------------------------------------------------------------------
def _vs_shared(b, ts, tips):
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


def _our_tip_run(b, dt, T):
    sim = Simulator(b.scene.replace(solver=S(RK4, dt).solver()), b.motion, 0.0)
    ts, tips = [0.0], [M._tip(sim)[0]]
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)
        for k in range(1, int(round(T / 0.01)) + 1):
            sim.advance_to(k * 0.01, b.motion)
            ts.append(sim.t)
            tips.append(M._tip(sim)[0])
    return np.array(ts), np.array(tips)


def cmd_mujoco(prof, out, meta, log=print):
    """MuJoCo side by side."""
    if not MJ.available():
        print('\nMuJoCo side by side: skipped (mujoco not installed: pip install mujoco)')
        write_table(out, 'mujoco', [], meta, dict(skipped='mujoco not installed'))
        return []
    rows, checks = [], []
    budget = prof['mujoco_budget_s']
    for n in prof['mujoco_n']:
        T = prof['mujoco_duration'] if n <= 50 else min(1.0, prof['mujoco_duration'])
        b = make_scene('moving', n_segments=n, duration=T)
        t0 = time.perf_counter()
        ref = M.reference(b, prof['mujoco_dt_ref'])
        checks.append(dict(n_segments=n, duration_s=T, dt=M.fmt_dt(prof['mujoco_dt_ref']),
                           ref_self_error_mm=ref.self_error * 1e3, ref_valid_until_s=ref.valid_until))
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
                us = mc.time_steps(max(5, min(steps, int(0.2 / max(mj_us, 1e-7)))), prof['repeats'])
                inside = ts <= ref.valid_until + 1e-9
                e = np.linalg.norm(tips[inside] - ref.at(ts[inside]), axis=1)
                stable = (not unst) and bool(np.all(np.isfinite(e)))
                sh_rms, sh_max = _vs_shared(b, ts, tips) if stable else (None, None)
                rows.append(dict(engine='mujoco', scene='moving', n_segments=n, dt=dt,
                                 dt_label=M.fmt_dt(dt), duration_s=T, cpu_us_per_step=us * 1e6,
                                 cpu_s_per_sim_s=us / dt, run_cpu_s_per_sim_s=run_cpu / T,
                                 tip_rms_mm=float(np.sqrt(np.mean(e ** 2))) * 1e3 if stable else float('nan'),
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
    cols = [('engine', 'engine', ''), ('N', 'n_segments', 'd'), ('dt', 'dt_label', ''),
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
    print_table(long_rows, [('engine', 'engine', ''), ('N', 'n_segments', 'd'), ('dt', 'dt_label', ''),
                            ('simulated s', 'duration_s', '.1f'),
                            ('first blow-up at s', 'first_failure_s', '.2f'),
                            ('blow-ups', 'failures', 'd')],
                title='Long run on the moving head, undamped (robustness at game steps)')
    _print_mujoco_verdict(rows)
    write_table(out, 'mujoco', rows, meta, dict(reference_checks=checks, long_run=long_rows,
                                                warnings=MJ.warnings_seen()[:20]))
    plots.mujoco_plot(rows, os.path.join(out, 'mujoco.png'))
    draw_pareto(out)
    return rows


def _long_run(prof):
    """Both engines on the undamped moving-head ponytail (N = 10) for ``long_run_s`` at 1/240 and
    1/120 s: when (if ever) does each blow up? (MuJoCo resets itself on a bad qacc; the core's
    guard resets and reports.)"""
    T = prof.get('long_run_s', 0.0)
    rows = []
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


def _print_mujoco_verdict(rows):
    print('\nPer segment count, cost per step (ours / MuJoCo) and error at the same step:')
    for n in sorted({r['n_segments'] for r in rows}):
        for dt in sorted({r['dt'] for r in rows if r['n_segments'] == n}, reverse=True):
            o = [r for r in rows if r['n_segments'] == n and r['dt'] == dt and r['engine'] == 'ours']
            m = [r for r in rows if r['n_segments'] == n and r['dt'] == dt and r['engine'] == 'mujoco']
            if o and m:
                o, m = o[0], m[0]
                ratio = o['cpu_us_per_step'] / m['cpu_us_per_step']
                faster = 'MuJoCo' if ratio > 1 else 'ours'
                print(f'  N={n:4d} dt={o["dt_label"]:>7}: {faster} {max(ratio, 1 / ratio):.1f}x '
                      f'cheaper per step; tip RMS ours {o["tip_rms_mm"]:.3g} mm vs MuJoCo '
                      f'{m["tip_rms_mm"]:.3g} mm' + ('' if m['stable'] else ' (MuJoCo unstable)')
                      + ('' if o['stable'] else ' (ours reset)'))


# -- batch ------------------------------------------------------------------------------------
def cmd_batch(prof, out, meta, log=print):
    rows = []
    n = prof['batch_segments']
    dt = 1.0 / 240.0
    steps = prof['batch_steps']
    solver = SolverSpec(dt=dt, max_steps_per_call=10 ** 6)
    alone = None
    check = {}
    for C in prof['batch_c']:
        motion = crowd_motion(C)
        chains = tuple(replace(ponytail_chain(n), name=f'c{c}', anchor_body=c) for c in range(C))
        sc = Scene(chains=chains, n_kinematic_bodies=C, solver=solver)
        k = max(2, int(steps * (1 if C < 100 else 0.5)))
        times = []
        for _ in range(prof['batch_repeats']):
            sim = Simulator(sc, motion, 0.0)
            sim.advance_to(dt, motion)              # warm up (first call allocations)
            c0 = time.process_time()
            sim.advance_to((k + 1) * dt + 0.5 * dt, motion)
            times.append((time.process_time() - c0) / k)
        per_step = float(np.median(times))
        if C == 1:
            alone = per_step
        # Correctness: chain c of the batch equals the same chain simulated alone.
        if C > 1:
            c = C // 2
            m1 = crowd_motion(C)
            solo_motion = _SingleBody(m1, c)
            solo = Simulator(Scene(chains=(ponytail_chain(n),), solver=solver), solo_motion, 0.0)
            solo.advance_to(0.25, solo_motion)
            batch = Simulator(sc, m1, 0.0)
            batch.advance_to(0.25, m1)
            sl = batch.model.chain_slice(c)
            check[C] = float(np.max(np.abs(batch.state.x[sl] - solo.state.x)))
        rows.append(dict(mode='one scene (batched)', chains=C, segments_per_chain=n,
                         cpu_ms_per_step=per_step * 1e3, cpu_us_per_chain_step=per_step / C * 1e6,
                         relative_to_alone=(per_step / C) / alone if alone else None,
                         max_dev_from_solo_m=check.get(C), steps_timed=k))
        log(f'  batch C={C} done')
    for C in prof['batch_c']:
        if C < 2 or C > prof['batch_loop_max']:
            continue
        motion = crowd_motion(C)
        sims = [(Simulator(Scene(chains=(ponytail_chain(n),), solver=solver), _SingleBody(motion, c), 0.0),
                 _SingleBody(motion, c)) for c in range(C)]
        k = max(2, steps // 2)
        for s, m in sims:
            s.advance_to(dt, m)
        times = []
        for rep in range(max(1, prof['batch_repeats'] - 1)):
            c0 = time.process_time()
            for j in range(k):
                t = (2 + rep * k + j) * dt + 0.5 * dt
                for s, m in sims:
                    s.advance_to(t, m)
            times.append((time.process_time() - c0) / k)
        per_step = float(np.median(times))
        rows.append(dict(mode='separate simulators', chains=C, segments_per_chain=n,
                         cpu_ms_per_step=per_step * 1e3, cpu_us_per_chain_step=per_step / C * 1e6,
                         relative_to_alone=(per_step / C) / alone if alone else None,
                         max_dev_from_solo_m=None, steps_timed=k))
    print_table(rows, [('mode', 'mode', ''), ('chains', 'chains', 'd'),
                       ('segments', 'segments_per_chain', 'd'),
                       ('CPU ms/step', 'cpu_ms_per_step', '.2f'),
                       ('µs per chain-step', 'cpu_us_per_chain_step', '.1f'),
                       ('vs one chain alone', 'relative_to_alone', '.3f'),
                       ('max dev vs solo m', 'max_dev_from_solo_m', '.1e')],
                title=f'Batched crowd: C chains of {n} segments, RK4 1/240, one banded solve')
    write_table(out, 'batch', rows, meta)
    return rows


class _SingleBody(HeadMotion):
    """Body ``c`` of a multi-body motion, as a one-body motion."""

    def __init__(self, motion, c):
        self.motion, self.c = motion, c

    def state_at(self, t):
        s = self.motion.state_at(t)
        c = slice(self.c, self.c + 1)
        return type(s)(s.position[c], s.orientation[c], s.linear_velocity[c], s.angular_velocity[c],
                       s.linear_acceleration[c], s.angular_acceleration[c])


# -- energy -----------------------------------------------------------------------------------
def energy_scene(solver=None):
    """5 segments of the reference ponytail on a still anchor, released 45° from vertical."""
    a = np.radians(45.0)
    chain = ponytail_chain(5, rest_direction=(np.sin(a), 0.0, -np.cos(a)))
    sc = Scene(chains=(chain,), solver=solver or SolverSpec())
    return BenchScene('energy', sc, StillMotion((0.0, 0.0, 1.6)), 10.0, True)


def cmd_energy(prof, out, meta, log=print):
    rows, series = [], {}
    T = prof['energy_T']
    for s in prof['energy_settings']:
        b = energy_scene().with_duration(T)
        e_rest = M.rest_energy(b)
        c0 = time.process_time()
        traj = M.simulate(b, s, sample_dt=0.01)
        cpu = time.process_time() - c0
        scale = traj.energy[0] - e_rest
        de = (traj.energy - traj.energy[0]) / scale
        series[s.label] = (traj.t, de)
        rows.append(dict(setting=s.label, integrator=s.integrator, dt=s.dt, dt_label=M.fmt_dt(s.dt),
                         projection=s.projection, duration_s=T, releasable_J=scale,
                         drift_max_abs=float(np.max(np.abs(de))), drift_final=float(de[-1]),
                         growth_max=float(np.max(de)), max_gap_m=float(np.max(traj.gap)),
                         resets=len(traj.resets), cpu_s=cpu))
    print_table(rows, [('setting', 'setting', ''), ('max |ΔE|/(E0-Erest)', 'drift_max_abs', '.2e'),
                       ('final ΔE/(E0-Erest)', 'drift_final', '+.2e'),
                       ('max growth', 'growth_max', '+.2e'), ('max gap m', 'max_gap_m', '.1e'),
                       ('resets', 'resets', 'd'), ('CPU s', 'cpu_s', '.1f')],
                title=f'Energy drift: still anchor, no damping, 5 segments released 45°, {T:g} s '
                      f'(E0 - E_rest = {rows[0]["releasable_J"]:.4f} J)' if rows else 'Energy drift')
    write_table(out, 'energy', rows, meta)
    plots.energy_plot(series, os.path.join(out, 'energy.png'))
    return rows


# -- terms ------------------------------------------------------------------------------------
def cmd_terms(prof, out, meta, log=print):
    """Cost of each term, collider and limit, and of each ready-made scene (``terms.py``)."""
    from . import terms
    seconds, repeats = prof['terms_seconds'], prof['terms_repeats']
    table = terms.bench_terms(20, seconds, repeats, out=log)
    rows = [dict(configuration=label, cpu_ms_per_sim_s=1e3 * per_s, vs_gravity=rel,
                 rows_per_step=r, seconds=seconds, repeats=repeats)
            for label, per_s, rel, r in table]
    write_table(out, 'terms', rows, meta)
    table = terms.bench_ready_made(seconds, repeats, out=log)
    scene_rows = [dict(scene=name, models=what, segments=n, cpu_ms_per_sim_s=1e3 * per_s,
                       rows_per_step=r, seconds=seconds, repeats=repeats)
                  for name, what, n, per_s, r in table]
    write_table(out, 'scenes', scene_rows, meta)
    return rows


# -- refcheck ---------------------------------------------------------------------------------
def cmd_refcheck(prof, out, meta, log=print):
    """This core's RK4 at the reference step against every shared reference file."""
    import glob
    rows = []
    dt = prof['dt_ref']
    for path in sorted(glob.glob(os.path.join(REFERENCE_DIR, 'ponytail_N*.json'))):
        name = os.path.splitext(os.path.basename(path))[0]
        shared = M.load_shared(name, REFERENCE_DIR)
        sc = shared['scene']
        n = int(sc['n_segments'])
        kind = 'moving' if sc['head'] == 'moving' else 'release'
        b = make_scene(kind, n_segments=n, duration=min(3.0, prof['durations']['moving'] * 2))
        variants = [('default', {})]
        if sc.get('damping', 0.0):
            chain = replace(b.scene.chains[0], damping=float(sc['damping']))
            b = replace(b, scene=b.scene.replace(chains=(chain,)))
            fields = SolverSpec.__dataclass_fields__
            if 'damping_method' in fields:
                variants = [(f'damping_method={k}', dict(damping_method=k))
                            for k in ('auto', 'implicit', 'explicit')]
            elif 'implicit_damping' in fields:
                variants = [('implicit damping', dict(implicit_damping=True)),
                            ('explicit damping', dict(implicit_damping=False))]
        for vname, kw in variants:
            bb = replace(b, scene=b.scene.replace(solver=SolverSpec(dt=dt, max_steps_per_call=10 ** 6, **kw)))
            traj = M.simulate(bb, S(RK4, dt, extra=tuple(kw.items())), every_step=True)
            c = M.check_against_shared(traj, shared, n)
            rows.append(dict(file=name, variant=vname, dt=M.fmt_dt(dt), max_mm=c['max_m'] * 1e3,
                             rms_mm=c['rms_m'] * 1e3, window_s=c['window_s']))
            log(f'  {name} ({vname}): max {c["max_m"] * 1e3:.2e} mm')
    print_table(rows, [('file', 'file', ''), ('variant', 'variant', ''), ('RK4 step', 'dt', ''),
                       ('tip max mm', 'max_mm', '.2e'), ('tip RMS mm', 'rms_mm', '.2e'),
                       ('window s', 'window_s', '.2f')],
                title='This core (RK4) against ../shared/reference/')
    write_table(out, 'refcheck_all', rows, meta)
    return rows


# -- report -----------------------------------------------------------------------------------
def md_table(rows, cols):
    """A markdown table (same ``cols`` as ``print_table``)."""
    out = ['| ' + ' | '.join(h for h, _, _ in cols) + ' |',
           '|' + '|'.join('---' if i == 0 else '---:' for i in range(len(cols))) + '|']
    for r in rows:
        cells = []
        for _, k, fmt in cols:
            v = k(r) if callable(k) else r.get(k)
            if v is None or (isinstance(v, float) and not math.isfinite(v)):
                cells.append('-')
            else:
                cells.append(format(v, fmt) if fmt else str(v))
        out.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(out)


def cmd_report(prof, out, meta, log=print):
    """``results.md``: every table of the JSON files in ``out`` as markdown."""
    parts = [f'# ponytail_bench results\n\nGenerated from the JSON files in this directory '
             f'({meta["date"]}).\n']
    trade, doc = _load_rows(out, 'trade')
    if trade:
        m = doc['meta']
        parts.append(f'Machine: {m.get("processor")} ({m.get("cpus")} CPUs), Python {m.get("python")}, '
                     f'NumPy {m.get("numpy")}, SciPy {m.get("scipy")}, MuJoCo {m.get("mujoco")}; '
                     f'profile `{m.get("profile")}`; core `{m.get("git")}`. Costs are CPU time '
                     f'(`time.process_time`, one BLAS thread), median of repeats.\n')
        rec = _recommendation(trade)
        if rec.get('recommended'):
            parts.append('## Recommended default\n\n**' + _summary_line(rec['recommended'],
                                                                          rec['recommended_rows']) + '**\n')
        if rec.get('recommended_without_shake'):
            parts.append('If the violent shake need not run clean (the guard resets it): '
                         + _summary_line(rec['recommended_without_shake'],
                                         rec['recommended_without_shake_rows']) + '\n')
        if rec.get('current_rows'):
            parts.append('Current default: ' + _summary_line(rec['current_default'],
                                                              rec['current_rows']) + '\n')
        parts.append('## Speed/accuracy trade\n\n![pareto](pareto.png)\n\n' + md_table(trade, TRADE_COLS))
    for name, title, cols in (
            ('refcheck', 'Reference checks', [('scene', 'scene', ''), ('N', 'n_segments', 'd'),
                                             ('reference', 'dt_ref', ''), ('against', 'against', ''),
                                             ('max mm', 'max_mm', '.2e'), ('RMS mm', 'rms_mm', '.2e'),
                                             ('window s', 'window_s', '.2f')]),
            ('scaling', 'Cost per step vs segment count', [
                ('series', 'series', ''), ('N', 'n_segments', 'd'), ('µs/step', 'cpu_us_per_step', '.1f'),
                ('µs/step/segment', lambda r: r['cpu_us_per_step'] / r['n_segments'], '.2f')]),
            ('mujoco', 'This core vs MuJoCo', [
                ('engine', 'engine', ''), ('N', 'n_segments', 'd'), ('dt', 'dt_label', ''),
                ('µs/step', 'cpu_us_per_step', '.1f'),
                ('CPU ms/sim-s', lambda r: r['cpu_s_per_sim_s'] * 1e3, '.1f'),
                ('tip RMS mm', 'tip_rms_mm', '.3g'), ('tip max mm', 'tip_max_mm', '.3g'),
                ('window s', 'error_window_s', '.2f'),
                ('RMS vs shared, whole run, mm', 'tip_rms_vs_shared_full_mm', '.3g'),
                ('stable', 'stable', '')]),
            ('batch', 'Batched crowd', [
                ('mode', 'mode', ''), ('chains', 'chains', 'd'), ('segments', 'segments_per_chain', 'd'),
                ('CPU ms/step', 'cpu_ms_per_step', '.2f'),
                ('µs per chain-step', 'cpu_us_per_chain_step', '.1f'),
                ('vs one chain alone', 'relative_to_alone', '.3f'),
                ('max dev vs solo m', 'max_dev_from_solo_m', '.1e')]),
            ('energy', 'Energy drift (still anchor, no damping, 5 segments released 45°)', [
                ('setting', 'setting', ''), ('max abs dE/(E0-Erest)', 'drift_max_abs', '.2e'),
                ('final', 'drift_final', '+.2e'), ('max growth', 'growth_max', '+.2e'),
                ('resets', 'resets', 'd')]),
            ('terms', 'Cost of each term, collider and limit (20-segment ponytail, moving head, '
                      'RK4 1/240 s; each row adds to the one above, the last two switch '
                      'features off)', [
                ('configuration', 'configuration', ''),
                ('CPU ms/sim-s', 'cpu_ms_per_sim_s', '.1f'), ('vs gravity', 'vs_gravity', '.2f'),
                ('contact+limit rows/step', 'rows_per_step', '.2f')]),
            ('scenes', 'Ready-made scenes (config/*.yaml) on the scripted head', [
                ('scene', 'scene', ''), ('models', 'models', ''),
                ('CPU ms/sim-s', 'cpu_ms_per_sim_s', '.1f'),
                ('contact+limit rows/step', 'rows_per_step', '.2f')])):
        rows, d = _load_rows(out, name)
        if not rows:
            continue
        fig = {'scaling': '\n\n![scaling](scaling.png)', 'mujoco': '\n\n![mujoco](mujoco.png)',
               'energy': '\n\n![energy](energy.png)'}.get(name, '')
        parts.append(f'## {title}{fig}\n\n' + md_table(rows, cols))
        if name == 'mujoco' and d.get('long_run'):
            parts.append(md_table(d['long_run'], [('engine', 'engine', ''), ('dt', 'dt_label', ''),
                                                  ('simulated s', 'duration_s', '.0f'),
                                                  ('first blow-up at s', 'first_failure_s', '.2f'),
                                                  ('blow-ups', 'failures', 'd')]))
    try:
        with open(os.path.join(out, 'summary.json')) as f:
            walls = json.load(f).get('wall_s', {})
        parts.append('## Wall time of the run\n\n' + ', '.join(f'{k} {v:.0f} s' for k, v in walls.items()))
    except (OSError, ValueError):
        pass
    with open(os.path.join(out, 'results.md'), 'w') as f:
        f.write('\n\n'.join(parts) + '\n')
    print(f'wrote {os.path.join(out, "results.md")}')
    return parts


# -- main -------------------------------------------------------------------------------------
COMMANDS = {'trade': cmd_trade, 'scaling': cmd_scaling, 'mujoco': cmd_mujoco, 'batch': cmd_batch,
            'energy': cmd_energy, 'terms': cmd_terms, 'refcheck': cmd_refcheck,
            'report': cmd_report, 'pose': pose_bench.cmd_pose}
ALL = ('trade', 'scaling', 'mujoco', 'batch', 'energy', 'terms')


def _common_options(suppress=False):
    """The options, accepted before and after the subcommand. The subcommand's copy has no
    defaults (``SUPPRESS``), so that it does not overwrite options given before it."""
    d = (lambda value: argparse.SUPPRESS) if suppress else (lambda value: value)
    common = argparse.ArgumentParser(add_help=False)
    g = common.add_mutually_exclusive_group()
    g.add_argument('--quick', dest='profile', action='store_const', const='quick', default=d(None),
                   help='the default: every subcommand in ~2-3 min')
    g.add_argument('--full', dest='profile', action='store_const', const='full', default=d(None),
                   help='the full sweep (~30-40 min)')
    g.add_argument('--tiny', dest='profile', action='store_const', const='tiny', default=d(None),
                   help='seconds; for tests (numbers meaningless)')
    common.add_argument('--out', default=d(None), help='output directory (default: docs/bench)')
    common.add_argument('--repeats', type=int, default=d(None), help='timing repeats (median)')
    common.add_argument('--no-mujoco', action='store_true', default=d(False),
                        help='skip MuJoCo even if installed')
    common.add_argument('--scenes', default=d(None),
                        help='comma-separated scenes for trade (default: the profile\'s; '
                             f'any of {", ".join(SCENES + EXTRA_SCENES)})')
    return common


def build_parser():
    common = _common_options()
    p = argparse.ArgumentParser(prog='ponytail_bench', parents=[common],
                                description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest='command')
    helps = dict(trade='the sweep on the named scenes: cost, tip error, gap, energy; Pareto plot',
                 scaling='cost per step vs segment count 1..1000 (banded, dense, MuJoCo)',
                 mujoco='the same chain in MuJoCo side by side (optional mujoco package)',
                 batch='C chains in one scene vs one chain alone vs C simulators',
                 energy='energy drift per integrator and step, still anchor, no damping',
                 terms='cost of each force term, collider and limit; of each ready-made scene',
                 refcheck="RK4 against every file of ../shared/reference/",
                 pose='head estimation p, v, a, w, alpha and tip errors, live and look-ahead, '
                      '30-1000 Hz input (pose_bench.py)',
                 report='results.md from the JSON files in --out',
                 all='trade, scaling, mujoco, batch, energy, terms, then report (the default)')
    for name in list(COMMANDS) + ['all']:
        sub.add_parser(name, parents=[_common_options(suppress=True)], help=helps[name])
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    profile = args.profile or 'quick'
    prof = dict(PROFILES[profile])
    if args.repeats:
        prof['repeats'] = prof['scaling_repeats'] = prof['batch_repeats'] = args.repeats
    if args.scenes:
        prof['scenes'] = tuple(x.strip() for x in args.scenes.split(',') if x.strip())
        prof['durations'] = dict(PROFILES['full']['durations'], **prof['durations'])
        prof['seg_counts'] = ()
    out = args.out or os.path.join('docs', 'bench')
    os.makedirs(out, exist_ok=True)
    command = args.command or 'all'
    todo = ALL if command == 'all' else (command,)
    saved_mujoco = MJ.mujoco
    if args.no_mujoco:
        MJ.mujoco = None
    try:
        _run_commands(todo, profile, prof, out, command)
    finally:
        MJ.mujoco = saved_mujoco
    return 0


def _run_commands(todo, profile, prof, out, command):
    walls = {}
    t_all = time.perf_counter()
    summary_path = os.path.join(out, 'summary.json')
    summary = {}
    if os.path.exists(summary_path):
        try:
            with open(summary_path) as f:
                summary = json.load(f)
        except ValueError:
            summary = {}
    print(f'ponytail_bench {command} --{profile} -> {out} (BLAS threads pinned: {_PINNED})')
    for name in todo:
        t0 = time.perf_counter()
        print(f'\n== {name} ==', flush=True)
        meta = make_meta(profile, name)
        res = COMMANDS[name](prof, out, meta, log=lambda *a: print(*a, flush=True))
        walls[name] = time.perf_counter() - t0
        print(f'[{name}: {walls[name]:.1f} s wall]', flush=True)
        if name == 'trade':
            summary['recommendation'] = _jsonable(res[2])
    wall = time.perf_counter() - t_all
    if command == 'all':
        summary.update(dict(meta=make_meta(profile, command), wall_s=dict(walls, total=wall)))
    elif command != 'report':
        # One subcommand re-run: its wall time joins those of the last full run.
        summary['wall_s'] = {**summary.get('wall_s', {}), **walls}
    if command != 'report':
        with open(summary_path, 'w') as f:
            json.dump(_jsonable(summary), f, indent=1, allow_nan=False)
        if command == 'all':
            cmd_report(prof, out, make_meta(profile, 'report'))
    print(f'\nTotal wall time {wall:.1f} s ({", ".join(f"{k} {v:.0f} s" for k, v in walls.items())})')
    return 0


if __name__ == '__main__':  # pragma: no cover
    sys.exit(main())
