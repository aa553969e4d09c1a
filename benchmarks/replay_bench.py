"""Benchmark of the offline replay: simulated seconds per wall second.

Run: ``python benchmarks/replay_bench.py [--seconds 20] [--quick]``.

Input: the demo head script (``HeadScript``: nod, shake, turn, run, sharp stop) published at
100 Hz for ``--seconds`` s, stored as ``ros2 bag record -s mcap`` would (``/head_pose``,
``geometry_msgs/msg/PoseStamped``). Scenes: ``config/ponytail.yaml`` with 1 chain of 20
segments, and 4 chains of 20 segments; node rate 120 Hz, RK4 at 1/240 s, markers (capsules) at
30 Hz -- the node's defaults.

Reported per scene:

* ``replay``: ``ponytail_replay`` end to end (read, simulate, build and serialise the messages,
  write the output file): simulated s per wall s and ticks per wall s;
* ``simulation only``: the same ``ChainRunner`` pushes and ticks without messages or output
  (the physics' share); the difference is the cost of the messages and the recording;
* the same per CPU second (``time.process_time``, all threads of this process): on a machine
  shared with other work the wall-time figures drop, the CPU-time ones much less.

Times are best of ``--repeat`` runs (default 1: the replay itself is long enough to average
out).
"""
import argparse
import sys
import tempfile
import time
from pathlib import Path

import yaml

from ponytail_ros.bench.head_bag import INPUT_RATE, make_head_recording

__all__ = ['main', 'bench_scene']

NODE_RATE = 120.0


def scene_params(n_chains, n_segments=20):
    """Node parameters (params-file tree) for ``n_chains`` chains of ``n_segments``."""
    from ponytail_ros.resources import config_path
    tree = yaml.safe_load(config_path('ponytail.yaml').read_text())
    params = tree['/**']['ros__parameters']
    base = dict(params.pop('ponytail'))
    base['n_segments'] = n_segments
    names = ['ponytail'] if n_chains == 1 else [f'strand{i}' for i in range(n_chains)]
    params['chains'] = names
    params['rate'] = NODE_RATE
    for i, name in enumerate(names):
        chain = dict(base)
        chain['attach'] = [-0.09, 0.03 * (i - (n_chains - 1) / 2), 0.06]
        params[name] = chain
    return tree


def simulation_only(head_path, values):
    """Wall time of the runner alone over the input (pushes and nominal ticks)."""
    from ponytail_ros.app.param_values import scene_and_settings
    from ponytail_ros.app.runner import ChainRunner
    from ponytail_ros.recording.bag import BagReader
    _, scene, settings = scene_and_settings(values)
    samples = []
    for _, _, m, log_ns in BagReader(head_path).messages('/head_pose'):
        p, q = m.pose.position, m.pose.orientation
        samples.append((log_ns, m.header.stamp.sec + m.header.stamp.nanosec * 1e-9,
                        (p.x, p.y, p.z), (q.x, q.y, q.z, q.w), m.header.frame_id))
    runner = ChainRunner(scene, settings)
    period = int(round(1e9 / values['rate']))
    wall0, cpu0 = time.perf_counter(), time.process_time()
    next_tick = samples[0][0] + period
    ticks = 0
    for log_ns, t, p, q, frame in samples:
        while next_tick < log_ns:
            runner.tick(next_tick * 1e-9)
            next_tick += period
            ticks += 1
        runner.push(t, p, q, frame)
    return time.perf_counter() - wall0, time.process_time() - cpu0


def bench_scene(tmp, head_path, n_chains, repeat=1):
    from ponytail_ros.app.param_values import complete_values, values_from_params_file
    from ponytail_ros.recording.offline import replay
    params_path = Path(tmp) / f'params_{n_chains}.yaml'
    params_path.write_text(yaml.safe_dump(scene_params(n_chains)))
    best = None
    for _ in range(repeat):
        result = replay(head_path, Path(tmp) / f'out_{n_chains}.mcap', params_file=params_path,
                        overwrite=True)
        if best is None or result.wall_seconds < best.wall_seconds:
            best = result
    values = complete_values(values_from_params_file(params_path))
    sim = [simulation_only(head_path, values) for _ in range(repeat)]
    return best, min(w for w, _ in sim), min(c for _, c in sim)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seconds', type=float, default=20.0, help='simulated seconds of input')
    parser.add_argument('--quick', action='store_true', help='5 s of input')
    parser.add_argument('--repeat', type=int, default=1)
    args = parser.parse_args(argv)
    seconds = 5.0 if args.quick else args.seconds
    with tempfile.TemporaryDirectory() as tmp:
        head = make_head_recording(Path(tmp) / 'head.mcap', seconds)
        print(f'Replay throughput: {seconds:g} s of head input at {INPUT_RATE:g} Hz, node rate '
              f'{NODE_RATE:g} Hz, RK4 1/240 s, markers capsules 30 Hz')
        print(f'{"":<22}{"":>6}{"---------- replay ----------":>30}'
              f'{"-- simulation only --":>24}')
        print(f'{"scene":<22}{"ticks":>6}{"wall s":>8}{"sim s/wall s":>13}{"sim s/CPU s":>12}'
              f'{"sim s/wall s":>13}{"sim s/CPU s":>12}')
        rows = []
        for n_chains in (1, 4):
            result, sim_wall, sim_cpu = bench_scene(tmp, head, n_chains, args.repeat)
            label = f'{n_chains} chain{"s" if n_chains > 1 else ""} x 20 segments'
            sim_s = result.sim_seconds
            speed = sim_s / result.wall_seconds
            print(f'{label:<22}{result.ticks:>6}{result.wall_seconds:>8.2f}{speed:>13.2f}'
                  f'{sim_s / result.cpu_seconds:>12.2f}{sim_s / sim_wall:>13.2f}'
                  f'{sim_s / sim_cpu:>12.2f}')
            rows.append((n_chains, speed))
        sys.stdout.flush()
    return rows


if __name__ == '__main__':
    main()
