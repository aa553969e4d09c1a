"""``python benchmarks/contact_cost.py``: CPU time of the contact and limit stage alone
(``contact_stage.resolve``) per internal step, on states recorded from a moving-head run.

A params file's scene (``--segments`` of its chain, or ``--characters`` N copies as in
``tick_cost --characters``) is run for ``--ticks`` frames of ``SwayYawMotion`` through the
simulator's Python step loop, which hands every step's end state to ``resolve``; those inputs
are recorded, then replayed through ``resolve`` in one compiled loop (no Python per call),
``--repeats`` times: the least CPU time (``time.process_time``) per call is printed, with the
contacts, limits and position passes the calls reported. ``--max-colliding`` lifts
``scene.MAX_COLLIDING_SEGMENTS`` for the measurement (e.g. 1024 colliding segments).
"""
import argparse
import time

import numpy as np
from numba import njit

from ponytail_ros.bench.tick_cost import crowd_scene
from ponytail_ros.core import contact_stage as K, scene as scene_module
from ponytail_ros.core.head import SwayYawMotion
from ponytail_ros.core.simulator import Simulator
from ponytail_ros.testing import load_config

__all__ = ['record', 'replay_cost', 'main']


def _crowd(params, n):
    """``tick_cost.crowd``'s scene and heads: n characters 1 m apart."""
    return crowd_scene(params, n)


def record(scene, heads, ticks, rate=120.0):
    """Every ``resolve`` call's inputs over ``ticks`` frames, stacked: ``(inputs, constants)``.

    The simulator is switched to its Python step loop (which calls ``resolve`` from Python)
    for the recording only."""
    sim = Simulator(scene, heads(0.0))
    uni = sim.unilateral
    calls = []
    inner = K.resolve

    def recording(x, q, v, w, anchor, pose, model, det, split, q_rest, has_colliders, project,
                  dt, stats):
        calls.append(tuple(np.array(a) for a in (x, q, v, w))
                     + (tuple(np.array(a) for a in anchor), tuple(np.array(a) for a in pose),
                        project, dt))
        return inner(x, q, v, w, anchor, pose, model, det, split, q_rest, has_colliders,
                     project, dt, stats)

    sim._compiled = False
    K.resolve = recording
    try:
        for k in range(1, ticks + 1):
            sim.advance_frame(k / rate, heads(k / rate))
    finally:
        K.resolve = inner
    if not calls:
        raise ValueError('the scene never reached resolve (no colliders or limits?)')
    stack = [np.stack([c[i] for c in calls]) for i in range(4)]
    anchor = tuple(np.stack([c[4][i] for c in calls]) for i in range(4))
    pose = tuple(np.stack([c[5][i] for c in calls]) for i in range(7))
    inputs = (*stack, anchor, pose, bool(calls[0][6]), float(calls[0][7]))
    constants = (uni.model_args, uni.detector_args, uni.split_args,
                 np.ascontiguousarray(sim.model.q_rest),
                 uni.detector is not None)
    return inputs, constants


@njit
def _replay(X, Q, V, W, AN, PO, project, dt, model, det, split, q_rest, has_colliders):
    stats = np.zeros(3, dtype=np.int64)
    total = np.zeros(3, dtype=np.int64)
    for k in range(X.shape[0]):
        anchor = (AN[0][k], AN[1][k], AN[2][k], AN[3][k])
        pose = (PO[0][k], PO[1][k], PO[2][k], PO[3][k], PO[4][k], PO[5][k], PO[6][k])
        K.resolve(X[k], Q[k], V[k], W[k], anchor, pose, model, det, split, q_rest,
                  has_colliders, project, dt, stats)
        total += stats
    return total


def replay_cost(inputs, constants, repeats=5):
    """``(least µs per resolve call, (contacts, limits, position passes) summed)``."""
    args = inputs + constants
    totals = _replay(*args)
    best = np.inf
    for _ in range(repeats):
        t0 = time.process_time()
        _replay(*args)
        best = min(best, time.process_time() - t0)
    return 1e6 * best / inputs[0].shape[0], totals


def main(argv=None):
    p = argparse.ArgumentParser(prog='python benchmarks/contact_cost.py',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--params', default='config/ponytail.yaml')
    p.add_argument('--chain', default='ponytail')
    p.add_argument('--segments', type=int, nargs='+', default=[12])
    p.add_argument('--characters', type=int, nargs='+',
                   help='measure crowds of this many characters instead')
    p.add_argument('--ticks', type=int, default=30)
    p.add_argument('--repeats', type=int, default=5)
    p.add_argument('--max-colliding', type=int,
                   help='raise scene.MAX_COLLIDING_SEGMENTS to this for the measurement')
    args = p.parse_args(argv)
    if args.max_colliding:
        scene_module.MAX_COLLIDING_SEGMENTS = args.max_colliding
    motion = SwayYawMotion()
    cases = []
    for n in args.characters or []:
        cases.append((f'{n} characters', *_crowd(args.params, n)))
    for n in [] if args.characters else args.segments:
        cfg = load_config(args.params, {f'{args.chain}.n_segments': n})
        cases.append((f'{n} segments', cfg.scene, motion.state_at))
    for label, scene, heads in cases:
        inputs, constants = record(scene, heads, args.ticks)
        us, (contacts, limits, passes) = replay_cost(inputs, constants, args.repeats)
        calls = inputs[0].shape[0]
        print(f'{label:>16}: {us:9.1f} µs per resolve ({calls} calls; per call '
              f'{contacts / calls:.1f} contacts, {limits / calls:.1f} limits, '
              f'{passes / calls:.2f} position passes)', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
