"""``python -m ponytail_ros.bench.step_cost``: CPU per internal step, the compiled step against
MuJoCo's ``mj_step``, measured in the same run on the same chain (RK4, head driven exactly).

Ours is timed two ways: the kernel alone (the compiled step the ``Simulator`` dispatches to,
over a precomputed anchor table: the physics; ``step.advance``, or for a crowd
``lanes.advance_lanes``) and through ``Simulator.advance_to`` in ticks of 1/120 s (what a caller
pays per step, Python included: the motion evaluated, the anchor table, the guard; the
simulator's construction, once per run, is not in it; ``sim/kernel`` their ratio, for single
chains and crowds). MuJoCo:
``mj_step`` in a Python loop (its own cost plus ~1 µs of binding per call). Crowds: C chains of
16 segments in one scene, per chain-step (the lanes kernel: ``lanes.LANES`` chains per SIMD
block), against one 16-segment chain in MuJoCo (MuJoCo is left out beyond 300 segments: its
serial chain's dense mass matrix makes a step O(n³)). Prints a table; ``--json`` writes the
rows; ``--no-mujoco`` leaves MuJoCo out (its column then nan). Compiles (or loads) only the
kernels its scenes use.
"""
import argparse
import json
import time

import numpy as np

from ponytail_ros.core import step as compiled
from ponytail_ros.core.compile import say_compiles
from ponytail_ros.core.head import stack_anchors
from ponytail_ros.core.scene import Scene, SolverSpec
from ponytail_ros.core.simulator import Simulator

from . import mujoco_chain
from .scenes import make_scene

DT = 1e-3


def _best(f, repeats):
    best = np.inf
    for _ in range(repeats):
        c0 = time.process_time()
        f()
        best = min(best, time.process_time() - c0)
    return best


def kernel_cost(scene, motion, integrator='rk4', n_steps=1000, repeats=5):
    """CPU seconds per step of the compiled step alone (anchor table precomputed): the kernel
    the ``Simulator`` runs for this scene (``step.advance``, or ``lanes.advance_lanes`` for a
    crowd)."""
    sim = Simulator(scene, motion, 0.0)
    times = sim._stage_times(n_steps)
    tab = stack_anchors([sim.anchors(motion.state_at(t)) for t in times])
    A = compiled.AnchorTable(*(np.ascontiguousarray(a) for a in tab.__dict__.values()))
    M = sim._step_model()
    kernel = sim._kernel(M).kernel
    st = sim.state
    zeros = np.zeros((sim.model.n, 3))
    f_c = np.zeros((sim.model.n, 3))

    def run():
        x, q, v, w = (a.copy() for a in (st.x, st.q, st.v, st.w))
        status = kernel(M, A, n_steps, scene.solver.dt, x, q, v, w, zeros, zeros, f_c)
        assert status == compiled.OK
    run()
    return _best(run, repeats) / n_steps


def simulator_cost(scene, motion, duration=1.0, tick=1 / 120, repeats=3):
    """CPU seconds per internal step through ``Simulator.advance_to`` at ticks of ``tick``,
    from rest at t = 0 over ``duration`` s (the simulator built before the clock starts)."""
    ticks = [k * tick for k in range(1, int(round(duration / tick)) + 1)]

    def run():
        sim = Simulator(scene, motion, 0.0)
        c0 = time.process_time()
        for t in ticks:
            sim.advance_to(t, motion)
        return time.process_time() - c0
    run()
    n_steps = int(round(duration / scene.solver.dt))
    return min(run() for _ in range(repeats)) / n_steps


def mujoco_cost(bench, n_steps=2000, repeats=5):
    if not mujoco_chain.available():
        return float('nan')
    return min(mujoco_chain.MujocoChain(bench, DT).time_steps(n_steps, 1) for _ in range(repeats))


def main(argv=None):
    p = argparse.ArgumentParser(prog='python -m ponytail_ros.bench.step_cost',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--segments', default='1,10,20,50,100,200,500,1000',
                   help='comma-separated chain lengths (default: %(default)s)')
    p.add_argument('--crowds', default='10,100,1000', help='chains of 16 segments per scene')
    p.add_argument('--json', help='write the rows to this file')
    p.add_argument('--no-mujoco', action='store_true', help='leave MuJoCo out (slow beyond '
                   '100 segments: its serial chain\'s step is O(n³))')
    args = p.parse_args(argv)
    say_compiles()
    mujoco = not args.no_mujoco
    rows = []
    print(f'{"case":>22} {"ours kernel µs":>15} {"ours sim µs":>12} {"sim/kernel":>11} '
          f'{"MuJoCo µs":>10} {"kernel/MuJoCo":>14}')
    for n in (int(s) for s in args.segments.split(',')):
        bench = make_scene('moving', n_segments=n,
                           solver=SolverSpec(integrator='rk4', dt=DT))
        k = kernel_cost(bench.scene, bench.motion)
        s = simulator_cost(bench.scene, bench.motion)
        # MuJoCo's serial chain has a dense mass matrix (O(n³) per step): beyond 300 segments
        # one run would take hours.
        mj = mujoco_cost(bench) if mujoco and n <= 300 else float('nan')
        rows.append(dict(case=f'{n} segments', n_segments=n, chains=1, kernel_s=k,
                         simulator_s=s, mujoco_s=mj, ratio=k / mj))
    bench16 = make_scene('moving', n_segments=16, solver=SolverSpec(integrator='rk4', dt=DT))
    mj16 = mujoco_cost(bench16) if mujoco else float('nan')
    for c in (int(s) for s in args.crowds.split(',')):
        chain = bench16.scene.chains[0]
        scene = Scene(chains=tuple(chain for _ in range(c)),
                      solver=SolverSpec(integrator='rk4', dt=DT))
        k = kernel_cost(scene, bench16.motion, n_steps=max(20, 20000 // c)) / c
        # (a shorter run for a large crowd: at least 12 ticks)
        s = simulator_cost(scene, bench16.motion, duration=max(0.1, min(1.0, 100 / c))) / c
        rows.append(dict(case=f'crowd {c} x 16', n_segments=16, chains=c, kernel_s=k,
                         simulator_s=s, mujoco_s=mj16, ratio=k / mj16))
    for r in rows:
        print(f'{r["case"]:>22} {r["kernel_s"] * 1e6:15.2f} {r["simulator_s"] * 1e6:12.2f} '
              f'{r["simulator_s"] / r["kernel_s"]:11.2f} {r["mujoco_s"] * 1e6:10.2f} '
              f'{r["ratio"]:14.4f}')
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(rows, f, indent=1)


if __name__ == '__main__':
    main()
