"""``kernel_cache``: the compiled kernels' cache is dropped when their sources change, in
numba's own cache locations (beside the sources, and under ``NUMBA_CACHE_DIR``); a read-only
install caches elsewhere, or runs uncached saying so, never with a traceback."""
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from numba.core.caching import _CacheLocator

from ponytail_ros.core import kernel_cache, step


def test_cache_dir_under_numba_cache_dir_is_numbas_own(monkeypatch, tmp_path):
    """Under ``NUMBA_CACHE_DIR`` numba keeps a module's cache in a directory named from the
    source directory (``_CacheLocator.get_suitable_cache_subpath``): that is one of those
    ``ensure_fresh`` clears."""
    monkeypatch.setenv('NUMBA_CACHE_DIR', str(tmp_path))
    here = Path(step.__file__).resolve().parent
    numbas = tmp_path / _CacheLocator.get_suitable_cache_subpath(step.__file__)
    assert numbas in kernel_cache._cache_dirs(here)


def test_numbas_user_wide_cache_dir_is_checked_too(monkeypatch, tmp_path):
    """numba's user-wide fallback (used when neither ``NUMBA_CACHE_DIR`` nor ``__pycache__``
    can be written) is among the directories ``ensure_fresh`` clears: a stale cache there is
    not run after an upgrade."""
    from numba.core.caching import UserWideCacheLocator
    here = Path(step.__file__).resolve().parent
    numbas = Path(UserWideCacheLocator(step.advance.py_func, step.__file__).get_cache_path())
    assert numbas in kernel_cache._cache_dirs(here)


def test_stale_cache_files_are_deleted_and_the_stamp_written(monkeypatch, tmp_path):
    monkeypatch.setenv('NUMBA_CACHE_DIR', str(tmp_path))
    monkeypatch.setattr(kernel_cache, '_checked', False)
    here = Path(kernel_cache.__file__).resolve().parent
    d = tmp_path / _CacheLocator.get_suitable_cache_subpath(step.__file__)
    d.mkdir(parents=True)
    stale = [d / 'step.advance-1.py311.nbi', d / 'step.advance-1.py311.1.nbc',
             d / 'lanes.advance_lanes-9.py311.nbi']
    other = d / 'someone_else.f-1.py311.nbi'
    for f in stale + [other]:
        f.write_bytes(b'old')
    (d / kernel_cache._STAMP).write_text('not the digest\n')
    kernel_cache.ensure_fresh()
    assert not any(f.exists() for f in stale)
    assert other.exists()                       # only the kernel modules' files
    assert (d / kernel_cache._STAMP).read_text().strip() == kernel_cache._digest(here)
    # Fresh: a second check keeps what is there.
    monkeypatch.setattr(kernel_cache, '_checked', False)
    stale[0].write_bytes(b'new')
    kernel_cache.ensure_fresh()
    assert stale[0].exists()


# -- a read-only install: the cache goes elsewhere, or nowhere, never a traceback ----------
_DROP_DAC = ['--bounding-set=-dac_override,-dac_read_search',
             '--inh-caps=-dac_override,-dac_read_search']
# The markers' stage: small, so the child compiles in seconds.
_RUN = ('from ponytail_ros.core import compile as c, kernel_cache as k; '
        'c.say_compiles(); c.compile_kernels(["markers"], c._log); '
        'print(k.choose_cache_dir()[0], c._cached(c._stage_kernels("markers")[0][0]))')


def _unprivileged(tmp):
    """The command prefix that runs a child unable to write read-only files: as an ordinary
    user, nothing; as root, ``setpriv`` dropping root's permission overrides (root ignores
    file modes). None if there is no such way (the test is skipped)."""
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which('setpriv')
    if setpriv is None:
        return None
    probe = tmp / 'probe'
    probe.mkdir()
    probe.chmod(0o555)
    r = subprocess.run([setpriv, *_DROP_DAC, 'sh', '-c', f'touch {probe}/f'],
                       capture_output=True)
    return [setpriv, *_DROP_DAC] if r.returncode != 0 else None


