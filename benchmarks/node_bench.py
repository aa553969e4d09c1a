"""Benchmark of the ponytail node: tick cost, input-to-output latency, latency vs smoothness.

Run: ``python benchmarks/node_bench.py [--quick] [--part ros|trade|all]``.

``ros`` part (real rclpy + DDS): the node runs in this process with nothing else in its executor
(as in production); a helper child process publishes the head (``HeadScript``, stamped with the
wall clock, at ``--input-rate``) and subscribes to the first chain's ``segment_poses``. At
``rate`` 120 Hz, for 1 and 4 chains of 20 segments (markers on, 30 Hz), it reports:

* tick cost: wall time of the whole timer callback (input checks, estimation, solver, filling
  and publishing the messages), and of the simulation part alone (``ChainRunner.tick``);
* input-to-output latency, per head pose: from its publication (its stamp) to
  - ``published``: the end of the publication of the first tick that consumed it;
  - ``received``: the arrival of that tick's ``PoseArray`` in the helper process.
  Both use the system clock of this machine. This is the transport + waiting-for-the-tick +
  computing latency. On top of it the chain's swing is driven by the head as it was ``delay``
  ago (node defaults: 2 input periods, 8 ms at 250 Hz; the root itself is latency compensated):
  a modelling latency, whose trade against smoothness is the ``trade`` part.

``trade`` part (ROS-free, simulated time, ``ChainRunner`` exactly as in the node): the head
script from 6 s (shake, 90° turn, run with bob, sharp stop at 3 g) sampled at 30/60/120/1000 Hz
with ±20 % stamp jitter, exact or noisy (0.3 mm, 3 mrad per axis), ticks at 120 Hz with ±20 %
jitter. For each ``interpolation_delay`` (0, ½, 1, 2 input periods), RMS errors of what the node
drives the chain with -- the attachment point's position (mm), velocity and acceleration (% of
the RMS true value) at each frame -- against the exact values at the same head time, and the
RMS distance of the chain's root as output (latency compensated) from the attachment point of the
head at the tick time (mm: how far the shown root detaches from the current head), and the
number of blow-up resets of an 8-segment chain (the core resets a chain whose speed or joint gap
explodes; noisy extrapolated accelerations trigger it). A chain-tip comparison against a
reference chain is not shown: after the sharp stop the whipping chain is so sensitive that even
exact 1 kHz input diverges from the reference by centimetres within a second.

The latency of the chain behind the head is ``delay`` plus the node latency of the ``ros`` part.
"""
import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

from ponytail_ros.app.head_script import HeadScript
from ponytail_ros.app.runner import ChainRunner, RunnerSettings
from ponytail_ros.core.rotations import quat_from_rotvec, quat_multiply
from ponytail_ros.core.scene import ChainSpec, Scene

CHAIN = dict(n_segments=20, length=0.4, mass=0.12, radius=0.03, attach=(-0.09, 0.0, 0.06),
             damping=1e-3, drag_linear=0.05)


def _pct(a, q):
    return float(np.percentile(np.asarray(a), q)) if len(a) else float('nan')


# -- the ros part ------------------------------------------------------------------------------

def helper(args):
    """Child process: publish the head, record the arrival of segment_poses; JSON on stdout."""
    import rclpy
    from geometry_msgs.msg import PoseArray, PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    rclpy.init(args=[])
    node = rclpy.create_node('bench_helper')
    pub = node.create_publisher(PoseStamped, 'head_pose', QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE))
    motion = HeadScript()
    arrivals = []
    node.create_subscription(
        PoseArray, args.topic,
        lambda m: arrivals.append((m.header.stamp.sec + m.header.stamp.nanosec * 1e-9,
                                   time.time())), 100)
    msg = PoseStamped()
    msg.header.frame_id = 'world'
    t0 = time.time()
    published = []

    def publish():
        now = time.time()
        p, q = motion.pose(now - t0)
        msg.header.stamp.sec = int(now)
        msg.header.stamp.nanosec = int((now - int(now)) * 1e9)
        (msg.pose.position.x, msg.pose.position.y, msg.pose.position.z) = p.tolist()
        (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
         msg.pose.orientation.w) = q.tolist()
        pub.publish(msg)
        published.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
    node.create_timer(1.0 / args.input_rate, publish)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    end = time.monotonic() + args.duration
    while time.monotonic() < end:
        ex.spin_once(timeout_sec=0.01)
    print(json.dumps({'arrivals': arrivals, 'published': published}))
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()


def _node_parameters(n_chains):
    """(name, value) of the node's parameters: ``n_chains`` copies of ``CHAIN``, side by side."""
    names = [f'c{i}' for i in range(n_chains)]
    params = [('chains', names), ('rate', 120.0)]
    for i, c in enumerate(names):
        for k, v in CHAIN.items():
            v = list(v) if isinstance(v, tuple) else v
            if k == 'attach':
                v = [v[0], 0.05 * (i - (n_chains - 1) / 2), v[2]]
            params.append((f'{c}.{k}', v))
    return params


