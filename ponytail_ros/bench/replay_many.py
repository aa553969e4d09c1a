"""``python -m ponytail_ros.bench.replay_many``: ``ponytail_replay`` over a folder of head bags
with ``-j 1`` and ``-j 2`` (worker processes), timed as a user runs it (one command, its start
included). With two free cores the second takes about half the first's wall time.

The bags are the demo head script at 100 Hz (``head_bag.make_head_recording``, as ``ros2
bag record`` stores it), ``--bags`` of ``--seconds`` s each; the scene a params file (default
``config/ponytail.yaml``). Prints each wall time, the CPU time of the command's processes
over it (how many cores it kept busy: ~1 at ``-j 1``, up to ``-j`` when that many cores are
free), the machine's load average before each run, and the wall times' ratio.
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .head_bag import make_head_recording


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed(bags: Path, out: Path, params: str, jobs: int):
    """``(wall, cpu)`` s of ``ponytail_replay BAGS -o OUT -j JOBS --params PARAMS --quiet`` in
    a new process (cpu: its processes', workers included)."""
    cpu0, t0 = _children_cpu(), time.perf_counter()
    subprocess.run([sys.executable, '-m', 'ponytail_ros.recording.cli', str(bags), '-o',
                    str(out), '-j', str(jobs), '--params', params, '--quiet', '--overwrite'],
                   check=True)
    return time.perf_counter() - t0, _children_cpu() - cpu0


def main(argv=None):
    p = argparse.ArgumentParser(prog='python -m ponytail_ros.bench.replay_many',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--params', default='config/ponytail.yaml')
    p.add_argument('--bags', type=int, default=8, help='how many bags')
    p.add_argument('--seconds', type=float, default=30.0, help='simulated seconds per bag')
    p.add_argument('--jobs', type=int, nargs='+', default=[1, 2], help='-j values to time')
    p.add_argument('--json', help='write the results to this file')
    args = p.parse_args(argv)
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        bags = Path(tmp) / 'bags'
        bags.mkdir()
        for i in range(args.bags):
            make_head_recording(bags / f'head_{i}.mcap', args.seconds)
        timed(bags, Path(tmp) / 'warm', args.params, max(args.jobs))  # the kernel cache warm
        walls = {}
        for jobs in args.jobs:
            load = os.getloadavg()[0]
            walls[jobs], cpu = timed(bags, Path(tmp) / f'out_j{jobs}', args.params, jobs)
            print(f'{args.bags} bags x {args.seconds:g} s, -j {jobs}: {walls[jobs]:.1f} s wall '
                  f'({args.bags * args.seconds / walls[jobs]:.1f}x real time overall), '
                  f'{cpu:.1f} s CPU = {cpu / walls[jobs]:.2f} cores busy (load average '
                  f'{load:.1f} before)', flush=True)
            runs.append({'jobs': jobs, 'wall_s': walls[jobs], 'cpu_s': cpu, 'load_before': load})
    first = walls[args.jobs[0]]
    for jobs in args.jobs[1:]:
        print(f'-j {jobs} / -j {args.jobs[0]}: {walls[jobs] / first:.2f} of the wall time '
              f'({os.cpu_count()} cores on this machine)')
    if args.json:
        with open(args.json, 'w') as f:
            json.dump({'bags': args.bags, 'seconds': args.seconds, 'params': args.params,
                       'cores': os.cpu_count(), 'runs': runs}, f, indent=1)


if __name__ == '__main__':
    main()
