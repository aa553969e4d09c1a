"""What the one-sided constraints cost per internal step: the whole step and ``resolve`` alone.

The 20-segment ponytail of ``terms`` on the reference moving head (``SwayYawMotion``), RK4 at
dt = 1/240 s, in the configurations of ``terms.term_scenes`` that have colliders or limits
(``+ 1 sphere`` is the ponytail resting on its skull collider). Each is stepped through
``seconds`` of simulated time, frame by frame at the internal step; the time spent inside
``Unilateral.resolve`` (contacts and limits: detection, position passes, impulses, friction)
is measured separately with a wrapper around it. CPU time (``time.process_time``), least of
``repeats`` interleaved runs.

Run: ``python -m ponytail_ros.bench.contacts [--segments N] [--seconds S] [--repeats R]``.
"""
import argparse
import time

from ponytail_ros.core.head import SwayYawMotion
from ponytail_ros.core.simulator import Simulator

from .terms import term_scenes

__all__ = ['bench_contacts', 'main']

LABELS = ('+ 1 sphere', '+ 1 capsule', '+ 3 colliders', '+ swing limit', '+ limits')


def _run(scene, motion, seconds):
    """``(µs per step, µs per step inside resolve, resolve calls per step)``."""
    sim = Simulator(scene, motion)
    uni = sim.unilateral
    spent = [0.0, 0]
    inner = uni.resolve

    def timed(*args, **kwargs):
        t0 = time.process_time()
        out = inner(*args, **kwargs)
        spent[0] += time.process_time() - t0
        spent[1] += 1
        return out

    uni.resolve = timed
    steps = int(round(seconds / sim.dt))
    t0 = time.process_time()
    for k in range(1, steps + 1):
        sim.advance_to(k * sim.dt, motion)
    cpu = time.process_time() - t0
    if sim.total_resets or not sim.state.is_finite():
        raise RuntimeError(f'the scene blew up: {sim.total_resets} resets')
    return 1e6 * cpu / steps, 1e6 * spent[0] / steps, spent[1] / steps


def bench_contacts(n_segments=20, seconds=2.0, repeats=3, out=print):
    """Measure; print and return ``[(label, µs_per_step, µs_in_resolve_per_step, calls)]``."""
    motion = SwayYawMotion()
    scenes = [(label, s) for label, s in term_scenes(n_segments) if label in LABELS]
    # One short run first: compiled kernels load (or compile) outside the measurement.
    _run(scenes[0][1], motion, 0.05)
    best = {}
    for _ in range(repeats):
        for label, scene in scenes:
            r = _run(scene, motion, seconds)
            old = best.get(label)
            best[label] = r if old is None else (min(old[0], r[0]), min(old[1], r[1]), r[2])
    table = [(label,) + best[label] for label, _ in scenes]
    if out is not None:
        out(f'{n_segments}-segment ponytail, reference moving head, RK4 dt = 1/240 s, '
            f'{seconds:g} s simulated, least of {repeats}')
        out(f'{"configuration":<16} {"µs / step":>10} {"µs resolve / step":>18} '
            f'{"calls/step":>11}')
        for label, step, res, calls in table:
            out(f'{label:<16} {step:>10.1f} {res:>18.1f} {calls:>11.2f}')
    return table


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--segments', type=int, default=20)
    parser.add_argument('--seconds', type=float, default=2.0)
    parser.add_argument('--repeats', type=int, default=3)
    args = parser.parse_args(argv)
    bench_contacts(args.segments, args.seconds, args.repeats)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
