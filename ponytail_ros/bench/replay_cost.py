"""``python -m ponytail_ros.bench.replay_cost``: ``ponytail_replay`` of a long head bag, timed
as a user runs it: one process, its start (imports, loading the compiled step) included.

The input is the demo head script recorded at 100 Hz for ``--seconds`` s (as ``ros2 bag
record`` stores it, ``replay_bench.make_head_recording``); the scene is a params file
(default ``config/ponytail.yaml``). Prints simulated seconds per wall second.
"""
import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .replay_bench import make_head_recording


def measure(params, seconds):
    with tempfile.TemporaryDirectory() as tmp:
        head = Path(tmp) / 'head.mcap'
        make_head_recording(head, seconds)
        out = Path(tmp) / 'out.mcap'
        t0 = time.perf_counter()
        subprocess.run([sys.executable, '-c', 'import sys; from ponytail_ros.recording.cli '
                        'import main; sys.exit(main())', str(head), '-o', str(out),
                        '--params', str(params), '--quiet'], check=True)
        wall = time.perf_counter() - t0
    return wall


def main(argv=None):
    p = argparse.ArgumentParser(prog='python -m ponytail_ros.bench.replay_cost',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--params', default='config/ponytail.yaml')
    p.add_argument('--seconds', type=float, default=300.0, help='simulated seconds of input')
    p.add_argument('--json', help='write the result to this file')
    args = p.parse_args(argv)
    wall = measure(args.params, args.seconds)
    row = dict(params=args.params, simulated_s=args.seconds, wall_s=wall,
               speed=args.seconds / wall)
    print(f'{args.params}: {args.seconds:g} s of head poses replayed in {wall:.1f} s of wall '
          f'time, process start included: {args.seconds / wall:.1f}x real time')
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(row, f, indent=1)


if __name__ == '__main__':
    main()
