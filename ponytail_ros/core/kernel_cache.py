"""Keeping numba's on-disk cache of the compiled kernels in step with their sources.

numba validates a cached function against the modification time and size of the file that
defines it, not of the files its callees live in: after a change to ``chain_solve.py`` (or an
upgrade that installs a new ``chain_solve.py`` beside an unchanged ``step.py``, whose wheel
timestamp is kept) the cached ``step.advance`` would still run the old solve. So the cache of
all kernel modules is keyed on one digest of their sources: when it differs from the digest
stored beside the cache, their cache files are deleted (numba then compiles once, and
``compile.report_compile`` says so).

Handled: the cache in ``__pycache__`` beside the sources (the default) and under
``NUMBA_CACHE_DIR``. numba's user-wide fallback directory (used when the install directory is
not writable) is not checked: set ``NUMBA_CACHE_DIR`` for system installs.
"""
import hashlib
import os
from pathlib import Path

__all__ = ['KERNEL_MODULES', 'ensure_fresh']

KERNEL_MODULES = ('chain_solve', 'step', 'contact_kernels', 'limit_kernels', 'head_kernels',
                  'state_kernels', 'lanes', 'step_unilateral', 'marker_kernels')
_STAMP = 'ponytail_kernels.sha256'
_checked = False


def _digest(here):
    h = hashlib.sha256()
    for name in KERNEL_MODULES:
        path = here / f'{name}.py'
        if path.exists():
            h.update(path.read_bytes())
    return h.hexdigest()


def _cache_dirs(here):
    dirs = [here / '__pycache__']
    root = os.environ.get('NUMBA_CACHE_DIR')
    if root:
        # numba's layout there: <dir name>_<sha1 of the source directory's absolute path>
        # (``_CacheLocator.get_suitable_cache_subpath``; a test holds the two together).
        src = os.path.abspath(str(here))
        hashed = hashlib.sha1(src.encode()).hexdigest()
        dirs.append(Path(root) / f'{os.path.basename(src)}_{hashed}')
    return dirs


def ensure_fresh():
    """Delete the kernels' cache files if their sources changed since they were written."""
    global _checked
    if _checked:
        return
    _checked = True
    here = Path(__file__).resolve().parent
    digest = _digest(here)
    for d in _cache_dirs(here):
        stamp = d / _STAMP
        try:
            if stamp.exists() and stamp.read_text().strip() == digest:
                continue
            if d.is_dir():
                for name in KERNEL_MODULES:
                    for f in list(d.glob(f'{name}.*.nbi')) + list(d.glob(f'{name}.*.nbc')):
                        f.unlink(missing_ok=True)
            d.mkdir(parents=True, exist_ok=True)
            stamp.write_text(digest + '\n')
        except OSError:
            pass                    # read-only: numba falls back to its user-wide cache
