"""The README's ``ponytail_replay`` commands, run as written on inputs of their names: a node's
recorded run (``run.mcap``), a head animation bag (``anim.mcap``), a folder of takes
(``takes/``) and a robot's bag folder with its head on TF (``robot_bag/``)."""
import os
import re
import shlex
import shutil
from pathlib import Path

import pytest

pytest.importorskip('rclpy')

from test_tf_replay import _write as write_tf_bag  # noqa: E402

from ponytail_ros.bench.head_bag import make_head_recording  # noqa: E402
from ponytail_ros.recording.cli import main  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _replay_lines():
    text = (ROOT / 'README.md').read_text(encoding='utf-8')
    return [line.strip() for line in text.splitlines()
            if re.match(r'^ {4}ponytail_replay ', line)]


def test_the_readme_replay_commands_run_as_written(live_run, tmp_path, monkeypatch, capsys):
    lines = _replay_lines()
    assert len(lines) >= 5, lines
    shutil.copy(live_run.path, tmp_path / 'run.mcap')
    make_head_recording(tmp_path / 'anim.mcap', 1.0)
    (tmp_path / 'takes').mkdir()
    for i in range(2):
        make_head_recording(tmp_path / 'takes' / f'take_{i}.mcap', 0.5)
    write_tf_bag(tmp_path, 'robot_bag')
    os.symlink(ROOT / 'config', tmp_path / 'config')
    monkeypatch.chdir(tmp_path)
    for line in lines:
        argv = shlex.split(line.split('#')[0])[1:]
        assert main(argv) == 0, (line, capsys.readouterr().err)
    for made in ('replayed.mcap', 'sim.mcap', 'sims/take_0.mcap', 'sims/take_1.mcap',
                 'robot_sim.mcap'):
        assert (tmp_path / made).stat().st_size > 0, made
    assert 'RMS' in capsys.readouterr().out        # compare printed the tips' distance
