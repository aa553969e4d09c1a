"""Where numba's on-disk cache of the compiled kernels lives, and keeping it in step with
their sources.

Where (``choose_cache_dir``, run by ``ponytail_ros.core`` before any kernel is defined):

1. ``NUMBA_CACHE_DIR`` if the user set it;
2. else ``__pycache__`` beside the sources (numba's default) when the package directory is
   writable (an editable or user install);
3. else (a system or read-only install) ``$XDG_CACHE_HOME/ponytail_ros/numba`` (default
   ``~/.cache/ponytail_ros/numba``) if that can be written, else
   ``<temp dir>/ponytail_ros-<uid>/numba``: the package sets ``NUMBA_CACHE_DIR`` to it
   (before numba reads its configuration, or in numba's ``config`` if it was imported);
4. else no cache: the kernels compile at every start, said in one line (``CACHE_WARNING``),
   and numba's "cannot cache function ...: no locator available" error is turned into an
   uncached function (``Dispatcher.enable_caching``) instead of a traceback.

Freshness (``ensure_fresh``): numba validates a cached function against the file that
defines it, not the files its callees live in: after a change to ``chain_solve.py`` (or an
upgrade that installs a new ``chain_solve.py`` beside an unchanged ``step.py``) the cached
``step.advance`` would still run the old solve. So the cache of all kernel modules is keyed
on one digest of their sources: when it differs from the digest stored beside the cache,
their cache files are deleted (numba then compiles once, and ``compile`` says
so). Checked in every place numba may keep them: ``__pycache__``, ``NUMBA_CACHE_DIR`` (set by
the user or by ``choose_cache_dir``) and numba's user-wide directory.
"""
import hashlib
import os
import sys
import tempfile
from pathlib import Path

__all__ = ['KERNEL_MODULES', 'cache_location', 'choose_cache_dir', 'ensure_fresh',
           'is_cold']

#: The sources whose edits invalidate the cache: every module of ``core`` that defines
#: compiled code (numba's own check sees only the file of the function it loads, not an edited
#: callee in another file); the plain-Python modules beside them do not.
KERNEL_MODULES = tuple(sorted(
    p.stem for p in Path(__file__).resolve().parent.glob('*.py')
    if p.stem != 'kernel_cache'                 # (it names the marks, and defines no kernel)
    and any(mark in p.read_text(encoding='utf-8') for mark in ('njit', '@intrinsic'))))
#: Whose cache files a stale cache loses: every module of ``core`` (a kernel's callee may be
#: in any of them), not another package's files in a shared ``NUMBA_CACHE_DIR``.
_SOURCE_MODULES = tuple(sorted(p.stem for p in Path(__file__).resolve().parent.glob('*.py')))
_STAMP = 'ponytail_kernels.sha256'
_HERE = Path(__file__).resolve().parent
_checked = False
#: ``choose_cache_dir``'s answer: ``(kind, directory)``, kind one of 'user' (NUMBA_CACHE_DIR
#: set by the user), 'package' (``__pycache__``), 'fallback' (set by the package), 'none'.
_location = None

#: Said once (stderr) when no directory can hold the cache.
CACHE_WARNING = ('ponytail_ros: warning: no writable directory for the compiled kernels\' cache '
                 '(package directory, $XDG_CACHE_HOME or ~/.cache, temp dir): they will compile '
                 'at every start; set NUMBA_CACHE_DIR to a writable directory')


def _writable(d):
    """Whether files can be created in directory ``d`` (made if missing), as numba tests it."""
    try:
        os.makedirs(d, exist_ok=True)
        tempfile.TemporaryFile(dir=d).close()
        return True
    except OSError:
        return False


def _fallback_dirs():
    xdg = os.environ.get('XDG_CACHE_HOME', '').strip()
    base = Path(xdg) if xdg and os.path.isabs(xdg) else Path(os.path.expanduser('~')) / '.cache'
    try:
        uid = str(os.getuid())
    except AttributeError:                      # (not POSIX)
        uid = os.environ.get('USERNAME', 'user')
    return [base / 'ponytail_ros' / 'numba',
            Path(tempfile.gettempdir()) / f'ponytail_ros-{uid}' / 'numba']


