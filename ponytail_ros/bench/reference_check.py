"""Accuracy against the independent reference trajectories (``../shared/reference/``).

    python -m ponytail_ros.bench.reference_check [--steps 240 1000 8000]
        [--files N10_moving_hanging ...]

For every file and internal step (RK4, head driven exactly): the largest distance of any joint
point to the reference over the file's valid window, the tip's RMS distance, and the CPU time
per simulated second. The chain is reported at the exact sample times (``Simulator.state_at``),
so the figures measure integration error, not the accumulator's sub-step lag.
"""
import argparse
import time

import numpy as np

from ponytail_ros.core import Simulator, SolverSpec
from ponytail_ros.core.reference import default_reference_dir, load_reference, reference_scene


def measure(ref, dt, integrator='rk4'):
    scene, motion = reference_scene(ref, SolverSpec(integrator=integrator, dt=dt,
                                                    max_steps_per_call=1_000_000))
    sim = Simulator(scene, motion)
    times = ref.t[ref.t <= ref.window() + 1e-9]
    worst = np.zeros(times.size)
    tip = np.zeros(times.size)
    cpu = time.process_time()
    for k, tk in enumerate(times):
        sim.advance_to(tk, motion)
        _, distal = sim.joint_positions(tk)
        d = np.linalg.norm(distal - ref.points[:, k], axis=1)
        worst[k], tip[k] = d.max(), d[-1]
    cpu = time.process_time() - cpu
    return worst.max(), float(np.sqrt(np.mean(tip ** 2))), cpu / times[-1], times[-1]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--steps', type=float, nargs='+', default=[240, 1000, 8000],
                        help='internal step rates, Hz (default 240 1000 8000)')
    parser.add_argument('--files', nargs='+', default=None,
                        help='reference names without the ponytail_ prefix (default: all)')
    parser.add_argument('--integrator', default='rk4')
    args = parser.parse_args(argv)
    ref_dir = default_reference_dir()
    paths = sorted(ref_dir.glob('ponytail_N*.json')) if args.files is None else \
        [ref_dir / f'ponytail_{f}.json' for f in args.files]
    if not paths or not paths[0].exists():
        raise SystemExit(f'no reference files in {ref_dir}')
    print(f'{"file":30s} {"step":>8s} {"window s":>8s} {"max any joint m":>15s} '
          f'{"tip RMS m":>10s} {"CPU s/sim s":>11s}')
    for path in paths:
        ref = load_reference(path)
        for rate in args.steps:
            worst, rms, cpu, window = measure(ref, 1.0 / rate, args.integrator)
            print(f'{path.stem[9:]:30s} {"1/" + format(rate, "g"):>8s} {window:8.2f} '
                  f'{worst:15.2e} {rms:10.2e} {cpu:11.3f}', flush=True)


if __name__ == '__main__':
    main()
