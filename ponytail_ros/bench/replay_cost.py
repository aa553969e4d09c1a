"""``python -m ponytail_ros.bench.replay_cost``: ``ponytail_replay`` of a long head bag, timed
as a user runs it: one process, its start (imports, loading the compiled step) included.

The input is the demo head script recorded at 100 Hz for ``--seconds`` s (as ``ros2 bag
record`` stores it, ``head_bag.make_head_recording``); the scene is a params file
(default ``config/ponytail.yaml``). Prints simulated seconds per wall second, then where the
time goes: the process start (the same command on a ``START_INPUT_S`` s input), and, in a
replay of the same input in this process, the compiled step's calls (``ReplayResult.
step_seconds``) and the rest of the loop (Python: head estimation, per-tick bookkeeping,
messages, the output). Start plus compiled step is the bound no saving in Python per tick can
beat.
"""
import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .head_bag import make_head_recording

#: The input of the process-start measurement, s: a few ticks, so that the start (imports,
#: loading the compiled step, opening the files) is what is timed.
START_INPUT_S = 0.1


def timed_replay(head, out, params):
    """Wall time of ``ponytail_replay head -o out --params params --quiet`` in a new process,
    s."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, '-c', 'import sys; from ponytail_ros.recording.cli '
                    'import main; sys.exit(main())', str(head), '-o', str(out),
                    '--params', str(params), '--quiet', '--overwrite'], check=True)
    return time.perf_counter() - t0


def measure(params, seconds, breakdown=True):
    """The replay's wall time (s); with ``breakdown``, also ``start_s`` (the process start),
    and of an in-process replay of the same input ``loop_s`` (its wall time) and ``step_s``
    (its compiled step's), as a dict."""
    with tempfile.TemporaryDirectory() as tmp:
        head = Path(tmp) / 'head.mcap'
        make_head_recording(head, seconds)
        out = Path(tmp) / 'out.mcap'
        wall = timed_replay(head, out, params)
        if not breakdown:
            return wall, {}
        short = make_head_recording(Path(tmp) / 'start.mcap', START_INPUT_S)
        start = timed_replay(short, out, params)
        from ponytail_ros.core.compile import report_compile
        from ponytail_ros.recording.offline import replay
        report_compile(lambda text: None)   # loaded before, as the command does (the start)
        result = replay(head, out, params_file=params, overwrite=True)
    return wall, dict(start_s=start, loop_s=result.wall_seconds, step_s=result.step_seconds,
                      ticks=result.ticks)


def main(argv=None):
    p = argparse.ArgumentParser(prog='python -m ponytail_ros.bench.replay_cost',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--params', default='config/ponytail.yaml')
    p.add_argument('--seconds', type=float, default=300.0, help='simulated seconds of input')
    p.add_argument('--no-breakdown', action='store_true',
                   help='the replay alone, not where its time goes')
    p.add_argument('--json', help='write the result to this file')
    args = p.parse_args(argv)
    wall, parts = measure(args.params, args.seconds, breakdown=not args.no_breakdown)
    row = dict(params=args.params, simulated_s=args.seconds, wall_s=wall,
               speed=args.seconds / wall, **parts)
    print(f'{args.params}: {args.seconds:g} s of head poses replayed in {wall:.1f} s of wall '
          f'time, process start included: {args.seconds / wall:.1f}x real time')
    if parts:
        ticks = max(parts['ticks'], 1)
        rest = parts['loop_s'] - parts['step_s']
        bound = args.seconds / (parts['start_s'] + parts['step_s'])
        row.update(python_s=rest, bound_speed=bound)
        print(f'  process start {parts["start_s"]:.2f} s (the same command on a '
              f'{START_INPUT_S:g} s input); in-process replay {parts["loop_s"]:.2f} s: the '
              f'compiled step {parts["step_s"]:.2f} s ({1e6 * parts["step_s"] / ticks:.0f} µs '
              f'a tick), the rest {rest:.2f} s ({1e6 * rest / ticks:.0f} µs a tick, '
              f'{parts["ticks"]} ticks)')
        print(f'  bound with nothing but the start and the compiled step: {bound:.0f}x real '
              f'time')
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(row, f, indent=1)


if __name__ == '__main__':
    main()
