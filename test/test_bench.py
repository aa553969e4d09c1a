"""``ponytail_bench`` runs on a tiny configuration and writes well-formed CSV, JSON and PNG files.

No timing is asserted (the numbers of the tiny profile mean nothing); only that every
subcommand runs, and that its outputs parse, agree with each other and are plausible.
"""
import csv
import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from ponytail_ros.app.motions import SinusoidHead, SpinHead, crowd_motion, reference_motion
from ponytail_ros.bench import cli, measure, mujoco_chain
from ponytail_ros.bench.scenes import SCENES, make_scene
from ponytail_ros.core import SwayYawMotion

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


def read_csv(path):
    with open(path, newline='') as f:
        return list(csv.DictReader(f))


def read_json(path):
    with open(path) as f:
        return json.load(f)          # strict: NaN/Infinity would not be valid JSON anyway


def assert_png(path):
    assert os.path.getsize(path) > 1000
    with open(path, 'rb') as f:
        assert f.read(8) == PNG_MAGIC


@pytest.fixture(scope='module')
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp('bench')
    assert cli.main(['--tiny', '--out', str(out)]) == 0
    return out


def test_default_run_writes_every_table_and_figure(tiny_run):
    names = {'trade', 'refcheck', 'scaling', 'mujoco', 'batch', 'energy', 'terms', 'scenes'}
    for name in names:
        assert (tiny_run / f'{name}.csv').exists(), name
        doc = read_json(tiny_run / f'{name}.json')
        assert doc['meta']['profile'] == 'tiny'
        assert isinstance(doc['rows'], list)
        rows = read_csv(tiny_run / f'{name}.csv')
        assert len(rows) == len(doc['rows'])
    for png in ('pareto.png', 'scaling.png', 'energy.png'):
        assert_png(tiny_run / png)
    assert '## Speed/accuracy trade' in (tiny_run / 'results.md').read_text()
    if mujoco_chain.available():
        assert_png(tiny_run / 'mujoco.png')
    summary = read_json(tiny_run / 'summary.json')
    assert set(summary['wall_s']) >= {'trade', 'scaling', 'mujoco', 'batch', 'energy', 'terms',
                                      'total'}
    assert 'recommendation' in summary


def test_trade_rows_are_complete_and_plausible(tiny_run):
    doc = read_json(tiny_run / 'trade.json')
    rows = doc['rows']
    assert {r['scene'] for r in rows} == set(SCENES)
    for r in rows:
        assert r['cpu_s_per_sim_s'] > 0 and r['cpu_us_per_step'] > 0
        assert r['steps_per_sim_s'] == pytest.approx(1.0 / r['dt'])
        assert r['stable'] == (r['resets'] == 0)
        assert r['tip_rms_mm'] >= 0 and r['tip_max_mm'] >= r['tip_rms_mm']
        assert r['max_gap_m'] < 1e-6
        if r['scene'] in ('release', 'rope'):
            assert r['energy_drift_max'] is not None
    rec = doc['recommendation']
    assert rec['current_default'] == 'RK4 1/240'
    assert set(rec['criteria']) >= {'tip_rms_mm_moving_and_shake', 'energy_drift_still'}
    csv_rows = read_csv(tiny_run / 'trade.csv')
    assert {'scene', 'setting', 'cpu_s_per_sim_s', 'tip_rms_mm', 'tip_max_mm', 'max_gap_m',
            'energy_drift_max', 'resets'} <= set(csv_rows[0])
    assert float(csv_rows[0]['cpu_s_per_sim_s']) > 0


def test_reference_checks_agree_with_the_shared_files(tiny_run):
    rows = read_json(tiny_run / 'refcheck.json')['rows']
    shared = [r for r in rows if r['against'].startswith('ponytail_N')]
    assert shared, 'the moving and release scenes match shared reference files'
    for r in shared:
        assert r['max_mm'] < 1e-2          # 10 µm even at the tiny profile's coarse reference
    for r in rows:
        if r['against'].startswith('itself'):
            assert r['window_s'] > 0


