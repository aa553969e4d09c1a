"""``python -m ponytail_ros.bench.scale_out``: one crowd as one node, then split over several.

The same number of characters (``--characters``, copies of one params file's character,
``app/crowd.py``) runs first in one ponytail node, then in ``--nodes`` nodes, each in its own
namespace (``/scale_<g>``) beside its own head demo publishing its characters' heads, every
process started as a user would (``ponytail_node``, ``ponytail_head_demo``) in a private ROS
domain. After ``--warmup`` s of start-up it reads, over ``--seconds`` of wall time, each
node's ``/diagnostics`` (``tick rate (Hz)`` per window: the node's ticks per s, its ``rate``
when it keeps up) and each process's CPU time (user + system, ``/proc/<pid>/stat``) as a share
of one core. A node's timer runs on one core: past what one core keeps at the rate, the ROS 2
way to scale is more node processes (more cores, more machines on one DDS graph), which is what
this shows. Prints the figures; ``--json`` writes them. The figures depend on what else runs
on the machine (the load average is printed with them).
"""
from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from ponytail_ros.bench.node_cpu import DIAGNOSTICS_LISTENER, _cpu_seconds, diagnostics_windows


def split(characters: int, nodes: int) -> list[int]:
    """``characters`` over ``nodes`` groups as evenly as possible, larger groups first."""
    if not 1 <= nodes <= characters:
        raise ValueError(f'nodes = {nodes}: must be in [1, characters = {characters}]')
    base, extra = divmod(characters, nodes)
    return [base + (g < extra) for g in range(nodes)]


def _crowd_params(params: str, n: int, folder: str) -> str:
    from ponytail_ros.app.crowd import crowd_values, params_file_text
    from ponytail_ros.app.param_values import values_from_params_file
    path = os.path.join(folder, f'crowd{n}.yaml')
    with open(path, 'w') as f:
        f.write(params_file_text(crowd_values(values_from_params_file(params), n), n, params))
    return path


def _stop(procs: Sequence[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for p in procs:
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def run_layout(params: str, groups: Sequence[int], seconds: float, warmup: float,
               head_rate: float, folder: str) -> dict[str, Any]:
    """One layout: a node and a head demo per group (``groups``: characters per node)."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(120, 200)),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    procs: list[dict[str, Any]] = []
    listener = None
    all_procs: list[subprocess.Popen] = []
    try:
        for g, n in enumerate(groups):
            ns = f'/scale_{g}'
            path = _crowd_params(params, n, folder)
            head = subprocess.Popen(
                [sys.executable, '-c', 'from ponytail_ros.ros.head_demo import main; main()',
                 '--ros-args', '-p', f'rate:={head_rate}', '-p', f'characters:={n}',
                 '-p', f'origin:=[0.0, {2.0 * g}, 1.6]', '-r', f'__ns:={ns}'],
                env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            node = subprocess.Popen(
                [sys.executable, '-c', 'from ponytail_ros.node import main; main()',
                 '--ros-args', '--params-file', path, '-r', f'__ns:={ns}'],
                env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            all_procs += [head, node]
            procs += [dict(role='node', namespace=ns, characters=n, proc=node),
                      dict(role='head demo', namespace=ns, characters=n, proc=head)]
        load_before = os.getloadavg()[0]
        time.sleep(warmup)
        listener = subprocess.Popen(
                [sys.executable, '-c', DIAGNOSTICS_LISTENER], env=env, text=True,
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        all_procs.append(listener)
        c0 = [_cpu_seconds(p['proc'].pid) for p in procs]
        t0 = time.monotonic()
        time.sleep(seconds)
        c1 = [_cpu_seconds(p['proc'].pid) for p in procs]
        t1 = time.monotonic()
        for p in procs:
            if p['proc'].poll() is not None:
                err = p['proc'].stderr.read().decode()[-2000:] if p['proc'].stderr else ''
                raise RuntimeError(f'{p["role"]} in {p["namespace"]} exited: {err}')
        listener.send_signal(signal.SIGINT)
        out, _ = listener.communicate(timeout=10)
    finally:
        _stop(all_procs)
    windows: dict[str, list[list[Any]]] = {}
    for name, kv in diagnostics_windows(out):
        if 'tick rate (Hz)' in kv:
            rate = kv['tick rate (Hz)']
            windows.setdefault(name, []).append([None if rate == 'n/a' else float(rate),
                                                 float(kv['ticks per s']),
                                                 float(kv['dropped time (s)'])])
    rows = []
    for p, a, b in zip(procs, c0, c1, strict=True):
        row = {k: p[k] for k in ('role', 'namespace', 'characters')}
        row['cpu_share'] = (b - a) / (t1 - t0)
        if p['role'] == 'node':
            mine = [w for name, ws in windows.items() if p['namespace'] + '/' in name
                    for w in ws]
            rates = [w[0] for w in mine if w[0] is not None]
            row.update(tick_rate_hz=rates, ticks_per_s=[w[1] for w in mine],
                       dropped_time_s=mine[-1][2] if mine else None)
        rows.append(row)
    return dict(groups=list(groups), seconds=seconds, warmup=warmup, head_rate=head_rate,
                load_average_before=load_before, load_average_after=os.getloadavg()[0],
                processes=rows)


def describe(layout: dict[str, Any]) -> str:
    groups = layout['groups']
    lines = [f'{len(groups)} node{"s" * (len(groups) > 1)} ({" + ".join(map(str, groups))} '
             f'characters; load average {layout["load_average_before"]:.1f} before, '
             f'{layout["load_average_after"]:.1f} after):']
    for row in layout['processes']:
        text = (f'  {row["namespace"]:9s} {row["role"]:9s} {row["characters"]:4d} characters: '
                f'{100 * row["cpu_share"]:5.1f} % of one core')
        if row['role'] == 'node':
            rates = row['tick_rate_hz']
            text += (f'; tick rate median {np.median(rates):.1f} Hz, lowest {min(rates):.1f} '
                     f'({len(rates)} windows); simulated time dropped '
                     f'{row["dropped_time_s"]:.2f} s' if rates else '; no /diagnostics heard')
        lines.append(text)
    total = sum(r['cpu_share'] for r in layout['processes'])
    lines.append(f'  all processes: {100 * total:.1f} % of one core')
    return '\n'.join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog='python -m ponytail_ros.bench.scale_out',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('params', nargs='?', default='config/ponytail.yaml',
                   help="one character's params file (default config/ponytail.yaml)")
    p.add_argument('--characters', type=int, default=100, help='characters in all (100)')
    p.add_argument('--nodes', type=int, default=2, help='nodes of the split layout (2)')
    p.add_argument('--seconds', type=float, default=15.0, help='measured wall time (s)')
    p.add_argument('--warmup', type=float, default=10.0, help='start-up left out (s)')
    p.add_argument('--head-rate', type=float, default=120.0, help='head demos\' rate (Hz)')
    p.add_argument('--json', help='write the results to this file')
    args = p.parse_args(argv)
    try:
        layouts = [[args.characters], split(args.characters, args.nodes)]
    except ValueError as err:
        p.error(str(err))
    print(f'{args.characters} characters of {args.params}, one node vs {args.nodes} nodes in '
          f'their own namespaces; {args.seconds:g} s measured after {args.warmup:g} s of '
          f'start-up; {os.cpu_count()} CPUs on this machine', flush=True)
    results = []
    with tempfile.TemporaryDirectory(prefix='scale_out_') as folder:
        for groups in layouts:
            layout = run_layout(args.params, groups, args.seconds, args.warmup,
                                args.head_rate, folder)
            results.append(layout)
            print(describe(layout), flush=True)
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
