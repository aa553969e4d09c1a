"""The node's behaviour without ROS: a configuration and a head motion in, a ``Trace`` out.

``run_offline`` drives ``NodeCore`` (what ``PonytailNode`` runs on every callback) on sim time
exactly as :class:`ponytail_ros.testing.harness.Harness` drives the node over ROS: tick ``k``
(``k = 1, 2, ...``) at ``k × P`` with ``P`` the node timer's period in integer ns, every head
sample whose stamp is ``<=`` the tick time delivered before that tick (received at the previous
tick's clock time). The two give the same ``PoseArray``s bit for bit (a project test checks
it), so a config's unit tests can run here, fast, and the in-process ROS test confirms them.

Does not import rclpy (only the message packages, for the ``PoseArray``/``MarkerArray`` it
builds); needs no ROS graph, no DDS, no sleeping.
"""
from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray

from ponytail_ros.app.node_core import NodeCore, time_msg

from .config import Config, load_config
from .motion import HeadInput, PoseSample, head_samples, stamp_ns
from .trace import Trace, TraceBuilder

__all__ = ['run_offline', 'tick_period_ns', 'n_ticks', 'stamp_msg']


def tick_period_ns(rate: float) -> int:
    """The node timer's period for ``rate`` Hz, integer ns (as rclpy's ``create_timer``)."""
    return int(float(1.0 / rate) * 1e9)


def n_ticks(duration: float, rate: float) -> int:
    """Ticks in ``duration`` s of sim time at ``rate`` Hz: ticks at ``k × P``, ``k >= 1``,
    up to and including ``duration``."""
    return int((stamp_ns(duration) + 1) // tick_period_ns(rate))


def stamp_msg(t: float) -> Time:
    """``builtin_interfaces/Time`` of ``t`` s (rounded to the ns)."""
    return time_msg(stamp_ns(t))


def _frame_samples(config: Config, frames: Mapping[str, HeadInput] | None,
                   duration: float, input_rate: float) -> list[list[PoseSample]]:
    """Per frame of the config (in its order) its samples; a frame not given has none."""
    given = dict(frames or {})
    unknown = sorted(set(given) - set(config.frames))
    if unknown:
        raise ValueError(f'no frame {unknown[0]!r} in this config (frames: {config.frames})')
    return [head_samples(given[f], duration, input_rate) if f in given else []
            for f in config.frames]


def _config(params: Config | str | Path | None,
            overrides: Mapping[str, Any] | None) -> Config:
    if isinstance(params, Config):
        return params.with_overrides(**overrides) if overrides else params
    return load_config(params, overrides)


def run_offline(params: Config | str | Path | None, head: HeadInput, duration: float, *,
                overrides: Mapping[str, Any] | None = None, input_rate: float = 100.0,
                frame_id: str = 'world', keep_markers: bool = False,
                frames: Mapping[str, HeadInput] | None = None) -> Trace:
    """Run the node's core on sim time for ``duration`` s (ticks at ``k / rate``).

    Args:
        params: a params file (``/**: ros__parameters:``), a ``Config``, or None (defaults).
        head: head poses in the world frame ``frame_id``: a list of ``PoseSample`` /
            ``(t, position, orientation)`` (stamps increasing, s of sim time) or a motion
            function ``t -> (position, orientation)`` sampled every ``1 / input_rate`` s from
            ``t = 0`` (see ``ponytail_ros.testing.motion``).
        duration: s of sim time.
        overrides: parameter overrides on top of ``params`` (dotted names).
        input_rate: Hz, for a motion function.
        frame_id: the head poses' ``header.frame_id``.
        frames: poses of the extra kinematic frames (``frames`` parameter: a forearm carrying
            a collider), frame name -> samples or motion as for ``head`` (same world frame).
        keep_markers: keep every ``MarkerArray`` (off by default: building the message
            objects costs about as much as a cheap chain's physics).

    Returns:
        The ``Trace``: every ``PoseArray`` the node would publish (per topic), the
        ``MarkerArray``s if ``keep_markers``, and a ``DiagnosticArray`` every
        ``diagnostics_period`` s of sim time.
    """
    config = _config(params, overrides)
    samples: list[PoseSample] = head_samples(head, duration, input_rate)
    if samples and all(stamp_ns(s.t) > stamp_ns(duration) for s in samples):
        raise ValueError(
            f'run_offline: all {len(samples)} head samples are stamped after the run\'s end '
            f'(first at t = {samples[0].t:.9g} s, the run ends at t = {duration:.9g} s of sim '
            f'time, which starts at 0): absolute stamps? bag_samples() rebases a bag\'s to '
            f'its first pose')
    frame_samples = _frame_samples(config, frames, duration, input_rate)
    frame_next = [0] * len(frame_samples)
    core = NodeCore(config.values)
    builder = TraceBuilder(config)
    topics = config.pose_topics
    poses: dict[str, list[Any]] = {tp: [] for tp in topics}
    markers: list[Any] = []
    diagnostics: list[Any] = []
    period = tick_period_ns(config.rate)
    diag_period = stamp_ns(float(config.values['diagnostics_period']))
    next_diag = diag_period
    i = 0
    last_ns = 0
    wall0 = time.perf_counter()
    for k in range(1, n_ticks(duration, config.rate) + 1):
        t_ns = k * period
        while i < len(samples) and stamp_ns(samples[i].t) <= t_ns:
            s = samples[i]
            core.push_head(stamp_msg(s.t), last_ns, s.position, s.orientation, frame_id)
            i += 1
        for f, fs in enumerate(frame_samples):
            while frame_next[f] < len(fs) and stamp_ns(fs[frame_next[f]].t) <= t_ns:
                s = fs[frame_next[f]]
                core.push_frame(f, stamp_msg(s.t), last_ns, s.position, s.orientation,
                                frame_id)
                frame_next[f] += 1
        tick = core.tick(t_ns)
        last_ns = t_ns
        if tick is not None:
            builder.record(core.runner, tick.output, tick.frame_id)
            # (each tick's messages are its own: built from its bytes when asked for)
            for tp, msg in zip(topics, tick.poses, strict=True):
                poses[tp].append(msg)
            if keep_markers and tick.markers is not None:
                markers.append(tick.markers)
        if t_ns >= next_diag:
            status = core.diagnostic_status(t_ns, diag_period * 1e-9, '/ponytail')
            msg = DiagnosticArray(status=[status])
            msg.header.stamp = time_msg(t_ns)
            diagnostics.append(msg)
            next_diag += diag_period
    return builder.build(poses, markers, diagnostics, time.perf_counter() - wall0)
