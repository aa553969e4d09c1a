"""``python -m ponytail_ros.bench.compile_cost``: the cold compile of every kernel, as the first
start after an install pays it, on two cores and on one.

Each run is a fresh process with an empty ``NUMBA_CACHE_DIR`` (a temporary directory: the
project's own cache is not touched) and ``PONYTAIL_COMPILE_JOBS`` set, calling
``compile.report_compile``. Prints per run the wall time, the CPU time of the process and its
children (a two-core compile that duplicated much work would show more CPU than the serial
one) and the wall time of each part (``compile.STAGE_SECONDS``), then a warm start (the same,
its cache kept). Runs one after the other (minutes each; figures: ``docs/performance.md``).
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

__all__ = ['measure', 'main']

_RUN = ('import json; from ponytail_ros.core import compile as c; '
        'seconds, compiled = c.report_compile(lambda m: None); '
        'print(json.dumps(dict(seconds=seconds, compiled=compiled, stages=c.STAGE_SECONDS)))')


def _cpu_children():
    import resource
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def measure(jobs, cache_dir):
    """``dict(jobs, wall, cpu, seconds, compiled, stages)`` of one start with ``cache_dir``
    as numba's cache (wall and CPU of the whole process and its children, s)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir), PONYTAIL_COMPILE_JOBS=str(jobs))
    c0, t0 = _cpu_children(), time.perf_counter()
    out = subprocess.run([sys.executable, '-c', _RUN], env=env, capture_output=True, text=True,
                         check=True)
    wall, cpu = time.perf_counter() - t0, _cpu_children() - c0
    row = json.loads(out.stdout.strip().splitlines()[-1])
    return dict(jobs=jobs, wall=wall, cpu=cpu, **row)


def _line(label, r):
    stages = ', '.join(f'{k} {v:.1f}' for k, v in r['stages'].items())
    return (f'{label}: {r["wall"]:.1f} s wall, {r["cpu"]:.1f} s CPU '
            f'(compiled: {r["compiled"]}; parts, s: {stages})')


def main(argv=None):
    p = argparse.ArgumentParser(prog='python -m ponytail_ros.bench.compile_cost',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--jobs', type=int, nargs='+', default=[2, 1], choices=[1, 2],
                   help='compile processes of each cold run, in order')
    p.add_argument('--json', help='write the results to this file')
    args = p.parse_args(argv)
    rows = []
    for jobs in args.jobs:
        with tempfile.TemporaryDirectory(prefix='compile_cost_') as cache:
            r = measure(jobs, cache)
            rows.append(r)
            print(_line(f'cold, {jobs} process(es)', r), flush=True)
            if jobs == args.jobs[-1]:
                w = measure(jobs, cache)
                rows.append(dict(w, warm=True))
                print(_line('warm start', w), flush=True)
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(rows, f, indent=1)


if __name__ == '__main__':
    main()
