"""``trade``: the speed/accuracy sweep on the named scenes; the Pareto plot; the recommendation.

Integrator, internal step, stabilisation (projection, Baumgarte), head tick rate and segment
count on the named scenes (``--scenes``: moving, release, shake, rope); per setting the CPU
cost per simulated second and per step, the tip error (RMS/max, mm) against a converged
reference (this core's RK4 at a tiny step, itself checked against ``../shared/reference/`` and
by Richardson), the joint gap and, on still heads, the energy drift. Writes ``trade.csv/json``,
``refcheck.csv/json``, ``pareto.png``.
"""
import os
import time
from typing import Any

from .. import measure as M, plots
from ..profiles import Profile
from ..recommend import (
    TARGET_ENERGY_DRIFT,
    TARGET_GAP_M,
    TARGET_TIP_RMS_MM,
    recommendation,
    summary_line,
)
from ..scenes import REFERENCE_DIR, BenchScene, make_scene
from ..tables import Column, Log, Meta, Row, load_rows, print_table, write_table

HELP = 'the sweep on the named scenes: cost, tip error, gap, energy; Pareto plot'


def _scene_list(prof: Profile) -> list[tuple[BenchScene, list[M.Setting]]]:
    """(bench scene, settings) pairs: the four named scenes, then the segment-count sweep."""
    out: list[tuple[BenchScene, list[M.Setting]]] = []
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


def _ref_check_rows(b: BenchScene, ref: Any, prof: Profile) -> list[Row]:
    """The reference's own error (Richardson) and, where a shared file matches, its error."""
    rows = [dict(scene=b.name, n_segments=b.n_segments,
                 against='itself at 2x step (Richardson: /15)',
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



TRADE_COLS: list[Column] = [
    ('scene', 'scene', ''), ('N', 'n_segments', 'd'), ('setting', 'setting', ''),
    ('CPU ms/sim-s', lambda r: r['cpu_s_per_sim_s'] * 1e3, '.1f'),
    ('µs/step', 'cpu_us_per_step', '.0f'),
    ('tip RMS mm', 'tip_rms_mm', '.3g'), ('tip max mm', 'tip_max_mm', '.3g'),
    ('max gap m', 'max_gap_m', '.1e'),
    ('|ΔE|/E_rel', 'energy_drift_max', '.2e'), ('resets', 'resets', 'd')]
REFCHECK_COLS: list[Column] = [
    ('scene', 'scene', ''), ('N', 'n_segments', 'd'), ('reference', 'dt_ref', ''),
    ('against', 'against', ''), ('max mm', 'max_mm', '.2e'),
    ('RMS mm', 'rms_mm', '.2e'), ('window s', 'window_s', '.2f')]


def run(prof: Profile, out: str, meta: Meta, log: Log = print
        ) -> tuple[list[Row], list[Row], dict[str, Any]]:
    """The sweep; returns (rows, reference checks, recommendation)."""
    rows: list[Row] = []
    checks: list[Row] = []
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
        log(f'  {b.name} N={b.n_segments}: {len(sets)} settings in '
            f'{time.perf_counter() - t0:.1f} s')
    rec = recommendation(rows)
    print_table(rows, TRADE_COLS, title='Speed/accuracy trade (CPU per simulated second; error '
                'against the converged reference)')
    print_table(checks, REFCHECK_COLS,
                title='Reference checks (tip; errors of settings are compared inside the window)')
    print(f'\nRecommendation criteria: no resets and gap ≤ {TARGET_GAP_M:g} m on every scene, '
          f'tip RMS ≤ {TARGET_TIP_RMS_MM:g} mm on the moving head and the shake, |ΔE| ≤ '
          f'{100 * TARGET_ENERGY_DRIFT:g}% on still heads; cheapest on the moving head.')
    if rec.get('recommended'):
        print('RECOMMENDED DEFAULT  ' + summary_line(rec['recommended'], rec['recommended_rows']))
    else:
        print('RECOMMENDED DEFAULT  none of the plain settings meets every criterion')
    if rec.get('recommended_without_shake'):
        print('WITHOUT THE SHAKE    ' + summary_line(rec['recommended_without_shake'],
                                                      rec['recommended_without_shake_rows']))
    if rec.get('current_rows'):
        print('CURRENT DEFAULT      ' + summary_line(rec['current_default'], rec['current_rows']))
    write_table(out, 'trade', rows, meta, dict(recommendation=rec))
    write_table(out, 'refcheck', checks, meta)
    draw_pareto(out)
    return rows, checks, rec



def draw_pareto(out: str) -> None:
    """``pareto.png`` from ``trade.json`` (+ MuJoCo's points from ``mujoco.json`` if there)."""
    rows, doc = load_rows(out, 'trade')
    if not rows:
        return
    mj_rows, mj_doc = load_rows(out, 'mujoco')
    if mj_doc and mj_doc['meta'].get('profile') != doc['meta'].get('profile'):
        mj_rows = None
    scenes: list[tuple[str, int]] = []
    for r in rows:
        key = (r['scene'], r['n_segments'])
        if key not in scenes:
            scenes.append(key)
    main = [k for k in scenes if k in (('moving', 10), ('release', 10), ('shake', 10),
                                       ('rope', 40), ('damped', 10))]
    rec = recommendation(rows).get('recommended')
    plots.pareto_plot(rows, os.path.join(out, 'pareto.png'), main or scenes[:4],
                      mujoco_rows=mj_rows or (), recommended=rec,
                      title=f'Speed/accuracy trade ({doc["meta"].get("profile")} profile): one '
                            f'point per setting; ringed = recommended ({rec})')
