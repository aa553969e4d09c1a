"""The benchmark's tables: CSV + JSON files, fixed-width and markdown printing, run metadata.

Every command writes its rows with ``write_table`` (``name.csv``: one row per dict, the union of
their keys as columns; ``name.json``: ``{meta, rows, ...}``), and ``make_meta`` says what ran
where: profile, versions, CPU, BLAS pinning and the git revision of the core.
"""
import csv
import datetime
import json
import math
import os
import platform
import subprocess
import sys
from collections.abc import Callable, Sequence
from typing import IO, Any

import numpy as np

from . import mujoco_chain as MJ
from .blas_threads import PINNED

Row = dict[str, Any]
#: Run metadata, stored as ``meta`` in every table (``make_meta``).
Meta = dict[str, Any]
#: Progress output of a command (``print`` by default).
Log = Callable[..., None]
#: (header, key or function of the row, format spec); '' formats with ``str``.
Column = tuple[str, str | Callable[[Row], Any], str]


def jsonable(x: Any) -> Any:
    """``x`` with NumPy scalars as Python ones and non-finite floats as ``None`` (strict JSON)."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        x = float(x)
        return x if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def write_table(out: str, name: str, rows: Sequence[Row], meta: dict[str, Any],
                extra: dict[str, Any] | None = None) -> None:
    """``name.csv`` (one row per dict, union of keys) and ``name.json`` ({meta, rows, ...})."""
    keys = []
    for r in rows:
        for k in r:
            if k not in keys:
                keys.append(k)
    with open(os.path.join(out, name + '.csv'), 'w', newline='') as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: ('' if r.get(k) is None else r.get(k)) for k in keys})
    doc = dict(meta=meta, rows=rows)
    if extra:
        doc.update(extra)
    with open(os.path.join(out, name + '.json'), 'w') as f:
        json.dump(jsonable(doc), f, indent=1, allow_nan=False)


def print_table(rows: Sequence[Row], cols: Sequence[Column], title: str | None = None,
                file: IO[str] | None = None) -> None:
    """Fixed-width table: ``cols`` = [(header, key or callable, format)]."""
    file = file or sys.stdout
    cells = [[h for h, _, _ in cols]]
    for r in rows:
        line = []
        for _, k, fmt in cols:
            v = k(r) if callable(k) else r.get(k)
            if v is None or (isinstance(v, float) and not math.isfinite(v)):
                line.append('-')
            else:
                line.append(format(v, fmt) if fmt else str(v))
        cells.append(line)
    widths = [max(len(c[i]) for c in cells) for i in range(len(cols))]
    if title:
        print(f'\n{title}', file=file)
    for j, c in enumerate(cells):
        print('  '.join(s.rjust(w) if j and i else s.ljust(w)
                        for i, (s, w) in enumerate(zip(c, widths, strict=True))), file=file)
        if j == 0:
            print('  '.join('-' * w for w in widths), file=file)
    file.flush()


def git_describe() -> str | None:
    """This checkout's short revision, ``+core-modified`` if ``ponytail_ros/core`` has changes."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        rev = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=root,
                             capture_output=True, text=True, timeout=5).stdout.strip()
        dirty = subprocess.run(['git', 'status', '--porcelain', '--', 'ponytail_ros/core'],
                               cwd=root, capture_output=True, text=True, timeout=5).stdout.strip()
        return rev + ('+core-modified' if dirty else '') if rev else None
    except Exception:  # pragma: no cover - no git
        return None


def make_meta(profile: str, command: str) -> dict[str, Any]:
    """What ran, where: stored as ``meta`` in every table."""
    import scipy
    meta = dict(command=command, profile=profile,
                date=datetime.datetime.now().isoformat(timespec='seconds'),
                python=platform.python_version(), numpy=np.__version__, scipy=scipy.__version__,
                mujoco=(MJ.mujoco.__version__ if MJ.available() else None),
                machine=platform.machine(), processor=cpu_name(), cpus=os.cpu_count(),
                blas_threads_pinned=PINNED, git=git_describe(),
                timer='time.process_time (CPU s of this process), median of repeats')
    return meta


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else ``platform.processor()``."""
    try:
        with open('/proc/cpuinfo') as f:
            for line in f:
                if line.startswith('model name'):
                    return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def load_rows(out: str, name: str) -> tuple[list[Row] | None, dict[str, Any]]:
    """The rows of ``name.json`` in ``out`` (``None`` errors as NaN) and the whole document.

    No such file: ``(None, {})``.
    """
    path = os.path.join(out, name + '.json')
    if not os.path.exists(path):
        return None, {}
    with open(path) as f:
        doc = json.load(f)
    rows = [{k: (float('nan') if v is None and k.endswith(('_mm', '_m', 'drift_max')) else v)
             for k, v in r.items()} for r in doc.get('rows', [])]
    return rows, doc



def md_table(rows: Sequence[Row], cols: Sequence[Column]) -> str:
    """A markdown table (same ``cols`` as ``print_table``)."""
    out = ['| ' + ' | '.join(h for h, _, _ in cols) + ' |',
           '|' + '|'.join('---' if i == 0 else '---:' for i in range(len(cols))) + '|']
    for r in rows:
        cells = []
        for _, k, fmt in cols:
            v = k(r) if callable(k) else r.get(k)
            if v is None or (isinstance(v, float) and not math.isfinite(v)):
                cells.append('-')
            else:
                cells.append(format(v, fmt) if fmt else str(v))
        out.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(out)
