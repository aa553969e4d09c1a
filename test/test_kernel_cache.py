"""``kernel_cache``: the compiled kernels' cache is dropped when their sources change, in
numba's own cache locations (beside the sources, and under ``NUMBA_CACHE_DIR``)."""
from pathlib import Path

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
