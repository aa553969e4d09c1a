"""``ReplayNode``: the node's behaviour (``app/node_core.py``) on a recording's clock, its output
through a ``TickSink`` (``app/sink.py``), the recorder of the offline replay."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from ponytail_ros.app.messages import ReceivedPose, ReceivedPoses
from ponytail_ros.app.node_core import NodeCore, time_msg
from ponytail_ros.app.parameters import ParameterError
from ponytail_ros.app.sink import HEAD, TickSink

from .inputs import head_pose
from .recorder import HEAD_TYPES, RunRecorder

__all__ = ['ReplayNode']


class ReplayNode:
    """What ``PonytailNode`` does with a head pose, a tick and a parameter change, on the
    recorded clock: the same ``NodeCore`` (``ponytail_ros/app/node_core.py``) with the same
    arguments, its output sent to a ``TickSink`` (``app/sink.py``; here the ``RunRecorder``)
    through the same calls as the node's sinks. Times are integer ns of the recorded clock."""

    def __init__(self, values: Mapping[str, Any], recorder: RunRecorder, head_type: str,
                 frame_types: Sequence[str] = (), zero_stamp_valid: bool = False):
        self.core = NodeCore(values)
        self.runner = self.core.runner
        self._recorder = recorder
        #: Where the output goes (the node's is its recorder and its publishers).
        self.sink: TickSink = recorder
        self._head_type = head_type
        self._frame_types = list(frame_types) or [HEAD_TYPES[0]] * len(self.core.frames)
        self._diag_period_ns = int(round(self.core.values['diagnostics_period'] * 1e9))
        self._diag_next_ns: int | None = None
        self._diag_last_ns: int | None = None
        #: A zero header stamp is a real stamp (a simulator clock starting at 0), not "no
        #: stamp", when the stream has other non-zero stamps.
        self._zero_stamp_valid = zero_stamp_valid

    @property
    def values(self):
        return dict(self.core.values)

    @property
    def published(self):
        return self.core.published

    def head(self, msg, log_time_ns: int) -> None:
        """A recorded head pose at its receive time: a message, or a ``ReceivedPose`` (a
        ``PoseStamped`` read as bytes)."""
        self.sink.on_input(HEAD, msg, log_time_ns)
        stamp, frame_id, p, q = _fields(msg, self._head_type)
        if (self._zero_stamp_valid and stamp.sec == 0 and stamp.nanosec == 0
                and self.core.stamp_source == 'header'):
            # (NodeCore would take "no stamp")
            self.runner.push(self.runner.seconds(0), p, q, frame_id)
            return
        self.core.push_head(stamp, log_time_ns, p, q, frame_id)

    def frame(self, i: int, msg, log_time_ns: int) -> None:
        """A recorded pose of frame ``i`` at its receive time (as ``head``)."""
        self.sink.on_input(i, msg, log_time_ns)
        stamp, frame_id, p, q = _fields(msg, self._frame_types[i])
        self.core.push_frame(i, stamp, log_time_ns, p, q, frame_id)

    def frame_poses(self, msg: ReceivedPoses, log_time_ns: int) -> None:
        """A recorded ``PoseArray`` of every frame's pose (``frames_topic``) at its receive
        time, recorded once and pushed as the node does (``NodeCore.push_frames``)."""
        self.sink.on_input(0, msg, log_time_ns)
        self.core.push_frames(msg.stamp, log_time_ns, msg.poses, msg.frame_id)

    def tick(self, t_ns: int):
        """Tick at ``t_ns``; its ``TickOutput`` (None: nothing to publish yet)."""
        tick = self.core.tick(t_ns)
        if tick is None:
            return None
        self.sink.on_tick(tick, t_ns)
        return tick.output

    def set_parameters(self, changed: Mapping[str, Any], log_time_ns: int) -> None:
        """A recorded live change: checked and applied as the node's parameter callbacks do."""
        changed = self.core.ours(changed)
        if not changed:
            return
        try:
            self.core.check_change(changed)
        except ParameterError:
            return  # the node rejects it too
        self.sink.on_parameters(changed, log_time_ns)
        self.core.apply_change(changed)

    def maybe_diagnostics(self, t_ns: int) -> None:
        """Diagnostics every ``diagnostics_period`` of the recorded clock (the node's timer)."""
        if self._diag_next_ns is None:
            self._diag_next_ns = t_ns + self._diag_period_ns
            self.core.window.t0_ns = t_ns
            return
        if t_ns < self._diag_next_ns:
            return
        self._diag_next_ns += self._diag_period_ns * max(
            1, (t_ns - self._diag_next_ns) // self._diag_period_ns + 1)
        self.sink.on_diagnostics(self.diagnostics_message(t_ns), t_ns)
        self._diag_last_ns = t_ns

    def final_diagnostics(self, t_ns: int) -> None:
        """The last, partial period's diagnostics at the end of the input (the node's last
        period ends when it is stopped; a replay's at its last tick), so that the drop and reset
        counts in the file are the run's totals."""
        if self._diag_next_ns is not None and t_ns != self._diag_last_ns \
                and t_ns > self.core.window.t0_ns:
            self.sink.on_diagnostics(self.diagnostics_message(t_ns), t_ns)
            self._diag_last_ns = t_ns

    def diagnostics_message(self, t_ns: int):
        from diagnostic_msgs.msg import DiagnosticArray
        span = (t_ns - self.core.window.t0_ns) * 1e-9
        status = self.core.diagnostic_status(t_ns, span, self._recorder.layout.node)
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = time_msg(t_ns)
        return msg


def _fields(msg, type_name):
    """``(stamp, frame_id, position, orientation)`` of a pose message or ``ReceivedPose``."""
    if isinstance(msg, ReceivedPose):
        return msg.stamp, msg.frame_id, msg.position, msg.orientation
    p, q = head_pose(msg, type_name)
    return msg.header.stamp, msg.header.frame_id, p, q
