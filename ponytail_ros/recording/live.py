"""``ponytail_replay --live``: a recording's head (and frame) poses published into a running
ROS graph at the recorded pace, with ``/clock`` for ``use_sim_time`` nodes."""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from .bag import BagError
from .inputs import ReplayError, ReplayInput
from .recorder import HEAD_TYPES, stamp_ns

__all__ = ['live_replay']


def live_replay(path, *, context=None, head_topic: str | None = None, rate: float = 1.0,
                clock: bool = True, clock_hz: float = 100.0, restamp: bool = False,
                loop: bool = False, wait_for_subscribers: float = 2.0,
                stop: threading.Event | None = None,
                warn: Callable[[str], None] | None = None) -> int:
    """Publish a recording's head poses into the ROS graph at the recorded pace.

    ``rclpy`` must be initialised (``context``: the context to use). Publishes the head topic
    (reliable, depth 10; same type as recorded), the recorded node's frame topics likewise
    (``frames``, in file order with the head poses), and, with ``clock``, ``/clock`` from the
    recorded times (before each pose and at ``clock_hz`` in between), for ``use_sim_time``
    nodes. ``rate`` scales the pace; ``restamp`` rewrites the header stamps with this process's
    clock (for nodes on the system clock); ``loop`` starts again at the end with the times
    shifted forward so the clock never goes back. Waits up to ``wait_for_subscribers`` s for a
    subscriber of the head topic first. Returns the number of head poses published.

    Raises:
        ReplayError: bad input (as the offline replay).
    """
    import rclpy
    from rclpy.publisher import Publisher
    from rclpy.qos import QoSProfile
    from rosgraph_msgs.msg import Clock

    from .bag.msgdefs import _message_class

    warn = warn or (lambda text: None)
    if not rate > 0.0:
        raise ReplayError(f'--rate must be positive, not {rate}')
    inp, topics, samples = _live_input(path, head_topic, warn)
    node = rclpy.create_node('ponytail_replay', context=context)
    try:
        pubs: dict[str, Publisher[Any]] = {
            topic: node.create_publisher(_message_class(type_name), topic, QoSProfile(depth=10))
            for topic, type_name in topics.items()}
        pub = pubs[inp.head_topic]
        clock_pub = node.create_publisher(Clock, '/clock', QoSProfile(depth=10)) if clock else None
        deadline = time.monotonic() + wait_for_subscribers
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        player = _Pacer(node, clock_pub, clock_hz, rate, stop or threading.Event())
        l0 = samples[0][2]
        duration = max(ns for _, _, ns, _ in samples) - l0
        offset = 0
        sent = 0
        while True:
            wall0 = time.monotonic()
            for topic, msg, log_ns, recorded_stamp_ns in samples:
                if not player.wait(wall0, l0, log_ns, offset):
                    return sent
                player.send_clock(offset + log_ns)
                if restamp:
                    msg.header.stamp = node.get_clock().now().to_msg()
                elif offset:
                    msg.header.stamp = _time(recorded_stamp_ns + offset)
                pubs[topic].publish(msg)
                sent += topic == inp.head_topic
            if not loop:
                return sent
            offset += duration + (player.period or 10_000_000)
    finally:
        node.destroy_node()


def _time(ns: int):
    """``builtin_interfaces/Time`` of ``ns``."""
    from builtin_interfaces.msg import Time
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _live_input(path, head_topic, warn):
    """``(input, topic -> type, samples)``: the head topic and the recorded frames' topics,
    every message on them as ``(topic, msg, log_ns, recorded stamp ns)`` in the input's order."""
    inp = ReplayInput(path, head_topic)
    if inp.note:
        warn(inp.note)
    for note in inp.notes:
        warn(note)
    if inp.truncated:
        warn(inp.truncated_warning().replace('replaying', 'playing'))
    topics = {inp.head_topic: inp.head_type}
    if inp.layout is not None:
        topics.update({t: inp.topics[t] for t in inp.layout.frame_topics
                       if inp.topics.get(t) in HEAD_TYPES})
    try:
        samples = [(topic, msg, log_ns, stamp_ns(msg.header.stamp)) for topic, _, msg, log_ns
                   in inp.messages(topics)]
    except BagError as exc:
        raise ReplayError(str(exc)) from None
    if not any(topic == inp.head_topic for topic, *_ in samples):
        raise ReplayError(f'{inp.path}: no message on {inp.head_topic} could be read')
    return inp, topics, samples


class _Pacer:
    """The recorded pace on the wall clock (scaled by ``rate``), with ``/clock`` (when
    ``clock_pub``) at ``clock_hz`` while waiting; never backwards."""

    def __init__(self, node, clock_pub, clock_hz: float, rate: float, stop: threading.Event):
        self.node, self.clock_pub, self.rate, self.stop = node, clock_pub, rate, stop
        self.period = int(1e9 / clock_hz) if clock_hz > 0 else None
        self.clock_ns = -1

    def send_clock(self, ns: int) -> None:
        from rosgraph_msgs.msg import Clock
        if self.clock_pub is None or ns <= self.clock_ns:
            return
        self.clock_ns = ns
        self.clock_pub.publish(Clock(clock=_time(ns)))

    def wait(self, wall0: float, l0: int, log_ns: int, offset: int) -> bool:
        """Until the message logged at ``log_ns`` is due (the pass started at ``wall0``, the
        first message logged at ``l0``); False if stopped or shut down meanwhile."""
        target = wall0 + (log_ns - l0) * 1e-9 / self.rate
        while True:
            now = time.monotonic()
            if self.stop.is_set() or not self.node.context.ok():
                return False
            if now >= target:
                return True
            if self.clock_pub is not None and self.period is not None:
                self.send_clock(offset + min(l0 + int((now - wall0) * self.rate * 1e9), log_ns))
                time.sleep(min(target - now, self.period * 1e-9))
            else:
                time.sleep(min(target - now, 0.05))
