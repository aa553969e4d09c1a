"""``compile``: the kernels compiled once per process; a cold cache compiled on two cores (the
step with contacts and limits in a child process), a warm one loaded with no child."""
import importlib
import subprocess
import sys

import pytest

from ponytail_ros.core import compile as kernels_compile
from ponytail_ros.core import step_unilateral


def test_a_warm_cache_is_told_apart_from_a_cold_one(tmp_path, monkeypatch):
    """``_cached`` reads numba's cache index: False before a kernel's first compile, True
    after it (and for the compiled contact step of this test run: a warm start starts no child)."""
    (tmp_path / 'cold_kernel.py').write_text(
        'import numba\n\n\n@numba.njit(cache=True)\ndef twice(x):\n    return 2 * x\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    module = importlib.import_module('cold_kernel')
    assert not kernels_compile._cached(module.twice)
    assert module.twice(3) == 6
    assert kernels_compile._cached(module.twice)
    assert kernels_compile._cached(step_unilateral.advance_unilateral)


def test_the_child_compile_entry_runs_and_reports_its_misses():
    """The child's command, as a cold start runs it: with this test run's cache warm it loads
    the contact step and prints 0 compiled kernels."""
    out = subprocess.run([sys.executable, '-c', kernels_compile._CHILD], capture_output=True,
                         text=True, timeout=300, check=True)
    assert out.stdout.strip() == '0'


def test_the_two_process_warm_up_loads_what_is_cached(monkeypatch):
    """The two-core path end to end (a child forced, the cache warm): every kernel runs, and
    nothing is reported compiled."""
    monkeypatch.setattr(kernels_compile, '_cached', lambda kernel: False)
    monkeypatch.setenv('PONYTAIL_COMPILE_JOBS', '2')
    started = []
    popen = subprocess.Popen

    def spy(*args, **kwargs):
        started.append(args[0])
        return popen(*args, **kwargs)
    monkeypatch.setattr(kernels_compile.subprocess, 'Popen', spy)
    assert kernels_compile._warm_up() == 0
    assert started == [[sys.executable, '-c', kernels_compile._CHILD]]


def test_one_compile_job_starts_no_child(monkeypatch):
    """``PONYTAIL_COMPILE_JOBS=1``: a cold cache is compiled in this process alone."""
    monkeypatch.setattr(kernels_compile, '_cached', lambda kernel: False)
    monkeypatch.setenv('PONYTAIL_COMPILE_JOBS', '1')
    monkeypatch.setattr(kernels_compile.subprocess, 'Popen',
                        lambda *a, **k: pytest.fail('a child was started'))
    assert kernels_compile._warm_up() == 0
    assert list(kernels_compile.STAGE_SECONDS) == ['free step', 'crowd lanes', 'head fit',
                                                   'markers', 'contact step']


@pytest.mark.parametrize('value', ['0', '3', 'two'])
def test_a_bad_compile_jobs_value_is_refused_naming_it(monkeypatch, value):
    monkeypatch.setenv('PONYTAIL_COMPILE_JOBS', value)
    with pytest.raises(ValueError, match='PONYTAIL_COMPILE_JOBS.*must be 1 or 2'):
        kernels_compile._jobs()
