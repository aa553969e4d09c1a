"""``scaling``: cost per step against segment count, 1..1000.

RK4, symplectic Euler and RATTLE (the compiled step's banded, O(n) joint solve) and MuJoCo
if installed: ``scaling.csv/json``, ``scaling.png``.
"""
import os
import time
import warnings

import numpy as np

from ponytail_ros.app.motions import reference_motion
from ponytail_ros.core.head import HeadMotion
from ponytail_ros.core.scene import Scene, SolverSpec
from ponytail_ros.core.simulator import Simulator

from .. import mujoco_chain as MJ, plots
from ..profiles import RATTLE, RK4, SE, Profile
from ..scenes import make_scene, ponytail_chain
from ..tables import Log, Meta, Row, print_table, write_table

HELP = 'cost per step vs segment count 1..1000 (RK4, SE, RATTLE, MuJoCo)'

SCALING_DT = 1e-4   # small enough that even 1000 segments of 0.4 mm are stable (cost per step
                    # does not depend on the step)


def _time_steps_core(scene: Scene, motion: HeadMotion, n_steps: int,
                     repeats: int) -> tuple[float, int]:
    """CPU s per internal step (median of ``repeats``) and the number of guard resets."""
    out = []
    resets = 0
    for _ in range(repeats):
        sim = Simulator(scene, motion, 0.0)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', RuntimeWarning)
            c0 = time.process_time()
            r = sim.advance_to(n_steps * scene.solver.dt + 0.5 * scene.solver.dt, motion)
            out.append((time.process_time() - c0) / max(r.steps, 1))
        resets += bool(r.reset_reason)
    return float(np.median(out)), resets


def run(prof: Profile, out: str, meta: Meta, log: Log = print) -> list[Row]:
    rows: list[Row] = []
    motion = reference_motion()
    for n in prof['scaling_n']:
        chain = ponytail_chain(n)
        steps = int(max(5, min(400, prof['scaling_steps_budget'] / (30.0 * n + 300.0))))
        for series, integ in (('RK4 banded', RK4), ('SE banded', SE),
                              ('RATTLE banded', RATTLE)):
            sc = Scene(chains=(chain,), solver=SolverSpec(integrator=integ, dt=SCALING_DT,
                                                          max_steps_per_call=10 ** 6))
            k = steps
            us, resets = _time_steps_core(sc, motion, k, prof['scaling_repeats'])
            rows.append(dict(series=series, engine='ours', integrator=integ,
                             n_segments=n, cpu_us_per_step=us * 1e6, steps_timed=k,
                             repeats=prof['scaling_repeats'], dt=SCALING_DT, resets=resets))
        if MJ.available() and n <= prof['mujoco_scaling_max']:
            mc = MJ.MujocoChain(make_scene('moving', n_segments=n), SCALING_DT)
            k = int(max(5, min(2000, 2e6 / (n ** 2.5 + 100))))
            rows.append(dict(series='MuJoCo RK4', engine='mujoco', integrator='rk4',
                             n_segments=n,
                             cpu_us_per_step=mc.time_steps(k, prof['scaling_repeats']) * 1e6,
                             steps_timed=k, repeats=prof['scaling_repeats'], dt=SCALING_DT,
                             resets=int(mc.unstable())))
        log(f'  scaling N={n} done')
    print_table(rows, [('series', 'series', ''), ('N', 'n_segments', 'd'),
                       ('µs/step', 'cpu_us_per_step', '.1f'), ('µs/step/segment',
                       lambda r: r['cpu_us_per_step'] / r['n_segments'], '.2f'),
                       ('steps', 'steps_timed', 'd'), ('resets', 'resets', 'd')],
                title='Cost per step vs segment count')
    write_table(out, 'scaling', rows, meta)
    plots.scaling_plot(rows, os.path.join(out, 'scaling.png'))
    return rows