def test_scaling_batch_energy_tables(tiny_run):
    sc = read_json(tiny_run / 'scaling.json')['rows']
    series = {r['series'] for r in sc}
    assert {'RK4 banded', 'SE banded', 'RATTLE banded'} <= series
    assert all(r['cpu_us_per_step'] > 0 for r in sc)
    batch = read_json(tiny_run / 'batch.json')['rows']
    batched = [r for r in batch if r['mode'] == 'one scene (batched)']
    assert [r['chains'] for r in batched] == list(cli.PROFILES['tiny']['batch_c'])
    for r in batched:
        if r['chains'] > 1:
            assert r['max_dev_from_solo_m'] < 1e-9     # chains in one solve do not interact
    energy = read_json(tiny_run / 'energy.json')['rows']
    assert {r['integrator'] for r in energy} == {'rk4', 'symplectic_euler', 'rattle'}
    for r in energy:
        assert r['releasable_J'] > 0 and r['drift_max_abs'] >= 0


@pytest.mark.skipif(not mujoco_chain.available(), reason='mujoco not installed')
def test_mujoco_side_by_side(tiny_run):
    doc = read_json(tiny_run / 'mujoco.json')
    engines = {r['engine'] for r in doc['rows']}
    assert engines == {'ours', 'mujoco'}
    for r in doc['rows']:
        if r['engine'] == 'mujoco':
            assert r['stable'] and r['head_error_m'] < 1e-6
    for c in doc['reference_checks']:
        assert c['ours_vs_mujoco_max_mm'] < 1e-3     # the two engines agree at a tiny step


def test_mujoco_missing_is_skipped_gracefully(tmp_path):
    assert cli.main(['mujoco', '--tiny', '--no-mujoco', '--out', str(tmp_path)]) == 0
    doc = read_json(tmp_path / 'mujoco.json')
    assert doc['rows'] == [] and 'not installed' in doc['skipped']
    assert cli.main(['scaling', '--tiny', '--no-mujoco', '--out', str(tmp_path)]) == 0
    assert 'MuJoCo RK4' not in {r['series'] for r in read_json(tmp_path / 'scaling.json')['rows']}
    assert cli.main(['report', '--out', str(tmp_path)]) == 0
    assert (tmp_path / 'results.md').read_text().startswith('# ponytail_bench results')


def test_single_subcommand_and_cli_parsing(tmp_path):
    assert cli.main(['energy', '--tiny', '--out', str(tmp_path)]) == 0
    assert (tmp_path / 'energy.csv').exists() and not (tmp_path / 'trade.csv').exists()
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(['--quick', '--full'])
    args = cli.build_parser().parse_args(['trade', '--full', '--out', 'x'])
    assert args.command == 'trade' and args.profile == 'full' and args.out == 'x'
    # Options before the subcommand count too (the subcommand's defaults used to reset them,
    # so `ponytail_bench --full --out X trade` ran the quick profile into docs/bench).
    args = cli.build_parser().parse_args(['--full', '--out', 'x', '--no-mujoco', 'trade'])
    assert args.command == 'trade' and args.profile == 'full' and args.out == 'x'
    assert args.no_mujoco
    args = cli.build_parser().parse_args(['trade'])
    assert args.profile is None and args.out is None and not args.no_mujoco


def test_motions_have_exact_derivatives():
    """Central differences of the analytic motions match their derivatives."""
    h = 1e-6
    for motion in (reference_motion(), crowd_motion(3), SinusoidHead(amplitude=(0.1, 0.02, 0.05),
                   frequency=(4.0, 2.0, 1.0), yaw_amplitude=1.0, yaw_frequency=3.0),
                   SpinHead(50.0, ramp=0.2)):
        for t in (0.05, 0.37, 1.3):
            a, b, c = motion.state_at(t - h), motion.state_at(t), motion.state_at(t + h)
            np.testing.assert_allclose((c.position - a.position) / (2 * h), b.linear_velocity,
                                       atol=1e-5)
            np.testing.assert_allclose((c.linear_velocity - a.linear_velocity) / (2 * h),
                                       b.linear_acceleration, atol=1e-3)
            np.testing.assert_allclose((c.angular_velocity - a.angular_velocity) / (2 * h),
                                       b.angular_acceleration, atol=1e-3)
    a, b = reference_motion(), SwayYawMotion()
    for t in (0.0, 0.4, 2.2):
        sa, sb = a.state_at(t), b.state_at(t)
        np.testing.assert_allclose(sa.orientation, sb.orientation, atol=1e-15)
        np.testing.assert_allclose(sa.linear_acceleration, sb.linear_acceleration, atol=1e-12)


