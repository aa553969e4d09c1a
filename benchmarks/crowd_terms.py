"""``python benchmarks/crowd_terms.py``: what each force term and the colliders cost a
crowd's tick, and which step takes its chains (the SIMD-lanes step or the general one).

The crowd is ``tick_cost.crowd_scene``'s (N copies of a params file's character, each on its
own moving head); each case switches force terms off (``ChainSpec`` fields at zero) and
optionally drops the colliders, and prints the median ms per tick and the median of the
``integrate`` stage (``StepReport.timings``) over ``--ticks`` ticks. Compare the cases of one
run only (the machine is shared).
"""
import argparse
import dataclasses
import time

import numpy as np

from ponytail_ros.bench.tick_cost import crowd_scene
from ponytail_ros.core import lanes
from ponytail_ros.core.compile import report_compile
from ponytail_ros.core.simulator import Simulator

__all__ = ['TERMS', 'cases', 'measure', 'main']

#: The force terms a case can keep (``ChainSpec`` fields; off is zero).
TERMS = ('damping', 'stiffness', 'drag_linear', 'drag_quadratic')


def cases():
    """``(name, colliders kept, terms kept)`` of every case."""
    out = [('as is', True, TERMS), ('no colliders', False, TERMS),
           ('no colliders, gravity only', False, ()), ('colliders, gravity only', True, ())]
    out += [(f'no colliders, {t} only', False, (t,)) for t in TERMS]
    return out


def measure(scene, heads, colliders, terms, ticks, rate):
    """``(median s per tick, median s of integrate, whether the lanes step runs)``."""
    off = {t: 0.0 for t in TERMS if t not in terms}
    sc = dataclasses.replace(scene, colliders=scene.colliders if colliders else [],
                             chains=[dataclasses.replace(c, **off) for c in scene.chains])
    sim = Simulator(sc, heads(0.0))
    wall, integrate = [], []
    for k in range(1, ticks + 6):
        t = k / rate
        t0 = time.perf_counter()
        report = sim.advance_frame(t, heads(t))
        if k > 5:               # (the start-up ticks left out)
            wall.append(time.perf_counter() - t0)
            integrate.append(report.timings.get('integrate', 0.0))
    uses_lanes = sim._kernel(sim._step_model()) is lanes.advance_lanes
    return float(np.median(wall)), float(np.median(integrate)), uses_lanes


def main(argv=None):
    p = argparse.ArgumentParser(prog='python benchmarks/crowd_terms.py',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--params', default='config/ponytail.yaml')
    p.add_argument('--characters', type=int, default=100)
    p.add_argument('--ticks', type=int, default=30)
    p.add_argument('--rate', type=float, default=120.0, help='ticks per simulated s')
    args = p.parse_args(argv)
    report_compile()
    scene, heads = crowd_scene(args.params, args.characters)
    for name, colliders, terms in cases():
        wall, integrate, uses_lanes = measure(scene, heads, colliders, terms, args.ticks,
                                              args.rate)
        print(f'{args.characters} characters, {name:32s} {1e3 * wall:7.2f} ms per tick, '
              f'integrate {1e3 * integrate:6.2f} ms ({"lanes" if uses_lanes else "general"} '
              f'step)')


if __name__ == '__main__':
    main()
