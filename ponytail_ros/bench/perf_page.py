"""``docs/performance.md``, generated from the benchmarks' data files in ``docs/bench/``.

Each benchmark writes its figures to a JSON file (``ponytail_bench <command>``); which machine
each file was measured on is in ``docs/bench/machines.json``. This module turns them into one
section per machine, a table per benchmark with the command that measured it::

    python -m ponytail_ros.bench.perf_page            # writes docs/performance.md

(``test/test_docs.py`` fails while the page differs from what this writes.)
"""
import json
import statistics
import sys
from pathlib import Path
from typing import Any

__all__ = ['page', 'main']

Rows = list[list[str]]


def _median(values: list[float]) -> float:
    return float(statistics.median(values)) if values else float('nan')


def _table(header: list[str], rows: Rows) -> list[str]:
    out = ['| ' + ' | '.join(header) + ' |', '|' + ' --- |' * len(header)]
    out += ['| ' + ' | '.join(r) + ' |' for r in rows]
    return out


def _pct(x: float | None) -> str:
    return '' if x is None else f'{100 * x:.1f} %'


def _node_cpu(data: Any) -> Rows:
    rows = []
    for r in data:
        p99 = r.get('tick_p99_ms')
        rows.append([str(r['params']).replace('config/', ''), _pct(r['cpu_share']),
                     _pct(r.get('step_share')),
                     f'{_median(p99):.2f}' if p99 else '',
                     f'{_median(r["ticks_per_s"]):.1f}' if r.get('ticks_per_s') else ''])
    return rows


def _node_crowd(data: Any) -> Rows:
    return [[str(r['characters']), _pct(r['cpu_share']), f'{_median(r["ticks_per_s"]):.1f}',
             f'{min(r["ticks_per_s"]):.1f}', f'{_median(r["tick_p99_ms"]):.2f}']
            for r in data]


def _replay(r: Any) -> Rows:
    return [[f'{r["simulated_s"]:g}', f'{r["wall_s"]:.1f}', f'{r["speed"]:.1f}×',
             f'{r["start_s"]:.2f}', f'{r["step_s"]:.2f}', f'{r["python_s"]:.2f}',
             f'{r["bound_speed"]:.0f}×']]


def _stages(r: Any) -> list[str]:
    s = r['stages_ms']
    return [f'{s["integrate"]:.3f}', f'{s["contacts"]:.3f}']


def _tick(data: Any) -> Rows:
    return [[str(r['n_segments']), 'yes' if r['collide'] else 'no',
             'after 1/120 s asleep' if r['idle_s'] else 'back to back',
             f'{r["median_ms"]:.3f}', *_stages(r)] for r in data]


def _crowd(data: Any) -> Rows:
    return [[str(r['characters']), f'{r["median_ms"]:.2f}', *_stages(r)]
            + ([f'{r["python_ms"]:.2f}'] if 'python_ms' in r else []) for r in data]


def _step(data: Any) -> Rows:
    rows = []
    for r in data:
        mj = r.get('mujoco_s')
        rows.append([str(r['case']), f'{1e6 * r["kernel_s"]:.2f}',
                     f'{1e6 * r["simulator_s"]:.1f}' if r.get('simulator_s') else '',
                     f'{1e6 * mj:.1f}' if mj else '',
                     f'{r["ratio"]:.4f}' if r.get('ratio') else ''])
    return rows


def _mujoco(data: Any) -> Rows:
    rows = []
    for r in data['rows']:
        rms = r.get('tip_rms_mm')
        rows.append([r['engine'], str(r['n_segments']), r['dt_label'],
                     f'{r["cpu_us_per_step"]:.1f}', f'{1e3 * r["cpu_s_per_sim_s"]:.2f}',
                     '' if rms is None or rms != rms else f'{rms:.3g}',
                     'yes' if r['stable'] else 'no'])
    return rows


def _compile(data: Any) -> Rows:
    rows = []
    for r in data:
        what = ('cache load' if not r['compiled'] else
                f'cold, {r["jobs"]} process{"es" if r["jobs"] > 1 else ""}')
        stages = ', '.join(f'{k} {v:.0f}' if v >= 1 else f'{k} {v:.2f}'
                           for k, v in r['stages'].items())
        rows.append([what, f'{r["wall"]:.0f}' if r['wall'] >= 10 else f'{r["wall"]:.1f}',
                     f'{r["cpu"]:.0f}' if r['cpu'] >= 10 else f'{r["cpu"]:.1f}', stages])
    return rows


