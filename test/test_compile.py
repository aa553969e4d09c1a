"""``compile``: the kernels a scene uses compiled once per process, said before it starts and
stage by stage; a cold cache compiled on two cores (the contact stages in a child process), a
warm one loaded with no child."""
import importlib
import io
import subprocess
import sys

import pytest

from ponytail_ros.core import compile as kernels_compile, step_unilateral
from ponytail_ros.core.scene import ChainSpec, ColliderSpec, Scene, SolverSpec
from ponytail_ros.core.simulator import Simulator


@pytest.fixture
def fresh(monkeypatch):
    """No stage run yet in this process, nothing said yet; the stages' warm-ups recorded
    (``calls``) and run as before (the session's cache is warm: they load)."""
    monkeypatch.setattr(kernels_compile, '_done', set())
    monkeypatch.setattr(kernels_compile, '_log', None)
    calls = []

    def recorded(name, f):
        def g():
            calls.append(name)
            f()
        return g
    monkeypatch.setattr(kernels_compile, '_WARM', {
        k: recorded(k, f) for k, f in kernels_compile._WARM.items()})
    return calls


def test_a_warm_cache_is_told_apart_from_a_cold_one(tmp_path, monkeypatch):
    """``_cached`` reads numba's cache index: False before a kernel's first compile, True
    after it (and for the session's compiled contact step: a warm start starts no child)."""
    (tmp_path / 'cold_kernel.py').write_text(
        'import numba\n\n\n@numba.njit(cache=True)\ndef twice(x):\n    return 2 * x\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    module = importlib.import_module('cold_kernel')
    assert not kernels_compile._cached(module.twice)
    assert module.twice(3) == 6
    assert kernels_compile._cached(module.twice)
    assert kernels_compile._cached(step_unilateral.advance_unilateral)
    assert not kernels_compile._missing('contact step')


def test_the_child_compile_entry_runs_and_reports_its_misses():
    """The child's command, as a cold start runs it: with this test run's cache warm it loads
    the contact stages and prints 0 compiled kernels."""
    out = subprocess.run([sys.executable, '-c', kernels_compile._CHILD,
                          *kernels_compile._CHILD_STAGES], capture_output=True, text=True,
                         timeout=300, check=True)
    assert out.stdout.strip() == '0'


def test_the_two_process_warm_up_loads_what_is_cached(monkeypatch, fresh):
    """The two-core path end to end (a child forced, the cache warm): every stage runs, the
    child's last, and nothing is reported compiled."""
    monkeypatch.setattr(kernels_compile, '_missing', lambda stage: True)
    monkeypatch.setenv('PONYTAIL_COMPILE_JOBS', '2')
    started = []
    popen = subprocess.Popen

    def spy(*args, **kwargs):
        started.append(args[0])
        return popen(*args, **kwargs)
    monkeypatch.setattr(kernels_compile.subprocess, 'Popen', spy)
    assert kernels_compile._run(kernels_compile.STAGES, None, False)[1] is False
    assert started == [[sys.executable, '-c', kernels_compile._CHILD,
                        *kernels_compile._CHILD_STAGES]]
    assert fresh == ['free step', 'other integrators', 'crowd lanes', 'head fit', 'markers',
                     *kernels_compile._CHILD_STAGES]


def test_one_compile_job_starts_no_child(monkeypatch, fresh):
    """``PONYTAIL_COMPILE_JOBS=1``: a cold cache is compiled in this process alone."""
    monkeypatch.setattr(kernels_compile, '_missing', lambda stage: True)
    monkeypatch.setenv('PONYTAIL_COMPILE_JOBS', '1')
    monkeypatch.setattr(kernels_compile.subprocess, 'Popen',
                        lambda *a, **k: pytest.fail('a child was started'))
    kernels_compile.compile_kernels(kernels_compile.STAGES)
    assert list(kernels_compile.STAGE_SECONDS) == list(kernels_compile.STAGES)


@pytest.mark.parametrize('value', ['0', '3', 'two'])
def test_a_bad_compile_jobs_value_is_refused_naming_it(monkeypatch, value):
    monkeypatch.setenv('PONYTAIL_COMPILE_JOBS', value)
    with pytest.raises(ValueError, match='PONYTAIL_COMPILE_JOBS.*must be 1 or 2'):
        kernels_compile._jobs()


_SKULL = ColliderSpec.sphere(center=(0.0, 0.0, 0.0), radius=0.1)


@pytest.mark.parametrize('scene, stages', [
    (Scene(chains=(ChainSpec(n_segments=12),)), ('free step', 'head fit', 'markers')),
    (Scene(chains=(ChainSpec(n_segments=12),), colliders=(_SKULL,)),
     ('free step', 'contact step', 'head fit', 'markers')),
    (Scene(chains=(ChainSpec(n_segments=4, swing_limit=1.0),)),
     ('free step', 'contact step', 'head fit', 'markers')),
    (Scene(chains=(ChainSpec(n_segments=4),), solver=SolverSpec(integrator='rattle')),
     ('free step', 'other integrators', 'head fit', 'markers')),
    (Scene(chains=(ChainSpec(n_segments=4),), colliders=(_SKULL,),
           solver=SolverSpec(integrator='symplectic_euler')),
     ('free step', 'other integrators', 'contact step (other integrators)', 'head fit',
      'markers')),
    (Scene(chains=(ChainSpec(n_segments=4, damping=0.0),) * 8),
     ('free step', 'crowd lanes', 'head fit', 'markers')),
    (Scene(chains=(ChainSpec(n_segments=4, damping=0.0),) * 8, colliders=(_SKULL,)),
     ('free step', 'crowd lanes', 'crowd contacts', 'head fit', 'markers')),
])
def test_a_scene_compiles_only_the_stages_it_uses(scene, stages):
    """No contact stage without colliders or limits; no lanes for one chain; no other
    integrator for RK4."""
    assert kernels_compile.stages_for(scene) == stages


def test_it_is_said_before_it_starts_then_stage_by_stage(monkeypatch, fresh):
    """Kernels missing from the cache: one line naming them and the time to expect, before
    any stage runs; then a plain line per stage (stderr not a terminal)."""
    monkeypatch.setattr(kernels_compile, '_missing', lambda stage: stage != 'head fit')
    monkeypatch.setenv('PONYTAIL_COMPILE_JOBS', '1')
    lines = []

    def log(line):
        lines.append((line, list(fresh)))
    monkeypatch.setattr(sys, 'stderr', io.StringIO())
    kernels_compile.compile_kernels(['free step', 'head fit', 'markers'], log)
    first, ran = lines[0]
    assert ran == []
    assert first.startswith('ponytail_ros: compiling the simulation kernels once after '
                            'install, about ')
    assert '(free step, markers; cache: ' in first
    assert [line for line, _ in lines[1:]] == [
        line for line, _ in lines[1:] if line.startswith('ponytail_ros: [')]
    assert [line.split(' in ')[0] for line, _ in lines[1:]] == [
        'ponytail_ros: [1/2] compiled free step', 'ponytail_ros: [2/2] compiled markers']
    assert sys.stderr.getvalue() == ''


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_on_a_terminal_progress_is_one_line_rewritten(monkeypatch, fresh):
    monkeypatch.setattr(kernels_compile, '_missing', lambda stage: True)
    monkeypatch.setenv('PONYTAIL_COMPILE_JOBS', '1')
    lines = []
    monkeypatch.setattr(sys, 'stderr', _Terminal())
    kernels_compile.compile_kernels(['markers'], lines.append)
    assert len(lines) == 1 and lines[0].startswith('ponytail_ros: compiling')
    out = sys.stderr.getvalue()
    assert '\rponytail_ros: compiling [1/1] markers' in out and '\n' not in out


def test_a_simulator_compiles_its_scenes_stages_once_said(monkeypatch, fresh):
    """After ``say_compiles`` a ``Simulator`` runs its scene's stages at its construction
    (once per process); before it, nothing."""
    Simulator(Scene(chains=[ChainSpec(n_segments=3)]))
    assert fresh == []
    kernels_compile.say_compiles(lambda line: None)
    Simulator(Scene(chains=[ChainSpec(n_segments=3)]))
    assert fresh == ['free step', 'head fit', 'markers']
    Simulator(Scene(chains=[ChainSpec(n_segments=3)], colliders=[_SKULL]))
    assert fresh == ['free step', 'head fit', 'markers', 'contact step']