@pytest.fixture
def read_only_install():
    """``(run, tmp)``: ``run(prelude, **env)`` runs ``prelude + _RUN`` against a copy of the
    package in a read-only directory, with ``HOME`` where nothing can be made (under the
    read-only ``tmp / 'ro'``), no ``NUMBA_CACHE_DIR`` or ``XDG_CACHE_HOME``; returns the
    ``CompletedProcess``."""
    tmp = Path(tempfile.mkdtemp(prefix='ponytail_ro_'))
    try:
        prefix = _unprivileged(tmp)
        if prefix is None:
            pytest.skip('running as root without a way to drop its file-mode override')
        site = tmp / 'site'
        src = Path(kernel_cache.__file__).resolve().parents[1]
        shutil.copytree(src, site / 'ponytail_ros',
                        ignore=shutil.ignore_patterns('__pycache__'))
        for d, _, files in os.walk(site):
            for f in files:
                os.chmod(os.path.join(d, f), 0o444)
            os.chmod(d, 0o555)
        ro = tmp / 'ro'
        ro.mkdir()
        ro.chmod(0o555)

        def run(prelude='', **env):
            e = {k: v for k, v in os.environ.items()
                 if k not in ('NUMBA_CACHE_DIR', 'XDG_CACHE_HOME')}
            e.update(PYTHONPATH=str(site), HOME=str(ro / 'home'), **env)
            # (cwd: not the checkout, whose package ``-c`` would import first)
            return subprocess.run([*prefix, sys.executable, '-c', prelude + _RUN], env=e,
                                  capture_output=True, text=True, timeout=600, cwd=tmp)
        yield run, tmp
    finally:
        for d, _, _ in os.walk(tmp):
            os.chmod(d, 0o755)
        shutil.rmtree(tmp, ignore_errors=True)


def test_a_read_only_install_caches_in_the_temp_dir(read_only_install):
    """Package directory read-only, HOME unwritable: the kernels are cached under the temp
    dir (``ponytail_ros-<uid>/numba``), said in the announcement, and a second start loads
    them."""
    run, tmp = read_only_install
    (tmp / 'tmp').mkdir()
    first = run(TMPDIR=str(tmp / 'tmp'))
    assert first.returncode == 0, first.stderr
    assert 'Traceback' not in first.stderr
    where = tmp / 'tmp' / f'ponytail_ros-{os.getuid()}' / 'numba'
    lines = first.stderr.splitlines()
    assert lines[0].startswith('ponytail_ros: compiling the simulation kernels')
    assert f'cache: {where}' in lines[0]
    assert first.stdout.split() == ['fallback', 'True']
    assert list(where.glob('*/marker_kernels.*.nbi'))
    second = run(TMPDIR=str(tmp / 'tmp'))
    assert second.returncode == 0 and second.stderr == ''     # loaded: nothing to say


def test_with_nowhere_to_cache_it_runs_uncached_saying_so_once(read_only_install):
    """Package directory, HOME and the temp dir all unwritable: it runs, compiling without a
    cache, and says so in one warning line (numba's "no locator available" error is not
    raised)."""
    run, tmp = read_only_install
    # (the temp dir read-only: Python's own choice of it, made here, as /tmp is writable)
    r = run(prelude=f'import tempfile; tempfile.tempdir = {str(tmp / "ro")!r}; ')
    assert r.returncode == 0, r.stderr
    assert 'Traceback' not in r.stderr and 'no locator' not in r.stderr
    assert r.stderr.count(kernel_cache.CACHE_WARNING) == 1
    assert r.stdout.split() == ['none', 'False']
    assert 'no cache: at every start' in r.stderr


# -- the first line: a cold cache said at once ---------------------------------------------
_SAY = ('import sys; from ponytail_ros.core import compile as c; said = c.say_if_cold(); '
        'print(said, "numba" in sys.modules)')


def _say_if_cold(cache_dir):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir))
    return subprocess.run([sys.executable, '-c', _SAY], env=env, capture_output=True,
                          text=True, timeout=60, check=True)


def test_a_cold_cache_is_said_before_numba_is_imported(tmp_path):
    """The commands' first line (``entry_points``): with no cache written by these sources,
    it says the kernels will compile, with the cache's directory, without importing numba
    (whose import takes a good part of a second)."""
    run = _say_if_cold(tmp_path)
    assert run.stdout.split() == ['True', 'False']
    assert 'compile before the first step' in run.stderr
    assert str(tmp_path) in run.stderr


def test_a_warm_cache_is_not_said(tmp_path):
    """Once the kernels are cached by these sources (the stamp of their digest and a step
    kernel's index), nothing is said; a stamp of other sources is cold again."""
    here = Path(kernel_cache.__file__).resolve().parent
    d = tmp_path / _CacheLocator.get_suitable_cache_subpath(step.__file__)
    d.mkdir(parents=True)
    (d / 'step.advance_rk4-1.py311.nbi').write_bytes(b'index')
    (d / kernel_cache._STAMP).write_text(kernel_cache._digest(here) + '\n')
    run = _say_if_cold(tmp_path)
    assert run.stdout.split() == ['False', 'False'] and run.stderr == ''
    (d / kernel_cache._STAMP).write_text('other sources\n')
    assert _say_if_cold(tmp_path).stdout.split() == ['True', 'False']
