"""``python benchmarks/output_cost.py``: what a tick's output costs beside the physics.

Runs ``NodeCore`` (what the node and ``ponytail_replay`` run) on a params file under a moving
head for ``--ticks`` ticks at 120 Hz, with the recorder as its sink (the replay's output), and
times, in main-thread CPU (``time.thread_time``, so the writer thread and other processes are
left out): ``NodeCore.tick`` minus the runner's tick and head evaluation (the tick's
messages: poses and markers encoded), and ``RunRecorder.on_tick`` (``/tf`` encoded, the bytes
queued). Prints the means per tick over the ticks after the first 100.
"""
import argparse
import math
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ponytail_ros.app.node_core import NodeCore
from ponytail_ros.recording.recorder import RunLayout, RunRecorder
from ponytail_ros.testing.config import load_config
from ponytail_ros.testing.offline import stamp_msg


def measure(params: str, ticks: int = 2400) -> dict[str, float]:
    """Mean main-thread CPU per tick (s): ``messages`` and ``recorder``."""
    config = load_config(params)
    core = NodeCore(config.values)
    runner = core.runner
    runner_tick, bodies_at = runner.tick, runner.bodies_at
    spent = [0.0]              # runner time within the current NodeCore.tick
    depth = [0]

    def timed(f: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any) -> Any:
            depth[0] += 1
            t0 = time.thread_time()
            try:
                return f(*args)
            finally:
                depth[0] -= 1
                if depth[0] == 0:    # (bodies_at inside runner.tick counted once)
                    spent[0] += time.thread_time() - t0
        return call
    runner.tick = timed(runner_tick)              # type: ignore[method-assign]
    runner.bodies_at = timed(bodies_at)           # type: ignore[method-assign]
    messages, recorder = [], []
    with tempfile.TemporaryDirectory() as tmp:
        rec = RunRecorder(Path(tmp) / 'out.mcap', RunLayout.for_node('/ponytail', core.chains),
                          config.values)
        for k in range(1, ticks + 1):
            t = k / 120
            core.push_head(stamp_msg(t), round(t * 1e9), (0.1 * math.sin(3 * t), 0.0, 1.6),
                           (0.0, 0.0, math.sin(0.4 * t), math.cos(0.4 * t)), 'world')
            spent[0] = 0.0
            t0 = time.thread_time()
            tick = core.tick(round(k * 1e9 / 120))
            t1 = time.thread_time()
            if tick is None:
                continue
            rec.on_tick(tick, round(k * 1e9 / 120))
            t2 = time.thread_time()
            messages.append(t1 - t0 - spent[0])
            recorder.append(t2 - t1)
        rec.close()
    return {'messages': float(np.mean(messages[100:])),
            'recorder': float(np.mean(recorder[100:]))}


def main(argv: Any = None) -> None:
    p = argparse.ArgumentParser(prog='python benchmarks/output_cost.py',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('params', nargs='*', default=['config/ponytail.yaml'])
    p.add_argument('--ticks', type=int, default=2400)
    args = p.parse_args(argv)
    for params in args.params:
        r = measure(params, args.ticks)
        print(f'{params}: per tick, main-thread CPU: messages {1e6 * r["messages"]:.1f} us, '
              f'recorder {1e6 * r["recorder"]:.1f} us, output side '
              f'{1e6 * (r["messages"] + r["recorder"]):.1f} us')


if __name__ == '__main__':
    main()