def ros_case(n_chains, duration, input_rate, domain_id):
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from ponytail_ros.node import PonytailNode

    params = [Parameter(name, value=v) for name, v in _node_parameters(n_chains)]
    topic = 'segment_poses' if n_chains == 1 else 'segment_poses/c0'
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id))
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    node = PonytailNode(context=ctx, parameter_overrides=params)
    ticks = []
    runner_tick = node.runner.tick
    sim_costs = []

    def timed_tick(t):
        a = time.perf_counter()
        out = runner_tick(t)
        if out is not None:
            sim_costs.append(time.perf_counter() - a)
        return out
    node.runner.tick = timed_tick
    # Wall clock (time.time) of the end of the PoseArray publication: perf_counter offset.
    offset = time.time() - time.perf_counter()
    clock = node.runner.clock_seconds           # (runner times are from its origin)
    node.tick_hook = lambda out, w0, w_pub, w_end: ticks.append(
        (clock(out.t), None if out.newest_stamp is None else clock(out.newest_stamp),
         w_end - w0, w_pub + offset))
    child = subprocess.Popen(
        [sys.executable, __file__, '--helper', '--topic', topic,
         '--duration', str(duration + 1.5), '--input-rate', str(input_rate)],
        env=env, stdout=subprocess.PIPE, text=True)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    end = time.monotonic() + duration + 2.0
    while time.monotonic() < end and child.poll() is None:
        ex.spin_once(timeout_sec=0.01)
    out, _ = child.communicate(timeout=30)
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=ctx)
    data = json.loads(out)
    arrivals = dict((round(s, 6), w) for s, w in data['arrivals'])
    published = np.array(data['published'])

    ticks = ticks[len(ticks) // 5:]                 # skip the start-up
    cost = [c for _, _, c, _ in ticks]
    sim = sim_costs[len(sim_costs) // 5:]
    lat_pub, lat_recv = [], []
    prev = None
    for t, newest, _, w_pub in ticks:
        if newest is None or (prev is not None and newest <= prev):
            continue
        if prev is not None:
            # The head poses first consumed by this tick: stamps in (prev, newest]; each was
            # published at its stamp (wall clock).
            stamps = published[(published > prev + 1e-7) & (published <= newest + 1e-7)]
            lat_pub.extend(w_pub - stamps)
            recv = arrivals.get(round(t, 6))
            if recv is not None:
                lat_recv.extend(recv - stamps)
        prev = newest
    return {
        'chains': n_chains, 'ticks': len(ticks),
        'tick_ms': (1e3 * _pct(cost, 50), 1e3 * _pct(cost, 99)),
        'sim_ms': (1e3 * _pct(sim, 50), 1e3 * _pct(sim, 99)),
        'published_ms': (1e3 * _pct(lat_pub, 50), 1e3 * _pct(lat_pub, 99)),
        'received_ms': (1e3 * _pct(lat_recv, 50), 1e3 * _pct(lat_recv, 99)),
        'tick_rate': len(ticks) / max(ticks[-1][0] - ticks[0][0], 1e-9) if ticks else 0.0,
    }


def ros_part(duration, input_rate):
    domain = 1 + (os.getpid() + 50) % 101
    print(f'ROS part: node at 120 Hz, {CHAIN["n_segments"]} segments per chain, head at '
          f'{input_rate:g} Hz from another process, {duration:g} s per case '
          f'(ROS_DOMAIN_ID={domain})')
    print(f"{'chains':>6} {'ticks/s':>8} {'tick ms p50/p99':>16} {'sim ms p50/p99':>16} "
          f"{'published ms p50/p99':>21} {'received ms p50/p99':>20}")
    rows = []
    for n in (1, 4):
        r = ros_case(n, duration, input_rate, domain)
        rows.append(r)
        print(f"{n:6d} {r['tick_rate']:8.1f} {r['tick_ms'][0]:7.2f} /{r['tick_ms'][1]:6.2f} "
              f"{r['sim_ms'][0]:7.2f} /{r['sim_ms'][1]:6.2f} "
              f"{r['published_ms'][0]:10.2f} /{r['published_ms'][1]:8.2f} "
              f"{r['received_ms'][0]:9.2f} /{r['received_ms'][1]:8.2f}", flush=True)
    return rows


# -- the trade part ----------------------------------------------------------------------------

class _ScriptWindow:
    """The head script from 6 s on: shake, 90° turn, run with bob, sharp stop, standing."""

    START = 6.0

    def __init__(self):
        self.script = HeadScript()

    def state_at(self, t):
        return self.script.state_at(t + self.START)


def trade_case(rate, delay, noise, duration, seed=0):
    """Errors of what the node drives the chain with: the attachment point's position, velocity
    and acceleration at each frame against the exact ones at the same head time; and the
    chain's blow-up resets."""
    motion = _ScriptWindow()
    rng = np.random.default_rng(seed)
    scene = Scene(chains=(ChainSpec(name='c', **dict(CHAIN, n_segments=8)),))
    runner = ChainRunner(scene, RunnerSettings(interpolation_delay=delay,
                                               interpolation_delay_periods=0.0))
    ts = np.cumsum((1.0 + 0.2 * rng.uniform(-1, 1, int(duration * rate * 1.3) + 10)) / rate)
    ts = ts[ts < duration]
    tick_ts = np.cumsum((1.0 + 0.2 * rng.uniform(-1, 1, int(duration * 150))) / 120.0)
    tick_ts = tick_ts[(tick_ts > 0.3) & (tick_ts < duration)]
    pos_noise, rot_noise = (3e-4, 3e-3) if noise else (0.0, 0.0)
    i = 0
    err = {'p': [], 'v': [], 'a': [], 'root': []}
    true = {'v': [], 'a': []}
    for t in tick_ts:
        while i < len(ts) and ts[i] <= t:
            s = motion.state_at(ts[i])
            p = s.position[0] + pos_noise * rng.standard_normal(3)
            q = quat_multiply(quat_from_rotvec(rot_noise * rng.standard_normal(3)),
                              s.orientation[0])
            runner.push(ts[i], p, q, 'world')
            i += 1
        out = runner.tick(t)
        if out is None or t < 1.0:
            continue
        got = runner.sim.anchors(runner.estimator.state_at(out.t_head))
        exact = runner.sim.anchors(motion.state_at(out.t_head))
        err['p'].append(np.linalg.norm(got.position - exact.position))
        # The root shown (latency compensated) against the head at the tick time.
        err['root'].append(np.linalg.norm(out.origins[0] - runner.sim.anchors(
            motion.state_at(out.t)).position[0]))
        for k, name in (('v', 'velocity'), ('a', 'acceleration')):
            err[k].append(np.linalg.norm(getattr(got, name) - getattr(exact, name)))
            true[k].append(np.linalg.norm(getattr(exact, name)))
    rms = lambda a: float(np.sqrt(np.mean(np.square(a))))  # noqa: E731
    return {'anchor_mm': 1e3 * rms(err['p']), 'root_mm': 1e3 * rms(err['root']),
            'v_pct': 100 * rms(err['v']) / rms(true['v']),
            'a_pct': 100 * rms(err['a']) / rms(true['a']),
            'guard': runner.resets['guard']}


def trade_part(duration, rates=(30.0, 60.0, 120.0, 1000.0), periods=(0.0, 0.5, 1.0, 2.0)):
    print(f'\nTrade part (simulated time, {duration:g} s of the head script from 6 s: shake, '
          f'turn, run, sharp stop; ticks at 120 Hz ±20 %, inputs ±20 % jitter): latency = '
          f'interpolation_delay')
    rows = []
    for noise in (False, True):
        print('\n' + ('noisy head poses (0.3 mm, 3 mrad per axis)' if noise else
                      'exact head poses'))
        print(f"{'input Hz':>8} {'delay ms':>9} {'pos mm':>7} {'v err %':>8} {'a err %':>8} "
              f"{'root mm':>8} {'blow-up resets':>15}")
        for rate in rates:
            for k in periods:
                d = k / rate
                r = trade_case(rate, d, noise, duration)
                rows.append(dict(r, rate=rate, delay=d, noise=noise))
                print(f"{rate:8.0f} {1e3 * d:9.1f} {r['anchor_mm']:7.2f} {r['v_pct']:8.2f} "
                      f"{r['a_pct']:8.1f} {r['root_mm']:8.2f} {r['guard']:15d}", flush=True)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--quick', action='store_true', help='shorter runs')
    parser.add_argument('--part', choices=('ros', 'trade', 'all'), default='all')
    parser.add_argument('--input-rate', type=float, default=250.0)
    parser.add_argument('--duration', type=float, default=None)
    parser.add_argument('--json', help='write the figures to this file')
    parser.add_argument('--helper', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--topic', default='segment_poses', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.helper:
        return helper(args)
    result = {}
    if args.part in ('ros', 'all'):
        result['ros'] = ros_part(args.duration or (4.0 if args.quick else 10.0),
                                 args.input_rate)
    if args.part in ('trade', 'all'):
        result['trade'] = (trade_part(8.0, rates=(30.0, 120.0), periods=(0.0, 1.0, 2.0))
                           if args.quick else trade_part(8.0))
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(result, f, indent=1)


if __name__ == '__main__':
    main()
