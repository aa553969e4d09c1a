"""``python -m ponytail_ros.bench.node_cpu``: what a ponytail node costs beside the head demo.

Starts ``ponytail_head_demo`` (the built-in animation publisher) and ``ponytail_node`` with a
params file as two processes in a private ROS domain, as a user would, lets the node start
(compile or load the step, first poses), then reads the node process's CPU time (user +
system, ``/proc/<pid>/stat``) over ``--seconds`` of wall time: the share of one core it takes.
Also reads the node's ``/diagnostics`` over that time: the tick's wall time, p99 and largest, the
ticks per second and the simulated time dropped, per 1 s window, and the compiled step's
share of a core (its calls' mean wall time a tick times the ticks per s). Prints one line per
run; ``--json`` writes them. With ``--floor``, rclpy's floor plus the compiled step is the
bound no saving in the node's Python can beat.

``--characters N``: each params file's character copied N times into one node
(``app/crowd.py``), the head demo publishing the other characters' heads in one ``PoseArray``
(``frame_poses``): whether a node with N characters keeps its rate on one core.
"""
import argparse
import json
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np

_TICK = os.sysconf('SC_CLK_TCK')

# A listener process: every node's /diagnostics window (1 s each) as one JSON line
# [status name, {key: value}] (``diagnostics_windows`` reads them back).
DIAGNOSTICS_LISTENER = """
import json, rclpy
from diagnostic_msgs.msg import DiagnosticArray
rclpy.init()
node = rclpy.create_node('ponytail_bench_listener')
def on_diagnostics(msg):
    for status in msg.status:
        kv = {v.key: v.value for v in status.values}
        if 'ticks per s' in kv:
            print(json.dumps([status.name, kv]), flush=True)
node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 100)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
    pass
"""


def diagnostics_windows(out: str):
    """``(status name, {key: value})`` of each window the listener printed."""
    return [tuple(json.loads(line)) for line in out.splitlines() if line.startswith('[')]


def _window(kv):
    """[tick p99 ms, tick max ms, ticks per s, dropped s, the compiled step's mean ms]."""
    return [float(kv['tick time p99 (ms)']), float(kv['tick time max (ms)']),
            float(kv['ticks per s']), float(kv['dropped time (s)']),
            float(kv['integrate time mean (ms)']) + float(kv['contact time mean (ms)'])]


