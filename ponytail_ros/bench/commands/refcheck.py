"""``refcheck``: this core's RK4 against every file of ``../shared/reference/``.

``refcheck_all.csv/json`` (``trade`` checks only the files its scenes match).
"""
import glob
import os
from dataclasses import replace
from typing import Any

from ponytail_ros.core.scene import SolverSpec

from .. import measure as M
from ..profiles import RK4, Profile, S
from ..scenes import REFERENCE_DIR, make_scene
from ..tables import Log, Meta, Row, print_table, write_table

HELP = "RK4 against every file of ../shared/reference/"


def run(prof: Profile, out: str, meta: Meta, log: Log = print) -> list[Row]:
    """This core's RK4 at the reference step against every shared reference file."""
    rows: list[Row] = []
    dt = prof['dt_ref']
    for path in sorted(glob.glob(os.path.join(REFERENCE_DIR, 'ponytail_N*.json'))):
        name = os.path.splitext(os.path.basename(path))[0]
        shared = M.load_shared(name, REFERENCE_DIR)
        sc = shared['scene']
        n = int(sc['n_segments'])
        kind = 'moving' if sc['head'] == 'moving' else 'release'
        b = make_scene(kind, n_segments=n, duration=min(3.0, prof['durations']['moving'] * 2))
        variants: list[tuple[str, dict[str, Any]]] = [('default', {})]
        if sc.get('damping', 0.0):
            chain = replace(b.scene.chains[0], damping=float(sc['damping']))
            b = replace(b, scene=b.scene.replace(chains=(chain,)))
            fields = SolverSpec.__dataclass_fields__
            if 'damping_method' in fields:
                variants = [(f'damping_method={k}', dict(damping_method=k))
                            for k in ('auto', 'implicit', 'explicit')]
            elif 'implicit_damping' in fields:
                variants = [('implicit damping', dict(implicit_damping=True)),
                            ('explicit damping', dict(implicit_damping=False))]
        for vname, kw in variants:
            solver = SolverSpec(dt=dt, max_steps_per_call=10 ** 6, **kw)
            bb = replace(b, scene=b.scene.replace(solver=solver))
            traj = M.simulate(bb, S(RK4, dt, extra=tuple(kw.items())), every_step=True)
            c = M.check_against_shared(traj, shared, n)
            rows.append(dict(file=name, variant=vname, dt=M.fmt_dt(dt), max_mm=c['max_m'] * 1e3,
                             rms_mm=c['rms_m'] * 1e3, window_s=c['window_s']))
            log(f'  {name} ({vname}): max {c["max_m"] * 1e3:.2e} mm')
    print_table(rows, [('file', 'file', ''), ('variant', 'variant', ''), ('RK4 step', 'dt', ''),
                       ('tip max mm', 'max_mm', '.2e'), ('tip RMS mm', 'rms_mm', '.2e'),
                       ('window s', 'window_s', '.2f')],
                title='This core (RK4) against ../shared/reference/')
    write_table(out, 'refcheck_all', rows, meta)
    return rows
