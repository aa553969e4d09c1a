"""``ponytail_replay compare``: two runs of the same chains, tip against tip, at the same stamps
(or the nearest within half a tick), as RMS / max / final distance; ``--plot`` draws them."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ponytail_ros.app.param_values import values_from_metadata
from ponytail_ros.app.parameters import ParameterError

from .bag import PARAMETERS_METADATA, BagError, BagReader
from .inputs import ReplayError
from .recorder import RECORDING_METADATA, RunLayout, stamp_ns

__all__ = ['ChainRun', 'ChainComparison', 'load_chain_runs', 'compare', 'format_comparison',
           'plot_comparison']


@dataclass
class ChainRun:
    """One chain of one recording: tick stamps (ns) and tip positions."""

    name: str
    topic: str
    stamps: np.ndarray
    tips: np.ndarray
    length_from: str


@dataclass
class ChainComparison:
    name: str
    matched: int
    only_a: int
    only_b: int
    rms: float
    max: float
    t_max: float
    final: float
    matching: str
    t: np.ndarray
    distance: np.ndarray
    tip_a: np.ndarray
    tip_b: np.ndarray


def load_chain_runs(path) -> tuple[dict[str, ChainRun], dict[str, Any]]:
    """Every chain's tip track in a recording (ours, or any with ``segment_poses`` topics),
    and its parameters (empty if not recorded).

    Raises:
        ReplayError: unreadable, or no ``PoseArray`` topic.
    """
    path = Path(path)
    try:
        reader = BagReader(path)
        topics = reader.topics()
        metadata = reader.metadata()
    except BagError as exc:
        raise ReplayError(str(exc)) from None
    values = _recorded_values(metadata)
    chains = _chain_topics(metadata, topics, values)
    if not chains:
        raise ReplayError(f'{path} has no segment_poses (geometry_msgs/msg/PoseArray) topic')
    lengths = _lengths(chains, values)
    tracks: dict[str, tuple[list, list]] = {t: ([], []) for t in chains.values()}
    try:
        # Only the stamp and the tip of each message are kept (hours of run fit in memory).
        for topic, _, m, _ in reader.messages(list(chains.values())):
            if not m.poses:
                continue
            tip, known = _tip(m, lengths[topic][1])
            if not known:
                lengths[topic] = (lengths[topic][0], None, 'unknown (tip = last joint)')
            tracks[topic][0].append(stamp_ns(m.header.stamp))
            tracks[topic][1].append(tip)
    except BagError as exc:
        raise ReplayError(str(exc)) from None
    runs = {}
    for topic, (stamps, tips) in tracks.items():
        if stamps:
            name, _, length_from = lengths[topic]
            runs[name] = ChainRun(name, topic, np.array(stamps, dtype=np.int64),
                                  np.array(tips), length_from)
    return runs, values


def _lengths(chains: dict[str, str], values) -> dict[str, tuple[str, float | None, str]]:
    """Topic -> (chain, its length or None, where the segment length comes from)."""
    lengths: dict[str, tuple[str, float | None, str]] = {}
    for name, topic in chains.items():
        try:
            lengths[topic] = (name, float(values[f'{name}.length']), 'parameters')
        except (KeyError, TypeError, ValueError):
            lengths[topic] = (name, None, 'joint spacing')
    return lengths


def _recorded_values(metadata) -> dict[str, Any]:
    """The recorded parameters (empty if none, or not readable)."""
    if PARAMETERS_METADATA in metadata:
        try:
            return values_from_metadata(metadata[PARAMETERS_METADATA])
        except ParameterError:
            return {}
    return {}


def _chain_topics(metadata, topics, values) -> dict[str, str]:
    """Chain name -> its ``PoseArray`` topic: the recorded layout's, else every
    ``segment_poses`` topic (``segment_poses/<chain>``; a lone ``segment_poses`` is the
    recorded first chain, else ``ponytail``; another ``PoseArray`` topic is named by itself)."""
    layout = None
    if RECORDING_METADATA in metadata:
        try:
            layout = RunLayout.from_metadata(metadata[RECORDING_METADATA])
        except (KeyError, ValueError):
            layout = None
    if layout is not None:
        return {c: t for c, t in zip(layout.chains, layout.pose_topics, strict=True)
                if t in topics}
    chains: dict[str, str] = {}
    for t in sorted(t for t, ty in topics.items() if ty == 'geometry_msgs/msg/PoseArray'):
        parts = t.strip('/').split('/')
        if parts[-1] == 'segment_poses':
            name = (values.get('chains') or ['ponytail'])[0]
        elif len(parts) > 1 and parts[-2] == 'segment_poses':
            name = parts[-1]
        else:
            name = t
        chains[name] = t
    return chains


def _tip(m, length: float | None) -> tuple[np.ndarray, bool]:
    """The far end of a ``PoseArray``'s last segment, and whether its length was known: from
    the chain's length (``length``), else the last joint spacing, else (one segment) the
    last joint itself. Per message: the segment count may change during a run (a live
    rebuild)."""
    from ponytail_ros.core.rotations import quat_axis_x
    last = m.poses[-1]
    o = np.array([last.position.x, last.position.y, last.position.z])
    q = np.array([last.orientation.x, last.orientation.y, last.orientation.z,
                  last.orientation.w])
    if length is not None:
        seg = length / len(m.poses)
    elif len(m.poses) > 1:
        p = m.poses[-2].position
        seg = float(np.linalg.norm(o - np.array([p.x, p.y, p.z])))
    else:
        return o + quat_axis_x(q) * 0.0, False
    return o + quat_axis_x(q) * seg, True


def _match(sa: np.ndarray, sb: np.ndarray):
    """Indices of matching stamps: exact, or nearest within half a tick if few match exactly."""
    common, ia, ib = np.intersect1d(sa, sb, assume_unique=False, return_indices=True)
    if len(common) >= 0.5 * min(len(sa), len(sb)) or len(sa) < 2 or len(sb) < 2:
        return ia, ib, 'exact stamps'
    tol = 0.5 * float(np.median(np.diff(sa)))
    j = np.clip(np.searchsorted(sb, sa), 1, len(sb) - 1)
    left, right = sb[j - 1], sb[j]
    nearest = np.where(np.abs(sa - left) <= np.abs(right - sa), j - 1, j)
    ok = np.abs(sb[nearest] - sa) <= tol
    return np.nonzero(ok)[0], nearest[ok], f'nearest stamps (within {tol * 1e-6:.2f} ms)'


def compare(path_a, path_b):
    """Per chain tip distances between two runs matched by stamp.

    Returns ``(comparisons, runs_a, runs_b, values_a, values_b)``.
    """
    runs_a, values_a = load_chain_runs(path_a)
    runs_b, values_b = load_chain_runs(path_b)
    pairs = [(n, n) for n in runs_a if n in runs_b]
    if not pairs and len(runs_a) == 1 and len(runs_b) == 1:
        pairs = [(next(iter(runs_a)), next(iter(runs_b)))]
    if not pairs:
        raise ReplayError(f'{path_a} and {path_b} have no chain in common '
                          f'({", ".join(runs_a)} vs {", ".join(runs_b)})')
    out = []
    for na, nb in pairs:
        a, b = runs_a[na], runs_b[nb]
        ia, ib, how = _match(a.stamps, b.stamps)
        d = np.linalg.norm(a.tips[ia] - b.tips[ib], axis=1)
        t = a.stamps[ia]
        t0 = min(a.stamps[0], b.stamps[0])
        name = na if na == nb else f'{na} / {nb}'
        if len(d):
            k = int(np.argmax(d))
            rms, mx, t_max, final = (float(np.sqrt(np.mean(d * d))), float(d[k]),
                                     (t[k] - t0) * 1e-9, float(d[-1]))
        else:
            rms = mx = t_max = final = float('nan')
        out.append(ChainComparison(name, len(d), len(a.stamps) - len(ia), len(b.stamps) - len(ib),
                                   rms, mx, t_max, final, how, (t - t0) * 1e-9, d,
                                   a.tips[ia], b.tips[ib]))
    return out, runs_a, runs_b, values_a, values_b


def format_comparison(path_a, path_b, comparisons, values_a=None, values_b=None) -> str:
    """The comparison as text: the files, the parameters that differ, a table per chain."""
    lines = [f'A: {path_a}', f'B: {path_b}']
    stamps = [(values or {}).get('output_stamp', 'tick') for values in (values_a, values_b)]
    lines.append(f'output stamps: A {stamps[0]}, B {stamps[1]} ' + (
        '(tick: the chain simulated a delay before its stamp, root on the head at the stamp)'
        if 'tick' in stamps else '(the time of each state)'))
    if stamps[0] != stamps[1]:
        lines.append('warning: A and B stamp differently: tips matched by stamp are the chain '
                     'at times a delay apart')
    if values_a and values_b:
        diff = [k for k in sorted(set(values_a) | set(values_b))
                if k not in ('record_path',) and values_a.get(k) != values_b.get(k)]
        if diff:
            lines.append('parameters that differ (A -> B):')
            lines += [f'  {k}: {values_a.get(k, "-")} -> {values_b.get(k, "-")}' for k in diff]
        else:
            lines.append('parameters: identical')
    header = ('chain', 'matched ticks', 'RMS tip dist (mm)', 'max tip dist (mm)', 'at t (s)',
              'final (mm)')
    rows = [(c.name, f'{c.matched}', f'{1e3 * c.rms:.4g}', f'{1e3 * c.max:.4g}',
             f'{c.t_max:.3f}', f'{1e3 * c.final:.4g}') for c in comparisons]
    widths = [max(len(r[i]) for r in [header] + rows) for i in range(len(header))]
    lines.append('  '.join(h.ljust(w) if i == 0 else h.rjust(w)
                           for i, (h, w) in enumerate(zip(header, widths, strict=True))))
    for r in rows:
        lines.append('  '.join(v.ljust(w) if i == 0 else v.rjust(w)
                               for i, (v, w) in enumerate(zip(r, widths, strict=True))))
    for c in comparisons:
        extra = [c.matching]
        if c.only_a or c.only_b:
            extra.append(f'{c.only_a} ticks only in A, {c.only_b} only in B')
        lines.append(f'  {c.name}: {"; ".join(extra)}')
    return '\n'.join(lines)


def plot_comparison(comparisons, out_png, label_a='A', label_b='B') -> Path:
    """Tip distance over time and the tips' height (z) in both runs, one column per chain."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    n = len(comparisons)
    fig, axes = plt.subplots(2, n, figsize=(6 * n, 6), squeeze=False, sharex='col')
    for i, c in enumerate(comparisons):
        ax = axes[0, i]
        ax.plot(c.t, 1e3 * c.distance, lw=1)
        ax.set_title(f'{c.name}: tip distance A-B (RMS {1e3 * c.rms:.3g} mm)')
        ax.set_ylabel('mm')
        ax.grid(alpha=0.3)
        ax = axes[1, i]
        for k, axis in enumerate('xyz'):
            ax.plot(c.t, c.tip_a[:, k], lw=1, label=f'{label_a} {axis}')
            ax.plot(c.t, c.tip_b[:, k], lw=1, ls='--', label=f'{label_b} {axis}')
        ax.set_xlabel('time from start (s)')
        ax.set_ylabel('tip position (m)')
        ax.legend(fontsize=7, ncol=3)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    out_png = Path(out_png)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return out_png
