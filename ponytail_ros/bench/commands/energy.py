"""``energy``: energy drift per integrator and step on a still anchor, no damping.

5 segments released 45° from vertical, for the profile's ``energy_T``: relative drift
``(E - E0) / (E0 - E_rest)``: ``energy.csv/json``, ``energy.png``.
"""
import os
import time

import numpy as np

from ponytail_ros.core.head import StillMotion
from ponytail_ros.core.scene import Scene, SolverSpec

from .. import measure as M, plots
from ..profiles import Profile
from ..scenes import BenchScene, ponytail_chain
from ..tables import Log, Meta, Row, print_table, write_table

HELP = 'energy drift per integrator and step, still anchor, no damping'


def energy_scene(solver: SolverSpec | None = None) -> BenchScene:
    """5 segments of the reference ponytail on a still anchor, released 45° from vertical."""
    a = np.radians(45.0)
    chain = ponytail_chain(5, rest_direction=(np.sin(a), 0.0, -np.cos(a)))
    sc = Scene(chains=(chain,), solver=solver or SolverSpec())
    return BenchScene('energy', sc, StillMotion((0.0, 0.0, 1.6)), 10.0, True)


def run(prof: Profile, out: str, meta: Meta, log: Log = print) -> list[Row]:
    """Energy drift of each of the profile's ``energy_settings``."""
    rows: list[Row] = []
    series: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    T = prof['energy_T']
    for s in prof['energy_settings']:
        b = energy_scene().with_duration(T)
        e_rest = M.rest_energy(b)
        c0 = time.process_time()
        traj = M.simulate(b, s, sample_dt=0.01)
        cpu = time.process_time() - c0
        scale = traj.energy[0] - e_rest
        de = (traj.energy - traj.energy[0]) / scale
        series[s.label] = (traj.t, de)
        rows.append(dict(setting=s.label, integrator=s.integrator, dt=s.dt,
                         dt_label=M.fmt_dt(s.dt), projection=s.projection, duration_s=T,
                         releasable_J=scale,
                         drift_max_abs=float(np.max(np.abs(de))), drift_final=float(de[-1]),
                         growth_max=float(np.max(de)), max_gap_m=float(np.max(traj.gap)),
                         resets=len(traj.resets), cpu_s=cpu))
    title = 'Energy drift'
    if rows:
        title = (f'Energy drift: still anchor, no damping, 5 segments released 45°, {T:g} s '
                 f'(E0 - E_rest = {rows[0]["releasable_J"]:.4f} J)')
    print_table(rows, [('setting', 'setting', ''), ('max |ΔE|/(E0-Erest)', 'drift_max_abs', '.2e'),
                       ('final ΔE/(E0-Erest)', 'drift_final', '+.2e'),
                       ('max growth', 'growth_max', '+.2e'), ('max gap m', 'max_gap_m', '.1e'),
                       ('resets', 'resets', 'd'), ('CPU s', 'cpu_s', '.1f')],
                title=title)
    write_table(out, 'energy', rows, meta)
    plots.energy_plot(series, os.path.join(out, 'energy.png'))
    return rows
