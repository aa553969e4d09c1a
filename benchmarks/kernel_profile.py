"""``python benchmarks/kernel_profile.py``: CPU µs per RK4 step of the compiled kernel
alone (``step_cost.kernel_cost``: ``step.advance`` over a precomputed anchor table, 1 ms steps,
the ``moving`` head driven exactly), without MuJoCo: the quick loop for kernel work.

Each case is timed ``--rounds`` times, interleaved, and the best kept (``time.process_time``:
the machine is shared, so compare figures of one run only).
"""
import argparse

import numpy as np

from ponytail_ros.bench.scenes import make_scene
from ponytail_ros.bench.step_cost import DT, kernel_cost
from ponytail_ros.core.scene import Scene, SolverSpec


def cases(segments, crowds, integrator):
    solver = SolverSpec(integrator=integrator, dt=DT)
    out = []
    for n in segments:
        b = make_scene('moving', n_segments=n, solver=solver)
        out.append((f'{n} segments', b.scene, b.motion, 1000, 1))
    b16 = make_scene('moving', n_segments=16, solver=solver)
    for c in crowds:
        scene = Scene(chains=tuple(b16.scene.chains[0] for _ in range(c)), solver=solver)
        out.append((f'crowd {c} x 16', scene, b16.motion, max(20, 20000 // c), c))
    return out


def main(argv=None):
    p = argparse.ArgumentParser(prog='python benchmarks/kernel_profile.py',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--segments', default='10,20,50')
    p.add_argument('--crowds', default='100')
    p.add_argument('--integrator', default='rk4')
    p.add_argument('--rounds', type=int, default=3)
    args = p.parse_args(argv)
    cs = cases([int(s) for s in args.segments.split(',') if s],
               [int(s) for s in args.crowds.split(',') if s], args.integrator)
    best = {name: np.inf for name, *_ in cs}
    for _ in range(args.rounds):
        for name, scene, motion, n_steps, chains in cs:
            t = kernel_cost(scene, motion, args.integrator, n_steps=n_steps) / chains
            best[name] = min(best[name], t)
    for name, *_ in cs:
        print(f'{name:>16} {best[name] * 1e6:8.2f} µs per chain-step')


if __name__ == '__main__':
    main()
