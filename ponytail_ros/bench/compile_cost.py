"""``python -m ponytail_ros.bench.compile_cost``: the cold compile of the kernels a scene uses,
as the first start after an install pays it, and the warm start after it, per stage.

Scenes (``--scenes``): ``demo`` (``config/ponytail.yaml``: what ``ponytail_demo`` and a node
with it compile), ``plain`` (one 12-segment chain, no colliders or limits), ``all`` (every
stage: ``python -m ponytail_ros.core.compile``, the test suite), or a params file's path.

Each run is a fresh process with an empty ``NUMBA_CACHE_DIR`` (a temporary directory: the
project's own cache is not touched) and ``PONYTAIL_COMPILE_JOBS`` set, compiling the scene's
stages (``compile.stages_for``) as a node does. Prints per run the wall time, the CPU time of
the process and its children (a two-core compile that duplicated much work would show more
CPU than the serial one; on a shared machine CPU time is the steadier figure) and the wall
and CPU time of each stage (``compile.STAGE_SECONDS``, ``STAGE_CPU``), then a warm start (the
same, its cache kept). Runs one after the other; pin them (``taskset``) for steadier figures.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

__all__ = ['measure', 'main', 'scene_stages']

_RUN = ('import json, sys; from ponytail_ros.bench.compile_cost import _run; '
        'print(json.dumps(_run(sys.argv[1])))')


def scene_stages(name):
    """The stages the scene ``name`` (see the module docstring) compiles."""
    from ponytail_ros.core import compile as c
    if name == 'all':
        return c.STAGES
    from ponytail_ros.core.scene import ChainSpec, Scene
    if name == 'plain':
        return c.stages_for(Scene(chains=[ChainSpec(n_segments=12)]))
    from ponytail_ros.app.param_values import complete_values, values_from_params_file
    from ponytail_ros.app.parameters import check_values
    if name == 'demo':
        from ponytail_ros.resources import config_path
        name = str(config_path('ponytail.yaml'))
    values = complete_values(values_from_params_file(name))
    return c.stages_for(check_values(values, [str(n) for n in values['chains']]))


def _run(name):
    """One start (in the measured process): the scene's stages compiled or loaded."""
    from ponytail_ros.core import compile as c
    t0 = time.perf_counter()
    stages = scene_stages(name)
    t1 = time.perf_counter()
    seconds, compiled = c.compile_kernels(stages)
    return dict(scene=name, seconds=seconds, compiled=compiled, setup=t1 - t0,
                stages=dict(c.STAGE_SECONDS), stages_cpu=dict(c.STAGE_CPU))


def _cpu_children():
    import resource
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def measure(scene, jobs, cache_dir):
    """``dict(scene, jobs, wall, cpu, seconds, compiled, setup, stages)`` of one start of
    ``scene`` with ``cache_dir`` as numba's cache (wall and CPU of the whole process and its
    children, s; ``setup``: building the scene, the Simulator that ``stages_for`` asks)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir), PONYTAIL_COMPILE_JOBS=str(jobs))
    c0, t0 = _cpu_children(), time.perf_counter()
    out = subprocess.run([sys.executable, '-c', _RUN, scene], env=env, capture_output=True,
                         text=True, check=True)
    wall, cpu = time.perf_counter() - t0, _cpu_children() - c0
    row = json.loads(out.stdout.strip().splitlines()[-1])
    return dict(jobs=jobs, wall=wall, cpu=cpu, **row)


def _line(label, r):
    stages = ', '.join(f'{k} {v:.1f}/{r["stages_cpu"][k]:.1f}' for k, v in r['stages'].items())
    return (f'{label}: {r["wall"]:.1f} s wall, {r["cpu"]:.1f} s CPU, scene set-up '
            f'{r["setup"]:.1f} s (compiled: {r["compiled"]}; stages, s wall/CPU: {stages})')


def main(argv=None):
    p = argparse.ArgumentParser(prog='python -m ponytail_ros.bench.compile_cost',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--scenes', default='demo,plain',
                   help='comma-separated: demo, plain, all or params files (default: '
                        '%(default)s)')
    p.add_argument('--jobs', type=int, nargs='+', default=[1], choices=[1, 2],
                   help='compile processes of each cold run, in order (default: 1)')
    p.add_argument('--json', help='write the results to this file')
    args = p.parse_args(argv)
    rows = []
    for scene in (s.strip() for s in args.scenes.split(',') if s.strip()):
        for jobs in args.jobs:
            with tempfile.TemporaryDirectory(prefix='compile_cost_') as cache:
                r = measure(scene, jobs, cache)
                rows.append(r)
                print(_line(f'{scene}, cold, {jobs} process(es)', r), flush=True)
                if jobs == args.jobs[-1]:
                    w = measure(scene, jobs, cache)
                    rows.append(dict(w, warm=True))
                    print(_line(f'{scene}, warm start', w), flush=True)
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(rows, f, indent=1)


if __name__ == '__main__':
    main()
