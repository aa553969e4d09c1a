"""A recorded run as a short 3D animation: the head and its chains, drawn from the node's own
recording (``record_path``: the head poses as received and every chain's published
``PoseArray``), read back with the recording reader.

Run: ``python -m ponytail_ros.animation run.mcap -o run.gif [--start 2 --seconds 10]``.
``ponytail_demo`` calls :func:`render` on the run it records. The GIF is written with
matplotlib's ``PillowWriter`` (pillow is a dependency of matplotlib).

Frames (REP 103): positions in the head pose's frame, Z up; the head is drawn as its sphere
collider when it has one fixed in it (else a 9 cm sphere), with a short line along its +X
(the face).
"""
import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np

from ponytail_ros.app.param_values import values_from_metadata
from ponytail_ros.core.rotations import quat_axis_x, quat_rotate
from ponytail_ros.recording.bag import PARAMETERS_METADATA, BagReader
from ponytail_ros.recording.recorder import RECORDING_METADATA, RunLayout

__all__ = ['RecordedRun', 'load_run', 'render', 'main']

#: Head radius drawn when no sphere collider is fixed in the head, m.
DEFAULT_HEAD_RADIUS = 0.09


@dataclass
class RecordedRun:
    """What the animation draws: head poses and each chain's joint points over time.

    ``head_t`` (s, from the first head pose), ``head_p`` (m) and ``head_q`` (x, y, z, w);
    ``chains``: chain name -> (stamps in s on the same clock, one ``(n + 1, 3)`` array of joint
    points per tick in m: each segment's origin, then the last segment's far end);
    ``head_radius`` in m.
    """

    head_t: np.ndarray
    head_p: np.ndarray
    head_q: np.ndarray
    chains: dict[str, tuple]
    head_radius: float


def _stamp(msg) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def _chain_lengths(values: dict, chain: str, n: int) -> np.ndarray:
    lengths = values.get(f'{chain}.segment_lengths') or []
    if len(lengths) == n:
        return np.asarray(lengths, float)
    return np.full(n, float(values.get(f'{chain}.length', 0.5)) / n)


def _head_radius(values: dict) -> float:
    for name in values.get('colliders', []):
        if (values.get(f'{name}.kind') == 'sphere'
                and values.get(f'{name}.frame', 'head') == 'head'):
            return float(values.get(f'{name}.radius', DEFAULT_HEAD_RADIUS))
    return DEFAULT_HEAD_RADIUS


def load_run(path) -> RecordedRun:
    """The head poses and every chain's joint points of a recorded run (an MCAP file)."""
    reader = BagReader(path)
    values = values_from_metadata(reader.metadata().get(PARAMETERS_METADATA, {}))
    layout = RunLayout.from_metadata(reader.metadata()[RECORDING_METADATA])
    head_topic = layout.head_topic
    topics = {head_topic: 'geometry_msgs/msg/PoseStamped'}
    chains: list[str] = list(layout.chains)
    pose_topic = dict(zip(layout.pose_topics, chains, strict=True))
    topics.update({t: 'geometry_msgs/msg/PoseArray' for t in pose_topic})
    head: list[tuple] = []
    seg: dict[str, list[tuple]] = {c: [] for c in chains}
    for topic, _, msg, _ in reader.messages(topics):
        if topic == head_topic:
            p, q = msg.pose.position, msg.pose.orientation
            head.append((_stamp(msg), p.x, p.y, p.z, q.x, q.y, q.z, q.w))
        else:
            seg[pose_topic[topic]].append(
                (_stamp(msg), [(p.position.x, p.position.y, p.position.z, p.orientation.x,
                                p.orientation.y, p.orientation.z, p.orientation.w)
                               for p in msg.poses]))
    if not head:
        raise ValueError(f'{path}: no head poses recorded on {head_topic}')
    h = np.array(head)
    h = h[np.isfinite(h).all(axis=1)]     # (the input as received: the node dropped these)
    if not len(h):
        raise ValueError(f'{path}: no finite head pose recorded on {head_topic}')
    t0 = h[0, 0]
    out = {}
    for c, rows in seg.items():
        if not rows:
            continue
        t = np.array([r[0] for r in rows]) - t0
        points = []
        for _, poses in rows:             # the segment count may change live (a rebuild)
            s = np.array(poses)           # (n, 7)
            tip = s[-1, :3] + _chain_lengths(values, c, len(s))[-1] * quat_axis_x(s[-1, 3:])
            points.append(np.vstack([s[:, :3], tip]))
        out[c] = (t, points)
    return RecordedRun(h[:, 0] - t0, h[:, 1:4], h[:, 4:8], out, _head_radius(values))