def test_trajectory_interpolation_is_exact_for_cubics():
    t = np.linspace(0.0, 1.0, 11)
    p = np.stack([t ** 3, 2 * t ** 2, 1 - t], axis=1)
    v = np.stack([3 * t ** 2, 4 * t, -np.ones_like(t)], axis=1)
    traj = measure.Trajectory(t, p, v)
    tq = np.array([0.013, 0.5, 0.77, 1.0])
    np.testing.assert_allclose(traj.at(tq), np.stack([tq ** 3, 2 * tq ** 2, 1 - tq], axis=1),
                               atol=1e-14)


@pytest.mark.skipif(not mujoco_chain.available(), reason='mujoco not installed')
def test_mujoco_model_matches_the_scene():
    """Same masses, inertias and rest pose; the head follows its formula."""
    b = make_scene('moving', n_segments=4)
    mc = mujoco_chain.MujocoChain(b, 1 / 1000)
    chain = b.scene.chains[0]
    body_mass = mc.model.body_mass[2:]
    np.testing.assert_allclose(body_mass, chain.masses())
    np.testing.assert_allclose(mc.model.body_inertia[2:], chain.principal_inertia())
    tip0 = mc.tip()
    np.testing.assert_allclose(tip0, [-0.1, 0.0, 1.65 - 0.4], atol=1e-12)
    ts, tips, head_err, unstable = mc.run(0.2)
    assert not unstable and head_err < 1e-9
    assert math.isfinite(float(np.sum(tips)))


def test_tick_cost_and_fit_cost_commands_print_their_figures(capsys):
    """``tick_cost --characters --runner`` (the crowd through the runner, frames and head
    estimation included) and ``head_estimation_bench --cost`` run and print one line per
    case, with the compiled stages' split and no reset."""
    from ponytail_ros.bench import head_estimation_bench, tick_cost
    from ponytail_ros.resources import config_path
    tick_cost.main(['--params', str(config_path('ponytail.yaml')), '--characters', '1', '3',
                    '--runner', '--ticks', '3'])
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split()[0] for ln in lines] == ['1', '3']
    for ln in lines:
        assert 'integrate' in ln and 'contacts' in ln and 'the rest' in ln
        assert ln.endswith('resets: none')
    head_estimation_bench.main(['--cost'])
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(head_estimation_bench.RATES)
    assert all('µs per pose fit' in ln for ln in lines)


def test_perf_map_names_each_compiled_kernel_at_its_address(tmp_path):
    """``perf_map`` writes perf's map format (hex address, hex size, name), one function per
    address, and names the kernels a tick runs (here: the contact step loop and the
    published segment poses, run once) by module and function, at the addresses their
    dispatchers call."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'benchmarks'))
    import perf_map  # benchmarks/: an investigation script, not installed

    from ponytail_ros.bench.tick_cost import crowd_runner
    from ponytail_ros.core import state_kernels, step_unilateral

    crowd_runner('config/ponytail.yaml', 1, 5)
    path, n = perf_map.write_map(str(tmp_path / 'perf.map'))
    rows = [line.split(' ', 2) for line in open(path).read().splitlines()]
    assert n == len(rows) > 0
    addresses = [int(a, 16) for a, _, _ in rows]
    assert all(int(s, 16) > 0 for _, s, _ in rows)        # (no two names at one address)
    names = {name.split(' v')[0] for _, _, name in rows}
    assert {'step_unilateral.advance_unilateral', 'state_kernels.segment_poses'} <= names
    # The map's address of a kernel is the one its dispatcher calls into.
    for kernel in (step_unilateral.advance_unilateral, state_kernels.segment_poses):
        for cres in kernel.overloads.values():
            entry = cres.library.get_pointer_to_function(cres.fndesc.llvm_func_name)
            assert entry in addresses


def test_the_product_measurements_are_ponytail_bench_commands(capsys):
    """``ponytail_bench --help`` lists every measurement; ``ponytail_bench crowds`` runs
    ``tick_cost`` with its crowd sizes, the user's options after them (here: one character)."""
    with pytest.raises(SystemExit):
        cli.main(['--help'])
    listing = capsys.readouterr().out
    for name in cli.TOOLS:
        assert f'    {name} ' in listing
    from ponytail_ros.resources import config_path
    assert cli.main(['crowds', '--params', str(config_path('ponytail.yaml')),
                     '--characters', '1', '--ticks', '3']) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split()[0] for ln in lines] == ['1']
