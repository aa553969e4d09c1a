"""The documentation is generated or checked, so it cannot drift from the code.

- ``docs/parameters.md`` is what ``python -m ponytail_ros.app.param_docs`` writes from the
  parameter table, and ``ponytail_node --help`` names every parameter of that table;
- ``docs/performance.md`` is what ``python -m ponytail_ros.bench.perf_page`` writes from the
  benchmarks' data files;
- every code block of the README runs in CI: a Python or YAML block is a verbatim part of a
  file of ``examples/`` (run by ``test/test_examples.py``), a shell block is a command of
  ``.ci/run`` or calls an installed command with options that command accepts.
"""
import re
import shlex
from pathlib import Path

import pytest

from ponytail_ros.app import param_docs
from ponytail_ros.app.parameters import (
    CHAIN_PARAMS,
    COLLIDER_PARAMS,
    FRAME_PARAMS,
    GLOBAL_PARAMS,
    NODE_PARAMS,
)
from ponytail_ros.bench import perf_page

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / 'README.md').read_text(encoding='utf-8')


def test_parameters_page_is_generated_from_the_table():
    page = (ROOT / 'docs' / 'parameters.md').read_text(encoding='utf-8')
    assert page == param_docs.markdown(), (
        'docs/parameters.md is stale: python -m ponytail_ros.app.param_docs docs/parameters.md')


def test_node_help_names_every_parameter_with_its_default():
    from ponytail_ros.ros.node import node_help
    text = node_help()
    groups = ((GLOBAL_PARAMS, ''), (NODE_PARAMS, ''), (CHAIN_PARAMS, '<chain>.'),
              (COLLIDER_PARAMS, '<collider>.'), (FRAME_PARAMS, '<frame>.'))
    for defs, prefix in groups:
        for p in defs:
            assert re.search(rf'^  {re.escape(prefix + p.name)} \(.*default ', text, re.M), \
                p.name


def test_every_parameter_has_a_row_in_the_page():
    page = param_docs.markdown()
    n = len(GLOBAL_PARAMS) + len(NODE_PARAMS) + len(CHAIN_PARAMS) + len(COLLIDER_PARAMS) \
        + len(FRAME_PARAMS)
    assert len(re.findall(r'^\| `', page, re.M)) == n


def test_performance_page_is_generated_from_the_data_files():
    page = (ROOT / 'docs' / 'performance.md').read_text(encoding='utf-8')
    assert page == perf_page.page(ROOT / 'docs' / 'bench'), (
        'docs/performance.md is stale: python -m ponytail_ros.bench.perf_page')


def _fenced_blocks(text):
    return re.findall(r'^```(\w*)\n(.*?)^```', text, re.M | re.S)


def _indented_commands(text):
    """The README's shell commands: lines indented by four spaces outside fenced blocks."""
    text = re.sub(r'^```.*?^```', '', text, flags=re.M | re.S)
    return [ln[4:] for ln in text.splitlines() if ln.startswith('    ') and ln.strip()]


def test_readme_code_blocks_are_parts_of_the_examples_ci_runs():
    examples = '\n'.join(p.read_text(encoding='utf-8')
                         for p in sorted((ROOT / 'examples').iterdir()) if p.is_file())
    blocks = _fenced_blocks(README)
    assert blocks, 'the README shows the example test'
    for lang, body in blocks:
        assert lang in ('python', 'yaml'), f'a README code block in {lang!r}'
        assert body in examples, f'README block not verbatim in examples/:\n{body}'


SCRIPTS = {'ponytail_node': 'ponytail_ros.node',
           'ponytail_head_demo': 'ponytail_ros.ros.head_demo',
           'ponytail_replay': 'ponytail_ros.recording.cli', 'ponytail_demo': 'ponytail_ros.demo',
           'ponytail_bench': 'ponytail_ros.bench.cli'}


def _options(words):
    """The options given before ``--ros-args`` (ROS arguments are rclpy's)."""
    if '--ros-args' in words:
        words = words[:words.index('--ros-args')]
    return [w.split('=')[0] for w in words if w.startswith('-')]


def _extras():
    setup = (ROOT / 'setup.py').read_text(encoding='utf-8')
    return set(re.findall(r"^\s+'(\w+)': ", setup, re.M))


def _check_install(part):
    """``python3 -m venv .venv`` or ``.venv/bin/pip install -q -e '.[extras]'`` with extras that
    ``setup.py`` defines."""
    if part == 'python3 -m venv .venv':
        return
    words = shlex.split(part)
    assert words[:2] == ['.venv/bin/pip', 'install'], part
    extras = re.search(r'\[([\w,]+)\]', words[-1]).group(1).split(',')
    assert set(extras) <= _extras(), f'{part}: extras {extras} not all in setup.py'


def _check_program(part):
    import subprocess
    import sys
    words = shlex.split(part)
    program = words[0].removeprefix('.venv/bin/')
    assert program in SCRIPTS, f'{part!r}: not a command of this package nor of .ci/run'
    sub = [w for w in words[1:2] if w in ('compare', 'repair')]
    done = subprocess.run([sys.executable, '-m', SCRIPTS[program], *sub, '--help'],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    for option in _options(words[1:]):
        assert option in done.stdout, f'{part!r}: {option} is not in {program} --help'


@pytest.mark.parametrize('command', _indented_commands(README))
def test_readme_shell_commands_are_ci_commands_or_accepted_options(command):
    """Each README command is a line of ``.ci/run``, or installs with extras ``setup.py`` has
    and then calls a command of this package with options its ``--help`` lists."""
    ci = (ROOT / '.ci' / 'run').read_text(encoding='utf-8')
    if command in ci.splitlines():
        return
    for part in (p.strip() for p in command.split('&&')):
        if part.startswith(('python3 -m venv', '.venv/bin/pip')):
            _check_install(part)
        else:
            _check_program(part)


def test_readme_and_docs_prose_carry_no_dates():
    """History belongs in CHANGELOG.md, figures in docs/performance.md (generated)."""
    pages = [ROOT / 'README.md'] + [ROOT / 'docs' / f'{n}.md'
                                    for n in ('method', 'limits', 'testing', 'parameters')]
    for page in pages:
        text = page.read_text(encoding='utf-8')
        assert not re.search(r'\b20\d\d-\d\d-\d\d\b', text), page.name