def _pose(data: Any) -> Rows:
    rows = []
    for r in data['rows']:
        pairwise = r['rate_hz'] == 'pairwise'
        rows.append([r['mode'].replace('_', '-'),
                     'largest difference between two rates' if pairwise else f'{r["rate_hz"]:g}',
                     '' if pairwise else f'1/{1 / r["dt"]:.0f}',
                     f'{r["tip_rms_m"]:.2g}', f'{r["tip_max_m"]:.2g}'])
    return rows


def _refcheck(data: Any) -> Rows:
    rows = []
    for r in data['rows']:
        rms = r.get('rms_mm')
        rows.append([r['scene'], str(r['n_segments']), r['against'], r['dt_ref'],
                     f'{r["max_mm"]:.2g}', '' if rms is None else f'{rms:.2g}',
                     f'{r["window_s"]:.2f}'])
    return rows


def _terms(data: Any) -> Rows:
    return [[r['configuration'], f'{r["cpu_ms_per_sim_s"]:.1f}', f'{r["vs_gravity"]:.2f}',
             f'{r["rows_per_step"]:.2f}'] for r in data['rows']]


def _many(data: Any) -> Rows:
    first = data['runs'][0]['wall_s']
    return [[str(r['jobs']), f'{r["wall_s"]:.1f}', f'{r["cpu_s"] / r["wall_s"]:.2f}',
             f'{data["bags"] * data["seconds"] / r["wall_s"]:.1f}×',
             f'{r["wall_s"] / first:.2f}', f'{r["load_before"]:.1f}'] for r in data['runs']]