def _cpu_seconds(pid):
    with open(f'/proc/{pid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICK       # utime + stime


def measure(params, seconds=15.0, warmup=8.0, extra=(), head_rate=120.0, floor=False,
            characters=1):
    """The node's share of one core (``floor``: of ``rclpy_floor`` instead, ``params``
    unused) and the /diagnostics windows seen; ``characters`` > 1: the head demo publishes
    the other characters' heads on ``frame_poses`` (``params`` must be a crowd's,
    ``app/crowd.py``)."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(random.randint(120, 200)),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    head = subprocess.Popen([sys.executable, '-c', 'from ponytail_ros.ros.head_demo import main; '
                             'main()', '--ros-args', '-p', f'rate:={head_rate}',
                             '-p', f'characters:={characters}'],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    cmd = (['-m', 'ponytail_ros.bench.rclpy_floor'] if floor else
           ['-c', 'from ponytail_ros.node import main; main()', '--ros-args', '--params-file',
            str(params), *extra])
    node = subprocess.Popen([sys.executable, *cmd],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    listener = None
    try:
        time.sleep(warmup)
        if not floor:
            listener = subprocess.Popen(
                [sys.executable, '-c', DIAGNOSTICS_LISTENER], env=env, text=True,
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        c0, t0 = _cpu_seconds(node.pid), time.monotonic()
        time.sleep(seconds)
        c1, t1 = _cpu_seconds(node.pid), time.monotonic()
        if node.poll() is not None:
            raise RuntimeError(f'the node exited: {node.stderr.read().decode()[-2000:]}')
        windows = []
        if listener is not None:
            listener.send_signal(signal.SIGINT)
            out, _ = listener.communicate(timeout=10)
            windows = [_window(kv) for _, kv in diagnostics_windows(out)
                       if 'tick time p99 (ms)' in kv]
        return (c1 - c0) / (t1 - t0), windows
    finally:
        for p in [q for q in (node, head, listener) if q is not None]:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in [q for q in (node, head, listener) if q is not None]:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()


def _step_share(windows):
    """The compiled step's share of a core in the median /diagnostics window (its calls' mean
    wall time a tick, ms, times the window's ticks per s)."""
    shares = [w[4] * 1e-3 * w[2] for w in windows]
    return float(np.median(shares)) if shares else float('nan')


def main(argv=None):
    p = argparse.ArgumentParser(prog='python -m ponytail_ros.bench.node_cpu',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('params', nargs='*', default=['config/ponytail.yaml'])
    p.add_argument('--seconds', type=float, default=15.0, help='measured wall time (s)')
    p.add_argument('--warmup', type=float, default=8.0, help='start-up left out (s)')
    p.add_argument('--json', help='write the results to this file')
    p.add_argument('--floor', action='store_true',
                   help='also measure rclpy_floor: the same ROS traffic with no simulation')
    p.add_argument('--characters', type=int, nargs='+', default=[1],
                   help='crowds of this many copies of each params file\'s character in one '
                        'node (app/crowd.py), the head demo publishing all their heads')
    args = p.parse_args(argv)
    rows = []
    runs = [(params, 1) for params in args.params]
    if args.characters != [1]:
        import tempfile

        from ponytail_ros.app.crowd import crowd_values, params_file_text
        from ponytail_ros.app.param_values import values_from_params_file
        tmp = tempfile.mkdtemp(prefix='node_cpu_')
        runs = []
        for params in args.params:
            for n in args.characters:
                path = os.path.join(tmp, f'crowd{n}_{os.path.basename(params)}')
                with open(path, 'w') as f:
                    f.write(params_file_text(crowd_values(values_from_params_file(params), n),
                                             n, params))
                runs.append((path, n))
    floor = None
    if args.floor:
        share, _ = measure(None, args.seconds, args.warmup, floor=True)
        floor = share
        rows.append(dict(params='rclpy_floor', cpu_share=share, seconds=args.seconds))
        print(f'rclpy_floor (no simulation): {100 * share:.1f} % of one core (same measurement)')
    for params, characters in runs:
        share, windows = measure(params, args.seconds, args.warmup, characters=characters)
        p99 = [w[0] for w in windows]
        rows.append(dict(params=params, characters=characters, cpu_share=share,
                         seconds=args.seconds, tick_p99_ms=p99,
                         tick_max_ms=[w[1] for w in windows],
                         ticks_per_s=[w[2] for w in windows],
                         dropped_time_s=[w[3] for w in windows],
                         step_share=_step_share(windows)))
        print(f'{params}: {100 * share:.1f} % of one core (CPU time over {args.seconds:g} s '
              f'after {args.warmup:g} s of start-up, beside ponytail_head_demo at 120 Hz'
              f'{f", {characters} characters" if characters > 1 else ""})')
        if p99:
            print(f'  tick time p99 per 1 s /diagnostics window: median {np.median(p99):.2f} ms, '
                  f'worst {max(p99):.2f} ms ({len(p99)} windows); largest tick '
                  f'{max(w[1] for w in windows):.2f} ms')
            rates = [w[2] for w in windows]
            print(f'  ticks per s per window: median {np.median(rates):.1f}, lowest '
                  f'{min(rates):.1f}; simulated time dropped by the end: {windows[-1][3]:.3f} s')
            step = _step_share(windows)
            print(f'  the compiled step: {100 * step:.1f} % of one core (its calls\' mean wall '
                  f'time a tick x ticks per s, median window)'
                  + (f'; with rclpy\'s floor: {100 * (floor + step):.1f} %, the least this node '
                     f'could cost with no Python of its own' if floor is not None else ''))
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(rows, f, indent=1)


if __name__ == '__main__':
    main()
