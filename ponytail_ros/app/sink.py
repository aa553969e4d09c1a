"""The one output interface of the tick: what the node publishes and the replay records.

``NodeCore`` turns inputs, ticks, parameter changes and diagnostics periods into messages; where
those messages go is a ``TickSink``. The live node has two: its publishers
(``ros/node.py``) and, with ``record_path``, the recorder (``recording/recorder.py``); the
offline replay has one, the recorder. Every sink sees the same calls with the same messages and
times, so a recording of the node and a replay of it are written by the same code path, and
neither the node nor the replay needs to know the other (the layers: ``core`` <- ``app`` <-
``ros``, ``recording``).

Times are integer ns of the node clock (the recorded clock in a replay): the receive time of an
input, the publishing time of an output.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Protocol

from .node_core import NodeTick

__all__ = ['TickSink', 'Sinks', 'HEAD']

#: ``source`` of :meth:`TickSink.on_input` for the head pose (a frame's is its index).
HEAD: int | None = None


class TickSink(Protocol):
    """Receives everything the node handles or emits, in the order it does."""

    def on_input(self, source: int | None, msg: Any, log_time_ns: int) -> None:
        """An input pose as received (a message, or the node's ``ReceivedPose``: its CDR and
        fields, ``.message()``): ``source`` is ``HEAD`` (None) or the frame's index."""

    def on_tick(self, tick: NodeTick, log_time_ns: int) -> None:
        """One tick's messages (``tick.segments`` per chain: its ``PoseArray`` as CDR bytes,
        ``.cdr``; ``tick.segment_markers``, the ``MarkerArray`` as CDR, or None)."""

    def on_diagnostics(self, msg: Any, log_time_ns: int) -> None:
        """A ``diagnostic_msgs/DiagnosticArray``."""

    def on_parameters(self, changed: Mapping[str, Any], log_time_ns: int) -> None:
        """An accepted live parameter change (name -> new plain value), before it is applied."""

    def close(self) -> None:
        """No more calls follow (finalise a file; idempotent)."""


class Sinks:
    """Several sinks as one, called in order (the recorder before the publishers, so that a
    shutdown between the two never leaves a message received downstream but not recorded)."""

    def __init__(self, sinks: Sequence[TickSink] = ()):
        self.sinks = list(sinks)

    def on_input(self, source: int | None, msg: Any, log_time_ns: int) -> None:
        for s in self.sinks:
            s.on_input(source, msg, log_time_ns)

    def on_tick(self, tick: NodeTick, log_time_ns: int) -> None:
        for s in self.sinks:
            s.on_tick(tick, log_time_ns)

    def on_diagnostics(self, msg: Any, log_time_ns: int) -> None:
        for s in self.sinks:
            s.on_diagnostics(msg, log_time_ns)

    def on_parameters(self, changed: Mapping[str, Any], log_time_ns: int) -> None:
        for s in self.sinks:
            s.on_parameters(changed, log_time_ns)

    def close(self) -> None:
        for s in self.sinks:
            s.close()
