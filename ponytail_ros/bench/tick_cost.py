"""``python -m ponytail_ros.bench.tick_cost``: wall time of one tick of the core for a params
file's scene at a given segment count, with and without its contacts.

Each tick is ``Simulator.advance_frame`` over one ``rate`` period with the head given at the
frame (``SwayYawMotion``, the reference's moving head), as the node calls it, Python
included; the first frames (start-up) are left out. Prints one line per
(n_segments, collide) case: median and largest ms per tick, and whether the guard reset.
What the segment ranges of ``core/scene.py`` (``MAX_SEGMENTS``, ``MAX_COLLIDING_SEGMENTS``)
rest on.

``--characters N``: instead, N characters in one scene, each the params file's chains and
colliders on its own kinematic body (the head moving as above, the characters 1 m apart): one
tick of the core for all of them, head estimation and ROS not included (a crowd node's floor).

Each line also gives the medians of the compiled step's stages (``StepReport.timings``:
``integrate``, the chains' own steps, and ``contacts``, the contact and limit stage), ms.

``--characters N --runner``: the same crowd through ``ChainRunner`` as a node runs it (the
first character on the head, the others on extra frames, one pose each per tick): head
estimation and the runner's bookkeeping included ("the rest": the tick minus the compiled
stages), ROS not.

``--idle S``: sleep S s between ticks, as a node does between its timer's ticks (1/120 s at
120 Hz): the tick then starts with caches and predictors cold, and costs more than back to
back.
"""
import argparse
import dataclasses
import json
import time

import numpy as np

from ponytail_ros.core.compile import report_compile
from ponytail_ros.core.head import KinematicState, SwayYawMotion
from ponytail_ros.core.scene import Scene
from ponytail_ros.core.simulator import Simulator
from ponytail_ros.core.stages import CONTACT_STAGES
from ponytail_ros.testing import load_config

__all__ = ['measure', 'main']


STAGES = ('integrate', 'contacts')
#: ``contacts``' parts (``stages.CONTACT_STAGES``), printed after it.
PARTS = tuple(f'contact_{name}' for name in CONTACT_STAGES)


def _stage_medians(reports):
    """Median s per tick of each of the compiled step's stages (``StepReport.timings``)."""
    return {k: float(np.median([r.timings.get(k, 0.0) for r in reports]))
            for k in STAGES + PARTS}


def _stages_text(stages):
    text = ', '.join(f'{k} {1e3 * stages[k]:.3f}' for k in STAGES)
    if stages.get('contacts', 0.0) > 0.0:
        text += ' (' + ', '.join(f'{k[len("contact_"):]} {1e3 * stages[k]:.3f}'
                                 for k in PARTS) + ')'
    return text


def measure(params, chain, n_segments, collide, ticks, idle=0.0):
    """``(median s, max s, reset reasons, stage medians)`` per tick of ``ticks`` ticks
    (``idle`` s of sleep between ticks)."""
    cfg = load_config(params, {f'{chain}.n_segments': n_segments, f'{chain}.collide': collide})
    rate = cfg.values['rate']
    motion = SwayYawMotion()
    sim = Simulator(cfg.scene, motion.state_at(0.0))
    wall, resets, reports = [], [], []
    for k in range(1, ticks + 3):
        t = k / rate
        t0 = time.perf_counter()
        report = sim.advance_frame(t, motion.state_at(t))
        if k > 2:
            wall.append(time.perf_counter() - t0)
            reports.append(report)
        if report.reset_reason:
            resets.append(report.reset_reason)
        if idle:
            time.sleep(idle)
    return float(np.median(wall)), float(max(wall)), resets, _stage_medians(reports)


def crowd_scene(params, n):
    """``(scene, heads)``: ``n`` copies of the params file's characters (chains and colliders)
    in one scene, character k on its own head ``k`` 1 m apart along Y, every head the same
    sway-and-yaw motion; ``heads(t)`` is their ``KinematicState``."""
    base = load_config(params).scene
    chains = [dataclasses.replace(c, anchor_body=k) for k in range(n) for c in base.chains]
    colliders = [dataclasses.replace(c, body=k) for k in range(n) for c in base.colliders]
    scene = Scene(chains=chains, colliders=colliders, n_kinematic_bodies=n,
                  gravity=base.gravity, wind=base.wind, solver=base.solver)
    motion = SwayYawMotion()
    offsets = np.stack([np.zeros(n), np.arange(n, dtype=float), np.zeros(n)], axis=1)

    def heads(t):
        one = motion.state_at(t)
        return KinematicState(one.position + offsets, *(np.repeat(getattr(one, f), n, axis=0)
                                                         for f in ('orientation',
                                                                   'linear_velocity',
                                                                   'angular_velocity',
                                                                   'linear_acceleration',
                                                                   'angular_acceleration')))
    return scene, heads


