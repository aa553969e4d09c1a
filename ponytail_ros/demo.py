"""``ponytail_demo``: the product end to end, in one command.

Starts the built-in animation publisher (``ponytail_head_demo``: idle sway, nod, shake, turn, a
run with bob, a sharp stop) and the ponytail node in one process, talking over ROS 2 topics, and
listens to what the node publishes as a user's RViz would. Afterwards it prints a summary
(ticks, joint gaps, how far and fast the tip went in each phase) and writes a picture and, from
the node's own recording of the run (``demo_run.mcap``), an animation (``animation.py``).

With ``--tf`` the head goes over TF instead, as from a character rig: the head demo publishes
its head as the tree world -> base_link -> neck -> head (``output: tf``) and the node reads it
with ``head_frame: head``, ``fixed_frame: world`` (both need ``tf2_msgs``, which the set-up
builds).
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ponytail_ros.resources import config_path

__all__ = ['main', 'run_demo']


#: The node's parameters with ``--tf``: the head from the head demo's TF tree.
TF_NODE_PARAMS = {'head_frame': 'head', 'fixed_frame': 'world'}


def run_demo(duration, config, domain_id=None, record_path=None, tf=False):
    """Run head demo + ponytail node for ``duration`` s of wall time; return the recorded data.
    ``record_path``: the node also records its run there (MCAP; the animation reads it).
    ``tf``: the head over TF (the head demo's ``output: tf``, the node's ``TF_NODE_PARAMS``)
    instead of the ``head_pose`` topic."""
    import rclpy
    from geometry_msgs.msg import PoseArray, PoseStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data

    from ponytail_ros.node import PonytailNode
    from ponytail_ros.ros.head_demo import HeadDemoNode

    ctx = Context()
    init_kw = {} if domain_id is None else {'domain_id': domain_id}
    ros_args = ['--ros-args', '--params-file', str(config)]
    if record_path is not None:
        ros_args += ['-p', f'record_path:={record_path}']
    rclpy.init(args=ros_args, context=ctx, **init_kw)
    poses, heads = [], []
    try:
        # (an empty frame_id, as config/ponytail.yaml gives the head demo, is no TF frame)
        head_params = ([Parameter('output', value='tf'),
                        Parameter('frame_id', value=TF_NODE_PARAMS['fixed_frame'])] if tf else [])
        node_params = [Parameter(k, value=v) for k, v in TF_NODE_PARAMS.items()] if tf else []
        head = HeadDemoNode(context=ctx, parameter_overrides=head_params)
        node = PonytailNode(context=ctx, parameter_overrides=node_params)
        viewer = rclpy.create_node('demo_viewer', context=ctx)
        viewer.create_subscription(
            PoseArray, 'segment_poses',
            lambda m: poses.append((m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec,
                                    [(p.position.x, p.position.y, p.position.z,
                                      p.orientation.x, p.orientation.y, p.orientation.z,
                                      p.orientation.w) for p in m.poses])), 10)
        viewer.create_subscription(
            PoseStamped, 'head_pose',
            lambda m: heads.append((m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec,
                                    (m.pose.position.x, m.pose.position.y, m.pose.position.z))),
            qos_profile_sensor_data)
        executor = SingleThreadedExecutor(context=ctx)
        for n in (head, node, viewer):
            executor.add_node(n)
        end = time.monotonic() + duration
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        # (no simulation when no head pose ever came: main says so)
        sim = node.runner.sim
        lengths = sim.model.length.copy() if sim is not None else np.zeros(0)
        diagnostics = {'resets': {k: v for k, v in node.runner.resets.items() if v},
                       'dropped': dict(node.runner.dropped),
                       'dropped_time': node.runner.dropped_time_total}
        executor.shutdown()
        for n in (head, node, viewer):
            n.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    t = np.array([p[0] for p in poses])
    segs = np.array([p[1] for p in poses])               # (ticks, n, 7)
    return {'t': t - t[0] if t.size else t, 't0': t[0] if t.size else 0.0, 'segments': segs,
            'lengths': lengths, 'head_t': np.array([h[0] for h in heads]),
            'head_p': np.array([h[1] for h in heads]), **diagnostics}


def chain_points(segments, lengths):
    """Joint points ``(ticks, n + 1, 3)``: each segment's origin, then the last one's far end."""
    from ponytail_ros.core.rotations import quat_axis_x
    origins = segments[..., :3]
    tip = origins[:, -1] + lengths[-1] * quat_axis_x(segments[:, -1, 3:])
    return np.concatenate([origins, tip[:, None]], axis=1)


def summarize(data):
    from ponytail_ros.app.head_script import PHASES
    from ponytail_ros.core.rotations import quat_axis_x
    segs, lengths = data['segments'], data['lengths']
    distal = segs[..., :3] + lengths[None, :, None] * quat_axis_x(segs[..., 3:])
    gap = (np.linalg.norm(distal[:, :-1] - segs[:, 1:, :3], axis=2).max() if segs.shape[1] > 1
           else 0)
    pts = chain_points(segs, lengths)
    t = data['t']
    tip_v = np.linalg.norm(np.diff(pts[:, -1], axis=0), axis=1) / np.maximum(np.diff(t), 1e-9)
    lines = [f'ticks published: {len(t)} over {t[-1]:.1f} s ({len(t) / max(t[-1], 1e-9):.0f} Hz), '
             f'{segs.shape[1]} segments',
             f'largest joint gap in any published PoseArray: {gap:.1e} m',
             f'chain resets: {sum(data["resets"].values())} {data["resets"] or ""}; dropped head '
             f'poses: {sum(data["dropped"].values())}; simulation time dropped (the machine '
             f'could not keep up): {data["dropped_time"]:.2f} s']
    rel = pts[:, -1] - pts[:, 0]
    for name, a, b in PHASES:
        sel = (t >= a) & (t < b)
        if sel.sum() < 2:
            continue
        swing = np.degrees(np.arccos(np.clip(-rel[sel, 2] / np.linalg.norm(rel[sel], axis=1),
                                             -1, 1)))
        lines.append(f'  {name:11s} {a:5.1f}-{b:4.1f} s: tip swings up to {swing.max():5.1f}° '
                     f'from vertical, tip speed up to {tip_v[sel[1:]].max():5.2f} m/s')
    return '\n'.join(lines), gap


def plot(data, path):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    pts = chain_points(data['segments'], data['lengths'])
    t = data['t']
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), gridspec_kw={'width_ratios': [1, 1, 1.6]})
    rel_pts = pts - pts[:, :1]                     # relative to the attachment point
    cmap = plt.get_cmap('viridis')
    for ax, (i, j), view in ((axes[0], (0, 2), 'side (x-z)'), (axes[1], (1, 2), 'front (y-z)')):
        for k in np.linspace(0, len(t) - 1, 60).astype(int):
            ax.plot(rel_pts[k, :, i], rel_pts[k, :, j], '-', color=cmap(t[k] / t[-1]), lw=1.2,
                    alpha=0.7)
        ax.plot([0], [0], 'ko')
        ax.set(xlabel='xyz'[i] + ' (m)', ylabel='z (m)',
               title=f'chain relative to its attachment, {view}\n(colour = time, 60 snapshots)')
        ax.set_aspect('equal')
    ax = axes[2]
    rel = pts[:, -1] - pts[:, 0]
    swing = np.degrees(np.arccos(np.clip(-rel[:, 2] / np.linalg.norm(rel, axis=1), -1, 1)))
    ax.plot(t, swing, color='tab:orange')
    from ponytail_ros.app.head_script import PHASES
    for name, a, b in PHASES:
        if a < t[-1]:
            ax.axvspan(a, min(b, t[-1]), alpha=0.08, color='k')
            ax.text(a, swing.max() * 1.02, name, fontsize=7, rotation=30)
    ax.set(xlabel='time (s)', ylabel='tip swing from vertical (°)', title='the ponytail follows')
    fig.suptitle('ponytail_ros demo: scripted head (ponytail_head_demo) → ponytail_node, '
                 'received over ROS 2 topics')
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _check_args(args, config):
    """What is wrong with the command line (one line naming the option), or None."""
    if not 0.0 < args.duration <= 86400.0:
        return f'--duration {args.duration:g}: must be > 0 and <= 86400 s'
    if not config.is_file():
        return f'--config {config}: no such file'
    if args.tf:
        try:
            import tf2_msgs.msg  # noqa: F401
        except ImportError as err:
            return (f'--tf needs tf2_msgs, which is not importable ({err}); the set-up '
                    f'(pip install -e .[pypi]) builds it when a C++ compiler is there')
    return None


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=20.0, help='wall seconds (default 20)')
    parser.add_argument('--config', default=None, help='parameters file (default ponytail.yaml)')
    parser.add_argument('--out', default='out', help='output folder (default out/)')
    parser.add_argument('--tf', action='store_true',
                        help='the head over TF (world -> base_link -> neck -> head) instead of '
                             'the head_pose topic; needs tf2_msgs')
    parser.epilog = ('Exit status: 0 done, 1 no segment poses received, 2 bad input (one line '
                     'naming it).')
    args = parser.parse_args(argv)

    def error(text):
        print(f'ponytail_demo: error: {text}', file=sys.stderr)
        return 2
    config = Path(args.config) if args.config else config_path('ponytail.yaml')
    problem = _check_args(args, config)
    if problem:
        return error(problem)
    print(f'Running the head demo and ponytail_node for {args.duration:g} s ({config})'
          f'{", the head over TF" if args.tf else ""} ...', flush=True)
    from rclpy.exceptions import ParameterException

    from ponytail_ros.app.parameters import ParameterError
    from ponytail_ros.ros.spin import describe_error
    run_file = _fresh(Path(args.out) / 'demo_run.mcap')
    try:
        data = run_demo(args.duration, config, record_path=run_file, tf=args.tf)
    except (ParameterError, ParameterException) as err:
        return error(f'invalid parameters in {config}: {describe_error(err)}')
    except KeyboardInterrupt:
        return 130
    except Exception as err:  # noqa: BLE001 - rclpy.init refusing the params file (RCLError)
        if type(err).__name__ != 'RCLError':
            raise
        return error(f'cannot start with {config}: {describe_error(err)}')
    if len(data['t']) < 2:
        print('no segment poses were received', file=sys.stderr)
        return 1
    text, _ = summarize(data)
    print(text)
    picture = Path(args.out) / 'demo.png'
    try:
        plot(data, picture)
        print(f'picture: {picture}')
        print(f'animation: {render_animation(run_file, Path(args.out) / "demo.gif")}')
    except ImportError:
        print('matplotlib is not installed (pip install .[plot]); no picture written')
    return 0


def _fresh(path):
    """``path``, emptied for a new recording (the recorder never overwrites a file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.unlink(missing_ok=True)
    return path


def render_animation(run_file, gif):
    """The recorded run as a GIF of the head and its ponytail (``animation.py``)."""
    from ponytail_ros.animation import load_run, render
    return render(load_run(run_file), gif, start=6.0, seconds=8.0)


if __name__ == '__main__':
    sys.exit(main())
