"""Assertions on a ``Trace`` for a user's own character: each raises ``CheckFailed`` (an
``AssertionError``, so pytest reports it as a test failure) whose message names the quantity,
its worst value, the bound, where (chain, segment or joint, collider) and when (tick time).

Every check judges ticks from ``since`` (s of sim time, default: the first tick) on. Why one
may need it: after a reset (the first tick, a teleport) the chain is published once or twice in
the reset pose — hanging straight along gravity, through a collider it is rooted on — before
the first internal steps push it out.

Units SI; positions in the head poses' frame (REP 103); angles rad; energy J. Does not import
rclpy.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from .trace import Trace

__all__ = ['CheckFailed', 'joint_gaps', 'assert_joints_closed', 'assert_no_penetration',
           'assert_within_joint_limits', 'tip_distance', 'assert_tips_close',
           'assert_energy_does_not_grow', 'assert_no_resets', 'max_penetration']


class CheckFailed(AssertionError):
    """A physical check failed; ``str()`` is the readable reason."""


def _window(trace: Trace, since: float | None) -> np.ndarray:
    """Indices of the ticks judged."""
    if trace.n_ticks == 0:
        raise CheckFailed('the run has no published tick: nothing to check (no head pose '
                          'reached the node?)')
    idx = np.arange(trace.n_ticks) if since is None else np.flatnonzero(trace.t >= since - 1e-12)
    if idx.size == 0:
        raise CheckFailed(f'no tick at or after since = {since} s (last tick at '
                          f't = {trace.t[-1]:.3f} s)')
    return idx


def _segment_name(trace: Trace, i: int) -> tuple[str, int]:
    """(chain, 1-based segment number) of row ``i``."""
    for c in trace.chains:
        sl = trace.segments(c)
        if sl.start <= i < sl.stop:
            return c, i - sl.start + 1
    raise IndexError(i)  # pragma: no cover - rows always belong to a chain


def _over(values: np.ndarray, bound: float) -> int:
    return int(np.count_nonzero(np.any(values.reshape(values.shape[0], -1) > bound, axis=1)))


def _first_over(trace: Trace, idx: np.ndarray, values: np.ndarray, bound: float) -> str:
    """'; first over the bound at t = ... s' (ticks ``idx``, values ``(len(idx), ...)``)."""
    over = np.flatnonzero(np.any(values.reshape(values.shape[0], -1) > bound, axis=1))
    return f'; first over at t = {trace.t[idx[over[0]]]:.3f} s' if over.size else ''


def joint_gaps(trace: Trace) -> np.ndarray:
    """``(T, n)`` distance, m, between the two sides of every joint of the published chains:
    joint 1 of a chain = its root against its attachment point on the head, joint ``j > 1`` =
    segment ``j - 1``'s far end (origin + length along its +X) against segment ``j``'s origin.
    A rigid, unstretched chain has all of them at rounding level."""
    distal = trace.distal()
    gaps = np.empty(trace.origins.shape[:2])
    for i, c in enumerate(trace.chains):
        sl = trace.segments(c)
        gaps[:, sl.start] = np.linalg.norm(trace.origins[:, sl.start] - trace.anchors[:, i],
                                           axis=1)
        gaps[:, sl.start + 1:sl.stop] = np.linalg.norm(
            distal[:, sl.start:sl.stop - 1] - trace.origins[:, sl.start + 1:sl.stop], axis=2)
    return gaps


def assert_joints_closed(trace: Trace, tolerance: float = 1e-6,
                         since: float | None = None) -> float:
    """Every joint of every published chain closed within ``tolerance`` m (no stretch, no
    segment drifting off its neighbour, the root on the head); returns the largest gap, m."""
    idx = _window(trace, since)
    gaps = joint_gaps(trace)[idx]
    k, j = np.unravel_index(int(np.argmax(gaps)), gaps.shape)
    worst = float(gaps[k, j])
    if not worst <= tolerance:
        chain, seg = _segment_name(trace, int(j))
        where = ('root against its attachment point' if seg == 1
                 else f'between segments {seg - 1} and {seg}')
        raise CheckFailed(
            f'joint gap {worst:.3g} m > tolerance {tolerance:g} m: chain {chain!r}, joint {seg} '
            f'({where}), at {trace.where(int(idx[k]))}; {_over(gaps, tolerance)} of '
            f'{idx.size} ticks over the tolerance{_first_over(trace, idx, gaps, tolerance)}')
    return worst


def max_penetration(trace: Trace, since: float | None = None) -> float:
    """The deepest penetration of any segment into any collider over the judged ticks, m
    (<= 0: never touching; -inf: nothing collides)."""
    idx = _window(trace, since)
    if trace.depth.shape[2] == 0:
        return -np.inf
    return float(np.max(trace.depth[idx]))


def assert_no_penetration(trace: Trace, max_depth: float = 1e-3,
                          since: float | None = None,
                          colliders: Sequence[str] | None = None) -> float:
    """No segment (a capsule of the chain's radius along its whole length) deeper than
    ``max_depth`` m inside any collider of the scene (or of ``colliders``, by name), each
    placed on the head as the node estimated it for the published instant; returns the
    deepest penetration, m.

    The whole segment counts: a chain rooted on a collider (hair on a scalp) is held out by
    the solver on its first segment's outer half, and its inner half dips by up to the sag of
    a chord of half its length, (l/2)^2 / (8 (R + r)) (0.2 mm for ``config/ponytail.yaml``):
    choose ``max_depth`` above that.
    """
    idx = _window(trace, since)
    names = trace.colliders
    cols = list(range(len(names))) if colliders is None else [names.index(c) for c in colliders]
    if not cols:
        raise CheckFailed('the scene has no colliders: nothing to check penetration against')
    depth = trace.depth[idx][:, :, cols]
    k, i, j = np.unravel_index(int(np.argmax(depth)), depth.shape)
    worst = float(depth[k, i, j])
    if worst > max_depth:
        chain, seg = _segment_name(trace, int(i))
        raise CheckFailed(
            f'penetration depth {worst:.3g} m > max_depth {max_depth:g} m: chain {chain!r} '
            f'segment {seg} inside collider {names[cols[j]]!r} at {trace.where(int(idx[k]))}; '
            f'{_over(depth, max_depth)} of {idx.size} ticks over the bound'
            f'{_first_over(trace, idx, depth, max_depth)}')
    return worst


def assert_within_joint_limits(trace: Trace, tolerance: float = 2e-5,
                               since: float | None = None) -> float:
    """Every swing (cone) and twist angle within its limit (``swing_limit(s)``,
    ``twist_limit(s)``) plus ``tolerance`` rad; returns the largest excess, rad (<= 0:
    within). Joints without a limit are not judged."""
    idx = _window(trace, since)
    model_limits = _limits(trace)
    worst_value = -np.inf
    worst: tuple[str, int, int, float, float, int] | None = None
    for kind, angles, limit in (('swing', trace.swing[idx], model_limits[0]),
                                ('twist', np.abs(trace.twist[idx]), model_limits[1])):
        on = np.isfinite(limit)
        if not np.any(on):
            continue
        excess = np.where(on[None], angles - np.where(on, limit, 0.0)[None], -np.inf)
        k, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
        if excess[k, j] > worst_value:
            worst_value = float(excess[k, j])
            worst = (kind, int(k), int(j), float(angles[k, j]), float(limit[j]),
                     _over(excess, tolerance))
    if worst is None:
        raise CheckFailed('no joint of this scene has a swing or twist limit: nothing to check')
    if worst_value > tolerance:
        kind, tick, joint, angle, bound, n_over = worst
        chain, seg = _segment_name(trace, joint)
        raise CheckFailed(
            f'{kind} angle {angle:.4g} rad exceeds its limit {bound:.4g} rad by '
            f'{worst_value:.3g} rad > tolerance {tolerance:g} rad: chain {chain!r} joint {seg} '
            f'at {trace.where(int(idx[tick]))}; {n_over} of {idx.size} ticks over')
    return worst_value


def _limits(trace: Trace) -> tuple[np.ndarray, np.ndarray]:
    swing, twist = [], []
    for c in trace.config.scene.chains:
        swing.append(c.joint_limits('swing_limit'))
        twist.append(c.joint_limits('twist_limit'))
    return np.concatenate(swing), np.concatenate(twist)


def tip_distance(a: Trace, b: Trace, chain: str | None = None) -> np.ndarray:
    """``(T,)`` distance, m, between ``chain``'s tip (its last segment's far end) in two runs
    at the same tick times (both runs must have ticked at the same instants)."""
    if a.n_ticks != b.n_ticks or not np.array_equal(a.t, b.t):
        raise CheckFailed(f'the two runs did not tick at the same instants ({a.n_ticks} ticks '
                          f'over {a.duration:.3f} s vs {b.n_ticks} over {b.duration:.3f} s): '
                          f'run them for the same duration at the same rate')
    return np.linalg.norm(a.tips(chain) - b.tips(chain), axis=1)


def assert_tips_close(a: Trace, b: Trace, max_distance: float, rms: float | None = None,
                      chain: str | None = None, since: float | None = None) -> float:
    """The tip trajectories of two runs (a tuning change, a replayed take against its
    reference) within ``max_distance`` m at every judged tick, and their RMS distance within
    ``rms`` m if given; returns the largest distance, m."""
    d = tip_distance(a, b, chain)
    idx = _window(a, since)
    d = d[idx]
    name = chain or a.chains[0]
    k = int(np.argmax(d))
    if not d[k] <= max_distance:
        raise CheckFailed(
            f'tip distance {d[k]:.3g} m > max_distance {max_distance:g} m: chain {name!r} at '
            f'{a.where(int(idx[k]))}; {int(np.count_nonzero(d > max_distance))} of {idx.size} '
            f'ticks over (RMS {float(np.sqrt(np.mean(d ** 2))):.3g} m)')
    r = float(np.sqrt(np.mean(d ** 2)))
    if rms is not None and not r <= rms:
        raise CheckFailed(f'tip distance RMS {r:.3g} m > rms {rms:g} m: chain {name!r} over '
                          f't = {a.t[idx[0]]:.3f} .. {a.t[idx[-1]]:.3f} s (max {d[k]:.3g} m at '
                          f'{a.where(int(idx[k]))})')
    return float(d[k])


def assert_energy_does_not_grow(trace: Trace, tolerance: float = 1e-6,
                                since: float | None = None,
                                chains: Iterable[str] | None = None) -> float:
    """On a head held still from ``since`` on, no chain's energy (kinetic + gravitational,
    J) ever rises more than ``tolerance`` J above the lowest value it had before: damping,
    drag, contacts and limits only take energy out. Returns the largest rise, J."""
    idx = _window(trace, since)
    worst, where = -np.inf, None
    for c in (chains or trace.chains):
        e = trace.energy(c)[idx]
        rise = e - np.minimum.accumulate(e)
        k = int(np.argmax(rise))
        if rise[k] > worst:
            low = int(np.argmin(e[:k + 1]))
            worst, where = float(rise[k]), (c, k, low, float(e[k]), float(e[low]))
    assert where is not None
    if worst > tolerance:
        c, k, low, e_k, e_low = where
        raise CheckFailed(
            f'energy rose by {worst:.3g} J > tolerance {tolerance:g} J on a still head: chain '
            f'{c!r}, from {e_low:.6g} J at {trace.where(int(idx[low]))} to {e_k:.6g} J at '
            f'{trace.where(int(idx[k]))}')
    return worst


def assert_no_resets(trace: Trace, reasons: Iterable[str] | None = None,
                     since: float | None = None) -> None:
    """No reset at rest (``reasons``: only these, e.g. ``['guard']``; default any: guard,
    teleport, frame_changed, clock_backwards, rebuild) from ``since`` on. A guard reset means
    the step was too coarse for the motion (see docs/limits.md)."""
    chosen = None if reasons is None else set(reasons)
    t0 = -np.inf if since is None else since - 1e-12
    bad: list = [r for r in trace.resets if r.t >= t0 and (chosen is None or r.reason in chosen)]
    # A run without a tick fails, like every check here: nothing simulated is not a pass.
    _window(trace, since)
    if bad:
        listed = '; '.join(f'{r.detail} at t = {r.t:.3f} s' for r in bad[:3])
        more = f' (and {len(bad) - 3} more)' if len(bad) > 3 else ''
        raise CheckFailed(f'{len(bad)} reset(s) of the chain at rest, expected none: '
                          f'{listed}{more}')