def _sphere(radius: float, n: int = 14):
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n), np.linspace(0, np.pi, n // 2 + 1))
    return (radius * np.cos(u) * np.sin(v), radius * np.sin(u) * np.sin(v),
            radius * np.cos(v))


def render(run: RecordedRun, path, start: float = 0.0, seconds: float | None = None,
           fps: float = 15.0, size: float = 3.2, dpi: int = 80) -> Path:
    """Write ``path`` (a GIF): ``seconds`` of the run from ``start`` (s), at ``fps`` frames a
    second of run time, ``size`` inches square at ``dpi``; the view follows the head."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.animation import PillowWriter
    from mpl_toolkits.mplot3d import Axes3D

    end = run.head_t[-1] if seconds is None else min(run.head_t[-1], start + seconds)
    times = np.arange(start, end, 1.0 / fps)
    if times.size == 0:
        raise ValueError(f'no frames between {start:g} s and {end:g} s')
    sx, sy, sz = _sphere(run.head_radius)
    fig = plt.figure(figsize=(size, size), dpi=dpi)
    ax = cast(Axes3D, fig.add_axes((0.0, 0.0, 1.0, 1.0), projection='3d'))
    half = 0.3
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # (matplotlib's stubs say int; a GIF's frame duration, 1000 / fps ms, takes any fps)
    writer = PillowWriter(fps=fps)  # type: ignore[arg-type]
    with writer.saving(fig, str(path), dpi):
        for t in times:
            i = min(np.searchsorted(run.head_t, t), run.head_t.size - 1)
            p, q = run.head_p[i], run.head_q[i]
            ax.cla()
            ax.plot_surface(sx + p[0], sy + p[1], sz + p[2], color='#e8c39e', linewidth=0,
                            alpha=0.55, shade=True)
            nose = p + quat_rotate(q, np.array([run.head_radius * 1.35, 0.0, 0.0]))
            ax.plot(*np.stack([p, nose]).T, color='#8a5a44', lw=2)
            for k, (ct, pts) in enumerate(run.chains.values()):
                j = min(np.searchsorted(ct, t), ct.size - 1)
                ax.plot(*pts[j].T, '-o', color=('#5a3216', '#b88a3c')[k % 2], lw=3, ms=2.5)
            ax.set(xlim=(p[0] - half, p[0] + half), ylim=(p[1] - half, p[1] + half),
                   zlim=(p[2] - 1.5 * half, p[2] + 0.5 * half))
            ax.set_box_aspect((1, 1, 1), zoom=1.35)
            ax.set_axis_off()
            ax.view_init(elev=12, azim=-60)
            ax.text2D(0.04, 0.94, f't = {t:4.1f} s', transform=ax.transAxes, fontsize=8)
            writer.grab_frame()
    plt.close(fig)
    return path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('run', help='a recorded run (.mcap, from record_path)')
    parser.add_argument('-o', '--out', default='run.gif', help='the GIF to write')
    parser.add_argument('--start', type=float, default=0.0, help='s into the run')
    parser.add_argument('--seconds', type=float, default=None, help='length, s (default: all)')
    parser.add_argument('--fps', type=float, default=15.0, help='frames per second of run time')
    args = parser.parse_args(argv)
    print(render(load_run(args.run), args.out, args.start, args.seconds, args.fps))
    return 0


if __name__ == '__main__':
    sys.exit(main())
