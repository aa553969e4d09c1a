"""``report``: ``results.md``, every table of the JSON files in the output directory as markdown.

Also written at the end of ``all``.
"""
import json
import os

from ..profiles import Profile
from ..recommend import recommendation, summary_line
from ..tables import Column, Log, Meta, load_rows, md_table
from .trade import REFCHECK_COLS, TRADE_COLS

HELP = 'results.md from the JSON files in --out'

#: The tables after the trade's: (JSON file name, section title, columns).
SECTIONS: list[tuple[str, str, list[Column]]] = [
    ('refcheck', 'Reference checks', REFCHECK_COLS),
    ('scaling', 'Cost per step vs segment count', [
        ('series', 'series', ''), ('N', 'n_segments', 'd'),
        ('µs/step', 'cpu_us_per_step', '.1f'),
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
        ('mode', 'mode', ''), ('chains', 'chains', 'd'),
        ('segments', 'segments_per_chain', 'd'),
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
        ('contact+limit rows/step', 'rows_per_step', '.2f')])]


def run(prof: Profile, out: str, meta: Meta, log: Log = print) -> list[str]:
    """``results.md``: every table of the JSON files in ``out`` as markdown."""
    parts = [f'# ponytail_bench results\n\nGenerated from the JSON files in this directory '
             f'({meta["date"]}).\n']
    trade, doc = load_rows(out, 'trade')
    if trade:
        m = doc['meta']
        parts.append(f'Machine: {m.get("processor")} ({m.get("cpus")} CPUs), '
                     f'Python {m.get("python")}, NumPy {m.get("numpy")}, SciPy {m.get("scipy")}, '
                     f'MuJoCo {m.get("mujoco")}; '
                     f'profile `{m.get("profile")}`; core `{m.get("git")}`. Costs are CPU time '
                     f'(`time.process_time`, one BLAS thread), median of repeats.\n')
        rec = recommendation(trade)
        if rec.get('recommended'):
            best = summary_line(rec['recommended'], rec['recommended_rows'])
            parts.append(f'## Recommended default\n\n**{best}**\n')
        if rec.get('recommended_without_shake'):
            parts.append('If the violent shake need not run clean (the guard resets it): '
                         + summary_line(rec['recommended_without_shake'],
                                         rec['recommended_without_shake_rows']) + '\n')
        if rec.get('current_rows'):
            parts.append('Current default: ' + summary_line(rec['current_default'],
                                                              rec['current_rows']) + '\n')
        parts.append('## Speed/accuracy trade\n\n![pareto](pareto.png)\n\n'
                     + md_table(trade, TRADE_COLS))
    for name, title, cols in SECTIONS:
        rows, d = load_rows(out, name)
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
        parts.append('## Wall time of the run\n\n'
                     + ', '.join(f'{k} {v:.0f} s' for k, v in walls.items()))
    except (OSError, ValueError):
        pass
    with open(os.path.join(out, 'results.md'), 'w') as f:
        f.write('\n\n'.join(parts) + '\n')
    print(f'wrote {os.path.join(out, "results.md")}')
    return parts