def choose_cache_dir():
    """Decide where numba caches the kernels (see the module docstring); idempotent. Returns
    ``(kind, directory or None)``."""
    global _location
    if _location is not None:
        return _location
    user = os.environ.get('NUMBA_CACHE_DIR', '').strip()
    if user:
        _location = ('user', user)
        if not _writable(user):
            _uncached_when_no_locator()
    elif _writable(_HERE / '__pycache__'):
        _location = ('package', str(_HERE / '__pycache__'))
    else:
        found = next((d for d in _fallback_dirs() if _writable(d)), None)
        if found is not None:
            _location = ('fallback', str(found))
            os.environ['NUMBA_CACHE_DIR'] = str(found)
            config = sys.modules.get('numba.core.config')
            if config is not None:              # numba already read its environment
                config.CACHE_DIR = str(found)
        else:
            _location = ('none', None)
            print(CACHE_WARNING, file=sys.stderr, flush=True)
            _uncached_when_no_locator()
    return _location


def cache_location():
    """The cache directory the kernels use (None: no cache), for messages."""
    return choose_cache_dir()[1]


def _uncached_when_no_locator():
    """numba raises ``RuntimeError('cannot cache function ...: no locator available')`` when
    defining a ``cache=True`` function with nowhere to cache it: the function is left
    uncached instead (numba's ``NullCache``), the case said by ``CACHE_WARNING``. Installed
    only then (a writable directory always has a locator): the cache's choice stays free of
    numba's import, which ``compile.say_if_cold`` relies on."""
    from numba.core import caching, dispatcher
    enable = dispatcher.Dispatcher.enable_caching
    if getattr(enable, '_ponytail_ros', False):
        return

    def enable_caching(self):
        try:
            enable(self)
        except RuntimeError as err:
            if 'no locator available' not in str(err):
                raise
            self._cache = caching.NullCache()
    enable_caching._ponytail_ros = True
    dispatcher.Dispatcher.enable_caching = enable_caching


def _digest(here):
    h = hashlib.sha256()
    for name in KERNEL_MODULES:
        path = here / f'{name}.py'
        if path.exists():
            h.update(path.read_bytes())
    return h.hexdigest()


def _subpath(here):
    # numba's layout under a cache root: <dir name>_<sha1 of the source directory's absolute
    # path> (``_CacheLocator.get_suitable_cache_subpath``; a test holds the two together).
    src = os.path.abspath(str(here))
    return f'{os.path.basename(src)}_{hashlib.sha1(src.encode()).hexdigest()}'


def _cache_dirs(here):
    dirs = [here / '__pycache__']
    root = os.environ.get('NUMBA_CACHE_DIR')
    if root:
        dirs.append(Path(root) / _subpath(here))
    try:                                        # numba's user-wide fallback
        from numba.misc.appdirs import AppDirs
        dirs.append(Path(AppDirs(appname='numba', appauthor=False).user_cache_dir)
                    / _subpath(here))
    except Exception:
        pass
    return dirs


def _used_dir(here):
    """The directory numba will cache the kernels in (None: none)."""
    kind, root = choose_cache_dir()
    if kind == 'package':
        return here / '__pycache__'
    return None if root is None else Path(root) / _subpath(here)


def is_cold():
    """Whether the kernels will compile: no cache, or none written by these sources (the
    first start after an install or an upgrade). Reads files only: no numba."""
    used = _used_dir(_HERE)
    if used is None:
        return True
    try:
        return not ((used / _STAMP).read_text().strip() == _digest(_HERE)
                    and any(used.glob('step.*.nbi')))
    except OSError:
        return True


def ensure_fresh():
    """Delete the kernels' cache files if their sources changed since they were written."""
    global _checked
    if _checked:
        return
    _checked = True
    here = _HERE
    digest = _digest(here)
    used = _used_dir(here)
    for d in _cache_dirs(here):
        stamp = d / _STAMP
        try:
            if stamp.exists() and stamp.read_text().strip() == digest:
                continue
            if d != used and not d.is_dir():
                continue                        # not used, nothing cached there
            d.mkdir(parents=True, exist_ok=True)
            for name in _SOURCE_MODULES:
                for f in list(d.glob(f'{name}.*.nbi')) + list(d.glob(f'{name}.*.nbc')):
                    f.unlink(missing_ok=True)
            stamp.write_text(digest + '\n')
        except OSError:
            pass                    # not ours to write (a read-only directory): not used


choose_cache_dir()      # at import: ``ponytail_ros.core`` imports this before any kernel module
