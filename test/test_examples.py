"""The test of the test: ``examples/`` (a user's character: params file, walk cycle, tests) is
copied to a temporary directory outside the repository and run there with plain pytest in a
subprocess, importing only the installed package (this test's ``ponytail_ros``) and its
plugin: it passes; with the skull collider grown into the ponytail's root it fails, naming
the quantity, the bound, the collider and the instant."""
import importlib.metadata
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import ponytail_ros

pytest.importorskip('rclpy')
pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_ROOT = str(Path(ponytail_ros.__file__).resolve().parents[1])
PLUGIN = 'ponytail_ros.testing.plugin'


def _plugin_registered():
    return any(ep.name == PLUGIN for ep in importlib.metadata.entry_points(group='pytest11'))


def _pytest(where, *args):
    env = dict(os.environ)
    # The package under test (this checkout's, however it is installed) and nothing of the
    # repository's test set-up.
    env['PYTHONPATH'] = PACKAGE_ROOT
    cmd = [sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider', '-p', 'no:xdist',
           '-p', 'no:randomly', *args]
    if not _plugin_registered():         # an install from before the entry point existed
        cmd[3:3] = ['-p', PLUGIN]
    return subprocess.run(cmd, cwd=where, env=env, capture_output=True, text=True,
                          timeout=1800)


@pytest.fixture
def examples(tmp_path):
    where = tmp_path / 'my_character'
    shutil.copytree(ROOT / 'examples', where,
                    ignore=shutil.ignore_patterns('__pycache__', '*.pyc'))
    assert ROOT not in where.resolve().parents
    return where


def test_the_example_passes_from_a_copy_outside_the_repository(examples):
    out = _pytest(examples)
    assert out.returncode == 0, out.stdout + out.stderr
    assert re.search(r'\b3 passed\b', out.stdout), out.stdout
    assert str(ROOT / 'test') not in out.stdout        # ran the copy, not the project's tests


def test_the_example_fails_readably_when_the_skull_grows_into_the_root(examples):
    params = examples / 'my_character.yaml'
    text = params.read_text()
    broken, n = re.subn(r'(skull:.*?radius: )0\.09', r'\g<1>0.12', text, flags=re.S)
    assert n == 1
    params.write_text(broken)
    out = _pytest(examples, '-k', 'skull')
    assert out.returncode == 1, out.stdout + out.stderr
    assert '1 failed' in out.stdout
    # The deepest penetration of the run, named: how deep, the bound, which segment of which
    # chain in which collider, when. The root alone is 0.12 + 0.02 - 0.11 = 0.03 m inside (its
    # segment is tested on its outer half: 0.0299 m measured); the chain hanging from it can
    # only be deeper, and never deeper than the sphere's radius plus its own, 0.14 m. (Which
    # segment is deepest, and how deep, depends on how the chain falls around the root: it
    # moved from segment 1 at 0.0299 m to segment 8 at 0.03-0.04 m with rounding-level changes
    # of the step or the head fit.)
    found = re.search(r"CheckFailed: penetration depth (0\.\d+) m > max_depth 0\.001 m: chain "
                      r"'ponytail' segment \d+ inside collider 'skull' at t = \d+\.\d{3} s "
                      r"\(tick \d+ of 179\)", out.stdout)
    assert found, out.stdout
    assert 0.0295 <= float(found.group(1)) <= 0.14
    assert 'test_ponytail_stays_out_of_the_skull_while_walking' in out.stdout
