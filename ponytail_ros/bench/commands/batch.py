"""``batch``: C chains of 20 segments in one scene (one banded solve).

Against one chain alone and against C separate simulators; checks that a chain of the batch
moves exactly as the same chain alone: ``batch.csv/json``.
"""
import time
from dataclasses import replace

import numpy as np

from ponytail_ros.app.motions import crowd_motion
from ponytail_ros.core.head import HeadMotion, KinematicState
from ponytail_ros.core.scene import Scene, SolverSpec
from ponytail_ros.core.simulator import Simulator

from ..profiles import Profile
from ..scenes import ponytail_chain
from ..tables import Log, Meta, Row, print_table, write_table

HELP = 'C chains in one scene vs one chain alone vs C simulators'


DT = 1.0 / 240.0


def run(prof: Profile, out: str, meta: Meta, log: Log = print) -> list[Row]:
    """The batched crowd against one chain alone and against separate simulators."""
    n = prof['batch_segments']
    solver = SolverSpec(dt=DT, max_steps_per_call=10 ** 6)
    rows, alone = _batched_rows(prof, n, solver, log)
    rows += _separate_rows(prof, n, solver, alone)
    print_table(rows, [('mode', 'mode', ''), ('chains', 'chains', 'd'),
                       ('segments', 'segments_per_chain', 'd'),
                       ('CPU ms/step', 'cpu_ms_per_step', '.2f'),
                       ('µs per chain-step', 'cpu_us_per_chain_step', '.1f'),
                       ('vs one chain alone', 'relative_to_alone', '.3f'),
                       ('max dev vs solo m', 'max_dev_from_solo_m', '.1e')],
                title=f'Batched crowd: C chains of {n} segments, RK4 1/240, one banded solve')
    write_table(out, 'batch', rows, meta)
    return rows


def _batched_rows(prof: Profile, n: int, solver: SolverSpec,
                  log: Log) -> tuple[list[Row], float | None]:
    """C chains in one scene, for each C of the profile; and the cost of one chain alone."""
    rows: list[Row] = []
    dt, steps = DT, prof['batch_steps']
    alone: float | None = None
    check: dict[int, float] = {}
    for C in prof['batch_c']:
        motion = crowd_motion(C)
        chains = tuple(replace(ponytail_chain(n), name=f'c{c}', anchor_body=c) for c in range(C))
        sc = Scene(chains=chains, n_kinematic_bodies=C, solver=solver)
        k = max(2, int(steps * (1 if C < 100 else 0.5)))
        times = []
        for _ in range(prof['batch_repeats']):
            sim = Simulator(sc, motion, 0.0)
            sim.advance_to(dt, motion)              # warm up (first call allocations)
            c0 = time.process_time()
            sim.advance_to((k + 1) * dt + 0.5 * dt, motion)
            times.append((time.process_time() - c0) / k)
        per_step = float(np.median(times))
        if C == 1:
            alone = per_step
        # Correctness: chain c of the batch equals the same chain simulated alone.
        if C > 1:
            check[C] = _deviation_from_solo(sc, C, n, solver)
        rows.append(dict(mode='one scene (batched)', chains=C, segments_per_chain=n,
                         cpu_ms_per_step=per_step * 1e3, cpu_us_per_chain_step=per_step / C * 1e6,
                         relative_to_alone=(per_step / C) / alone if alone else None,
                         max_dev_from_solo_m=check.get(C), steps_timed=k))
        log(f'  batch C={C} done')
    return rows, alone


def _deviation_from_solo(sc: Scene, C: int, n: int, solver: SolverSpec) -> float:
    """Largest state difference (m) at 0.25 s of chain C // 2 of ``sc`` from that chain alone."""
    c = C // 2
    m1 = crowd_motion(C)
    solo_motion = _SingleBody(m1, c)
    solo = Simulator(Scene(chains=(ponytail_chain(n),), solver=solver), solo_motion, 0.0)
    solo.advance_to(0.25, solo_motion)
    batch = Simulator(sc, m1, 0.0)
    batch.advance_to(0.25, m1)
    sl = batch.model.chain_slice(c)
    return float(np.max(np.abs(batch.state.x[sl] - solo.state.x)))


def _separate_rows(prof: Profile, n: int, solver: SolverSpec,
                   alone: float | None) -> list[Row]:
    """C separate simulators of one chain each, stepped in turn (C up to ``batch_loop_max``)."""
    rows: list[Row] = []
    dt, steps = DT, prof['batch_steps']
    for C in prof['batch_c']:
        if C < 2 or C > prof['batch_loop_max']:
            continue
        motion = crowd_motion(C)
        sims = [(Simulator(Scene(chains=(ponytail_chain(n),), solver=solver),
                           _SingleBody(motion, c), 0.0),
                 _SingleBody(motion, c)) for c in range(C)]
        k = max(2, steps // 2)
        for s, m in sims:
            s.advance_to(dt, m)
        times = []
        for rep in range(max(1, prof['batch_repeats'] - 1)):
            c0 = time.process_time()
            for j in range(k):
                t = (2 + rep * k + j) * dt + 0.5 * dt
                for s, m in sims:
                    s.advance_to(t, m)
            times.append((time.process_time() - c0) / k)
        per_step = float(np.median(times))
        rows.append(dict(mode='separate simulators', chains=C, segments_per_chain=n,
                         cpu_ms_per_step=per_step * 1e3, cpu_us_per_chain_step=per_step / C * 1e6,
                         relative_to_alone=(per_step / C) / alone if alone else None,
                         max_dev_from_solo_m=None, steps_timed=k))
    return rows


class _SingleBody(HeadMotion):
    """Body ``c`` of a multi-body motion, as a one-body motion."""

    def __init__(self, motion: HeadMotion, c: int) -> None:
        self.motion, self.c = motion, c

    def state_at(self, t: float) -> KinematicState:
        s = self.motion.state_at(t)
        c = slice(self.c, self.c + 1)
        return type(s)(s.position[c], s.orientation[c], s.linear_velocity[c],
                       s.angular_velocity[c], s.linear_acceleration[c], s.angular_acceleration[c])