def crowd(params, n, ticks):
    """``(median s, max s, reset reasons, stage medians)`` per tick of ``n`` characters in
    one scene."""
    cfg = load_config(params)
    scene, heads = crowd_scene(params, n)
    rate = cfg.values['rate']
    sim = Simulator(scene, heads(0.0))
    wall, resets, reports = [], [], []
    for k in range(1, ticks + 3):
        t = k / rate
        t0 = time.perf_counter()
        report = sim.advance_frame(t, heads(t))
        if k > 2:
            wall.append(time.perf_counter() - t0)
            reports.append(report)
        if report.reset_reason:
            resets.append(report.reset_reason)
    return float(np.median(wall)), float(max(wall)), resets, _stage_medians(reports)


def crowd_runner(params, n, ticks):
    """``crowd`` through ``ChainRunner`` as a node runs it: the first character on the head,
    the others on ``n - 1`` extra frames, one pose sample of each per tick (one
    ``push_frames``, as a node with ``frames_topic`` takes them; so the head
    estimation, the sample checks and the runner's bookkeeping are included; ROS is not).
    ``(median s, max s, reset reasons, stage medians, median s of the runner's Python)``."""
    from ponytail_ros.app.runner import ChainRunner, RunnerSettings
    cfg = load_config(params)
    scene, heads = crowd_scene(params, n)
    rate = cfg.values['rate']
    runner = ChainRunner(scene, RunnerSettings(), frames=[f'character_{k}' for k in range(1, n)])
    wall, python, resets, reports = [], [], [], []
    for k in range(1, ticks + 3 + START_TICKS):
        t = k / rate
        st = heads(t)
        runner.push(t, st.position[0], st.orientation[0], 'world')
        if n > 1:                       # (one PoseArray of every frame: frames_topic)
            runner.push_frames(t, np.concatenate([st.position[1:], st.orientation[1:]], 1),
                               'world')
        t0 = time.perf_counter()
        out = runner.tick(t)
        if out is not None and k > 2 + START_TICKS:
            wall.append(time.perf_counter() - t0)
            python.append(wall[-1] - sum(out.report.timings.get(s, 0.0) for s in STAGES))
            reports.append(out.report)
        if out is not None and out.reset_reason:
            resets.append(out.reset_reason)
    return (float(np.median(wall)), float(max(wall)), resets, _stage_medians(reports),
            float(np.median(python)))


# Ticks before the runner publishes (the first poses: a velocity needs three).
START_TICKS = 3


def main(argv=None):
    p = argparse.ArgumentParser(prog='python -m ponytail_ros.bench.tick_cost',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--params', default='config/ponytail.yaml')
    p.add_argument('--chain', default='ponytail')
    p.add_argument('--segments', type=int, nargs='+', default=[12, 256, 1024, 4096])
    p.add_argument('--ticks', type=int, default=10)
    p.add_argument('--idle', type=float, nargs='+', default=[0.0],
                   help='also measure with this many seconds of sleep between ticks')
    p.add_argument('--characters', type=int, nargs='+',
                   help='measure crowds of this many characters instead')
    p.add_argument('--runner', action='store_true',
                   help='crowds through ChainRunner, each character but the first on a frame '
                        '(head estimation included)')
    p.add_argument('--json', help='write the rows to this file')
    args = p.parse_args(argv)
    report_compile()
    rows = []
    for n in args.characters or []:
        python = None
        if args.runner:
            med, worst, resets, stages, python = crowd_runner(args.params, n, args.ticks)
        else:
            med, worst, resets, stages = crowd(args.params, n, args.ticks)
        rows.append(dict(characters=n, runner=args.runner, median_ms=1e3 * med,
                         max_ms=1e3 * worst, resets=resets,
                         stages_ms={k: 1e3 * v for k, v in stages.items()},
                         **({} if python is None else {'python_ms': 1e3 * python})))
        extra = '' if python is None else f', the rest {1e3 * python:.2f}'
        print(f'{n:5d} characters: {1e3 * med:9.1f} ms per tick (max {1e3 * worst:.1f}; '
              f'120 Hz allows 8.3; {_stages_text(stages)}{extra}), '
              f'resets: {resets or "none"}')
    for n in [] if args.characters else args.segments:
        for collide in (False, True):
            for idle in args.idle:
                try:
                    med, worst, resets, stages = measure(args.params, args.chain, n, collide,
                                                         args.ticks, idle)
                except ValueError as err:               # out of the range that runs: say so
                    print(f'{n:5d} segments, collide {collide!s:5}: refused: {err}')
                    break
                rows.append(dict(n_segments=n, collide=collide, idle_s=idle,
                                 median_ms=1e3 * med, max_ms=1e3 * worst, resets=resets,
                                 stages_ms={k: 1e3 * v for k, v in stages.items()}))
                print(f'{n:5d} segments, collide {collide!s:5}, idle {idle:g} s: '
                      f'{1e3 * med:9.3f} ms per tick (max {1e3 * worst:.1f}; '
                      f'{_stages_text(stages)}), resets: {resets or "none"}')
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(rows, f, indent=1)


if __name__ == '__main__':
    main()