#: data file -> (title, command, column headers, rows from the file's JSON, note).
BENCHMARKS: dict[str, tuple] = {
    'node_cpu.json': (
        'The node beside the head demo at 120 Hz',
        'ponytail_bench node config/ponytail.yaml config/tail.yaml config/rope.yaml --floor',
        ['params', 'CPU of one core', 'of it the compiled step', 'tick p99 ms (median 1 s '
         'window)', 'ticks/s (median window)'], _node_cpu,
        '`rclpy_floor`: an rclpy node doing the same ROS I/O with no simulation.'),
    'node_crowd_cpu.json': (
        'Characters in one node (copies of `config/ponytail.yaml`) at 120 Hz',
        'ponytail_bench node config/ponytail.yaml --characters 1 5 10 20 30 100 --seconds 10',
        ['characters', 'CPU of one core', 'ticks/s (median window)', 'ticks/s (lowest window)',
         'tick p99 ms (median window)'], _node_crowd, ''),
    'replay_cost.json': (
        '`ponytail_replay` of a head bag, `config/ponytail.yaml`, process start included',
        'ponytail_bench replay',
        ['simulated s', 'wall s', 'speed', 'process start s', 'compiled step s', 'Python s',
         'start + step bound'], _replay, ''),
    'tick_cost.json': (
        'One 120 Hz tick of the core, `config/ponytail.yaml`\'s chain at RK4 1/960 s',
        'ponytail_bench tick --idle 0 0.008333',
        ['segments', 'skull contact', 'ticks', 'median ms', 'integrate ms', 'contacts ms'],
        _tick, ''),
    'crowd_tick_cost.json': (
        'Characters in one scene: one core tick (no head estimation, no ROS)',
        'ponytail_bench crowds',
        ['characters', 'median ms', 'integrate ms', 'contacts ms'], _crowd, ''),
    'crowd_runner_tick_cost.json': (
        'Characters through the runner as a node runs them (head estimation included, no ROS)',
        'ponytail_bench crowds --runner',
        ['characters', 'median ms', 'integrate ms', 'contacts ms', 'the rest (Python) ms'],
        _crowd, 'A 120 Hz tick has 8.3 ms.'),
    'step_cost.json': (
        'Per RK4 step at 1 ms against MuJoCo `mj_step` (RK4) on the same chain, same run',
        'ponytail_bench step',
        ['chain', 'compiled step µs', 'through `advance_to` µs', 'MuJoCo µs', 'ours / MuJoCo'],
        _step, 'Crowd rows: per chain-step; MuJoCo column: one 16-segment chain.'),
    'mujoco.json': (
        'Accuracy against CPU, side by side with MuJoCo (moving reference head, 3 s)',
        'ponytail_bench mujoco',
        ['engine', 'segments', 'dt s', 'CPU µs per step', 'CPU ms per simulated s',
         'tip RMS mm', 'stable'], _mujoco, ''),
    'pose/pose_reference.json': (
        'Driven by head poses: the reference\'s moving head as a PoseStamped bag, replayed onto '
        'its 10-segment scene; tip against the reference over 3 s',
        'python -m ponytail_ros.bench.pose_bench --reference',
        ['mode', 'input Hz', 'RK4 step s', 'tip RMS m', 'tip max m'], _pose,
        '`look-ahead`: `ponytail_replay --look-ahead`; `live`: the node\'s defaults with '
        '`output_stamp: simulated`.'),
    'full/refcheck.json': (
        'The core\'s RK4 against the independent reduced-coordinate reference '
        '(`../shared/reference/`) and against itself at twice the step',
        'ponytail_bench refcheck --full',
        ['scene', 'segments', 'against', 'RK4 step s', 'max mm (window)', 'tip RMS mm',
         'window s'], _refcheck, ''),
    'terms.json': (
        'What each term, collider and limit costs: a 20-segment ponytail on the moving head, '
        'RK4 1/240 s, each configuration adding one thing',
        'ponytail_bench terms',
        ['configuration', 'CPU ms per simulated s', 'against gravity alone',
         'contact/limit rows per step'], _terms, ''),
    'replay_many.json': (
        'Many bags: `ponytail_replay BAGS -o DIR -j N` over 8 head bags of 30 s, '
        '`config/ponytail.yaml`, one command each, its start included',
        'ponytail_bench many --json docs/bench/replay_many.json',
        ['-j', 'wall s', 'cores busy', 'simulated / wall', 'of -j 1\'s wall time',
         'load average before'], _many, ''),
    'compile_cost.json': (
        'The cold compile of every kernel (an empty `NUMBA_CACHE_DIR` each run)',
        'ponytail_bench compile',
        ['run', 'wall s', 'CPU s', 'stages s'], _compile, ''),
}


def _section(bench: Path, heading: str, label: str, files: list[str]) -> list[str]:
    out = ['', f'## {heading}', '', label]
    for f in files:
        title, command, header, rows_of, note = BENCHMARKS[f]
        rows = rows_of(json.loads((bench / f).read_text()))
        out += ['', f'### {title}', '', f'`{command}` (data: `docs/bench/{f}`)', '']
        out += _table(header, rows)
        if note:
            out += ['', note]
    return out


def page(bench: Path = Path('docs/bench')) -> str:
    """The markdown of ``docs/performance.md`` from the data files under ``bench``."""
    machines = json.loads((bench / 'machines.json').read_text())['machines']
    out = [
        '# Performance',
        '',
        '<!-- Generated by `python -m ponytail_ros.bench.perf_page` from docs/bench/*.json and '
        'docs/bench/machines.json; do not edit by hand. -->',
        '',
        'Speed and accuracy figures as measured, one section per machine (absolute times hold '
        'for that machine only; ratios within one run compare). Each table names the command '
        'that measured it; `ponytail_bench --help` lists them all. The quick sweep of the '
        'speed/accuracy trade (`ponytail_bench`) writes its own tables to '
        '[bench/results.md](bench/results.md). Accuracy against the independent reference '
        'is asserted by the tests (`test/test_core_reference.py`, '
        '`test/test_pose_accuracy.py`).',
    ]
    for m in machines:
        out += _section(bench, m.get('heading') or f'Machine {m["name"]}', m['label'],
                        m['files'])
    return '\n'.join(out) + '\n'


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    root = Path(args[0]) if args else Path('.')
    target = root / 'docs' / 'performance.md'
    target.write_text(page(root / 'docs' / 'bench'), encoding='utf-8')
    print(f'wrote {target}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
