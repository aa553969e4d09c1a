"""``terms``: what each force term, collider and joint limit costs, and each ready-made scene.

A 20-segment ponytail with each term added in turn (switched-off terms against the plain
scene), and every ``config/*.yaml`` (``bench/term_cost.py``): ``terms.csv/json``,
``scenes.csv/json``.
"""
from .. import term_cost as terms
from ..profiles import Profile
from ..tables import Log, Meta, Row, write_table

HELP = 'cost of each force term, collider and limit; of each ready-made scene'


def run(prof: Profile, out: str, meta: Meta, log: Log = print) -> list[Row]:
    """Cost of each term, collider and limit, and of each ready-made scene (``term_cost.py``)."""
    seconds, repeats = prof['terms_seconds'], prof['terms_repeats']
    table = terms.bench_terms(20, seconds, repeats, out=log)
    rows = [dict(configuration=label, cpu_ms_per_sim_s=1e3 * per_s, vs_gravity=rel,
                 rows_per_step=r, seconds=seconds, repeats=repeats)
            for label, per_s, rel, r in table]
    write_table(out, 'terms', rows, meta)
    table = terms.bench_ready_made(seconds, repeats, out=log)
    scene_rows = [dict(scene=name, models=what, segments=n, cpu_ms_per_sim_s=1e3 * per_s,
                       rows_per_step=r, seconds=seconds, repeats=repeats)
                  for name, what, n, per_s, r in table]
    write_table(out, 'scenes', scene_rows, meta)
    return rows
