"""``pose``: the head estimation's p, ṗ, p̈, ω, α errors and the tip error they cause, live and
look-ahead, 30-1000 Hz input with and without jitter (``pose_bench``; not in ``all``)."""
from .. import pose_bench
from ..profiles import Profile
from ..tables import Log, Meta, Row

HELP = ('head estimation p, v, a, w, alpha and tip errors, live and look-ahead, '
        '30-1000 Hz input (pose_bench.py)')


def run(prof: Profile, out: str, meta: Meta, log: Log = print) -> list[Row]:
    """``pose_bench.run`` at the profile named in ``meta``."""
    return pose_bench.cmd_pose(prof, out, meta, log)
