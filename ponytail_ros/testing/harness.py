"""The ponytail node in-process, for plain pytest (no launch files): a fresh rclpy ``Context``
of its own, ``PonytailNode`` from a params file plus overrides, a tester node (head pose and
``/clock`` publishers, subscriptions to every output) and one ``SingleThreadedExecutor``.

Isolation. Each harness initialises its own context with automatic discovery **off**
(``ROS_AUTOMATIC_DISCOVERY_RANGE=OFF`` while ``rclpy.init`` reads it; rcl supports OFF,
LOCALHOST, SUBNET and SYSTEM_DEFAULT since Iron): the nodes of one context (one DDS
participant) talk to each other and to nothing else, even on the same machine and ROS domain,
so parallel test runs (two checkouts, CI jobs, pytest-xdist workers) cannot hear each other.
The ROS domain is set too (``domain_id``; default ``ROS_DOMAIN_ID`` if set, else from the
process id). Use ``discovery='LOCALHOST'`` to talk to nodes in other processes of the same
test instead (then give each run its own ``domain_id``).

Sim time (``sim_time=True``, the default): the node runs with ``use_sim_time`` and the harness
drives ``/clock`` itself (:meth:`Harness.run`), tick by tick: tick ``k`` at ``k × P`` (``P`` the
node timer's period, integer ns); before each tick every head pose stamped at or before it is
published and received. Nothing waits on wall time, so a run is deterministic (the same
``PoseArray``s as :func:`ponytail_ros.testing.offline.run_offline`, bit for bit) and as fast as
the machine simulates. ``sim_time=False`` runs the node on the wall clock, for tests of live
behaviour (:meth:`spin_until`, :attr:`head`).

Frames and units as the node's: poses in the head poses' ``frame_id`` (REP 103), m,
quaternions ``(x, y, z, w)``; times s.
"""
from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Pose, PoseArray, PoseStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from rosgraph_msgs.msg import Clock
from visualization_msgs.msg import MarkerArray

from ponytail_ros.app.node_core import NodeCore, NodeTick, time_msg
from ponytail_ros.node import PonytailNode

from .config import Config, load_config
from .motion import HeadInput, PoseSample, head_samples, stamp_ns
from .offline import _frame_samples, n_ticks, stamp_msg, tick_period_ns
from .trace import Trace, TraceBuilder

__all__ = ['Harness', 'HarnessError', 'HarnessTimeout', 'default_domain_id', 'pose_msg',
           'pose_array_msg', 'bag_samples', 'BagSamples', 'diagnostic_values',
           'TIMEOUT_SCALE']

#: Wall-time waits are stretched by this factor (``PONYTAIL_TEST_TIMEOUT_SCALE``, default 4):
#: they only matter when a loaded machine is slow; a passing test never waits for one to
#: expire.
TIMEOUT_SCALE = float(os.environ.get('PONYTAIL_TEST_TIMEOUT_SCALE', '4'))

#: A head motion for the wall-clock stream: wall/node time t (s) -> (position, orientation,
#: frame_id).
HeadStream = Callable[[float], tuple[Sequence[float], Sequence[float], str]]


class HarnessError(RuntimeError):
    """The harness saw something its own node did not publish (cross-talk), or was misused."""


class HarnessTimeout(HarnessError):
    """A wait for the node (a head pose received, a tick, its messages) did not end."""


def default_domain_id() -> int:
    """``ROS_DOMAIN_ID`` if set, else 1 + (process id mod 101) (a valid Fast DDS domain)."""
    env = os.environ.get('ROS_DOMAIN_ID', '').strip()
    return int(env) if env else 1 + os.getpid() % 101


@contextlib.contextmanager
def _env(name: str, value: str | None) -> Iterator[None]:
    old = os.environ.get(name)
    if value is not None:
        os.environ[name] = value
    try:
        yield
    finally:
        if value is not None:
            if old is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = old


def pose_msg(t: float | Time, position: Sequence[float], orientation: Sequence[float],
             frame_id: str = 'world') -> PoseStamped:
    """A ``PoseStamped`` at ``t`` (s, or a ``Time``); ``orientation`` ``(x, y, z, w)``."""
    m = PoseStamped()
    m.header.frame_id = frame_id
    m.header.stamp = t if isinstance(t, Time) else stamp_msg(float(t))
    m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(x) for x in position)
    (m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
     m.pose.orientation.w) = (float(x) for x in orientation)
    return m


def pose_array_msg(t: float | Time, positions: Any, orientations: Any,
                   frame_id: str = 'world') -> PoseArray:
    """A ``PoseArray`` of poses ``positions`` ``(n, 3)`` and ``orientations`` ``(n, 4)`` (x, y,
    z, w) stamped ``t`` (s or a ``Time``): the frames' poses on ``frames_topic``."""
    m = PoseArray()
    m.header.stamp = t if isinstance(t, Time) else stamp_msg(float(t))
    m.header.frame_id = frame_id
    poses = []
    for p, q in zip(np.asarray(positions, float).tolist(), np.asarray(orientations,
                                                                     float).tolist(), strict=True):
        pose = Pose()
        pose.position.x, pose.position.y, pose.position.z = p
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = q
        poses.append(pose)
    m.poses = poses
    return m


class _FramesSample(NamedTuple):
    """Every frame's pose at one stamp: ``t`` s, ``position`` ``(F, 3)`` m, ``orientation``
    ``(F, 4)`` ``(x, y, z, w)``."""

    t: float
    position: np.ndarray
    orientation: np.ndarray


#: A head or frame sample, or the frames' batched one.
_Sample = TypeVar('_Sample', PoseSample, _FramesSample)


def _batched(frames: Sequence[str], per_frame: list[list[PoseSample]]) -> list[_FramesSample]:
    """The frames' samples as one sample per stamp with ``(F, 3)`` / ``(F, 4)`` poses (what a
    ``frames_topic`` publisher sends): every frame needs a sample at every stamp."""
    if not per_frame:
        return []
    stamps = [s.t for s in per_frame[0]]
    for name, rows in zip(frames, per_frame, strict=True):
        if [s.t for s in rows] != stamps:
            raise HarnessError(f'with frames_topic every frame needs a pose at the same stamps '
                               f'(frame {name} differs from frame {frames[0]})')
    return [_FramesSample(t, np.array([rows[k].position for rows in per_frame]),
                          np.array([rows[k].orientation for rows in per_frame]))
            for k, t in enumerate(stamps)]


def _pose_arrays(msg: PoseArray) -> tuple[np.ndarray, np.ndarray]:
    o = np.array([[p.position.x, p.position.y, p.position.z] for p in msg.poses], dtype=float)
    q = np.array([[p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]
                  for p in msg.poses], dtype=float)
    return o.reshape(-1, 3), q.reshape(-1, 4)


def diagnostic_values(msg: DiagnosticArray) -> dict[str, str]:
    """key -> value of the node's status in a ``/diagnostics`` message."""
    return {kv.key: kv.value for kv in msg.status[0].values}


class BagSamples(list[PoseSample]):
    """A bag's head poses as ``PoseSample``s, times in s from its first head pose
    (:attr:`start_ns`, the absolute stamp of ``t = 0``, integer ns)."""

    start_ns: int = 0


def bag_samples(path: str | Path, head_topic: str | None = None) -> BagSamples:
    """The head poses (``PoseStamped`` or ``TransformStamped``) of a rosbag2 bag (a bag folder,
    its ``metadata.yaml``, or a ``.mcap`` / ``.db3`` file), in log-time order, timed by their
    ``header.stamp`` **rebased to the first head pose** (``t = 0``; the absolute stamp of that
    instant in :attr:`BagSamples.start_ns`): what :meth:`Harness.run` and
    :func:`~ponytail_ros.testing.run_offline` take as they are, whose sim time starts at 0.

    Raises:
        ponytail_ros.recording.inputs.ReplayError: not a bag, no head topic (the message names
            the file and the topics recorded), a damaged file.
    """
    from ponytail_ros.recording.inputs import ReplayInput, head_pose
    from ponytail_ros.recording.recorder import stamp_ns as stamp_of
    inp = ReplayInput(path, head_topic)
    out = BagSamples()
    stamps = []
    for _, _, msg, _ in inp.reader.messages({inp.head_topic: inp.head_type}):
        p, q = head_pose(msg, inp.head_type)
        stamps.append(stamp_of(msg.header.stamp))
        out.append(PoseSample(0.0, p, q))
    if stamps:
        out.start_ns = stamps[0]
        out[:] = [s._replace(t=(t - out.start_ns) * 1e-9)
                  for s, t in zip(out, stamps, strict=True)]
    return out


def check_samples_reach(samples: Sequence[PoseSample], end_ns: int, what: str) -> None:
    """A run ending at ``end_ns`` whose head samples all lie after it would tick without a
    head: an error saying so (stamps in another time base, e.g. a bag's absolute stamps),
    never 0 ticks in silence."""
    if samples and all(stamp_ns(s.t) > end_ns for s in samples):
        raise HarnessError(
            f'{what}: all {len(samples)} head samples are stamped after the run\'s end '
            f'(first at t = {samples[0].t:.9g} s, the run ends at t = {end_ns * 1e-9:.9g} s of '
            f'sim time, which starts at 0): absolute stamps? bag_samples() rebases a bag\'s to '
            f'its first pose')


class Harness:
    """``PonytailNode`` and a tester node on a fresh context, one executor.

    Args:
        params: a node params file (``/**: ros__parameters:``), or None (defaults).
        overrides: parameters on top of it (dotted names -> values, as ``-p name:=value``).
        sim_time: drive the node by ``/clock`` (see the module docstring); False: wall clock.
        namespace: the node's namespace (its relative topics follow it).
        domain_id: ROS domain of the context (default :func:`default_domain_id`).
        discovery: ``ROS_AUTOMATIC_DISCOVERY_RANGE`` for this context: ``'OFF'`` (default:
            only this context's nodes talk), ``'LOCALHOST'``, ``'SUBNET'``, or None (leave
            the environment as it is).
        topics: ``PoseArray`` topics to collect (default: the node's, one per chain).
        head_qos: QoS (or depth) of the tester's ``head_pose`` publisher.
        timeout: s of wall time any single wait may take (times ``TIMEOUT_SCALE``).
        node_name: the node's name.
        measure: measure every tick for the ``Trace`` (default: with sim time only, so that
            a wall-clock test's node is not slowed down).

    The configuration is validated first, without ROS (``load_config``): a bad params file
    fails with the parameter named before any node exists.
    """

    def __init__(self, params: str | Path | None = None,
                 overrides: Mapping[str, Any] | None = None, *, sim_time: bool = True,
                 namespace: str | None = None, domain_id: int | None = None,
                 discovery: str | None = 'OFF', topics: Sequence[str] | None = None,
                 head_qos: int | QoSProfile = 10, timeout: float = 10.0,
                 node_name: str = 'ponytail', measure: bool | None = None) -> None:
        self.config: Config = load_config(params, overrides)
        self.sim_time = bool(sim_time)
        self._measure = self.sim_time if measure is None else bool(measure)
        self.timeout = float(timeout)
        self.domain_id = default_domain_id() if domain_id is None else int(domain_id)
        self.context = Context()
        with _env('ROS_AUTOMATIC_DISCOVERY_RANGE', discovery):
            rclpy.init(context=self.context, domain_id=self.domain_id)
        self._closed = False
        self._extra: list[Node] = []
        try:
            self._make_nodes(params, namespace, topics, head_qos, node_name)
        except BaseException:
            rclpy.try_shutdown(context=self.context)
            raise

    def _make_nodes(self, params: str | Path | None, namespace: str | None,
                    topics: Sequence[str] | None, head_qos: int | QoSProfile,
                    node_name: str) -> None:
        cli = ['--ros-args', '--params-file', str(params)] if params is not None else None
        overrides = [Parameter(k, value=v) for k, v in self.config.overrides.items()]
        if self.sim_time:
            overrides.append(Parameter('use_sim_time', value=True))
        kw: dict[str, Any] = {'namespace': namespace} if namespace else {}
        #: The node under test.
        self.node = PonytailNode(node_name, context=self.context, cli_args=cli,
                                 parameter_overrides=overrides, **kw)
        #: The tester node: publishers and subscriptions (in the node's namespace).
        self.tester = rclpy.create_node(node_name + '_tester', context=self.context, **kw)
        self.head_pub = self.tester.create_publisher(PoseStamped, 'head_pose', head_qos)
        self.clock_pub = self.tester.create_publisher(Clock, '/clock', 10)
        #: One publisher per extra kinematic frame (``frames``), on its ``<frame>.topic``; or,
        #: with ``frames_topic``, none and :attr:`frames_pub` (a ``PoseArray`` of all frames).
        batched = bool(self.config.values.get('frames_topic')) and bool(self.config.frames)
        self.frame_pubs = [] if batched else [
            self.tester.create_publisher(PoseStamped, tp, head_qos)
            for tp in self.config.frame_topics]
        self.frames_pub = (self.tester.create_publisher(
            PoseArray, self.config.values['frames_topic'], head_qos) if batched else None)
        topics = list(topics) if topics is not None else self.config.pose_topics
        #: Every ``PoseArray`` received, per topic, in arrival order.
        self.poses: dict[str, list[PoseArray]] = {tp: [] for tp in topics}
        #: Every ``MarkerArray`` received on ``segment_markers``.
        self.markers: list[MarkerArray] = []
        #: Every ``DiagnosticArray`` received on ``/diagnostics``.
        self.diagnostics: list[DiagnosticArray] = []
        for tp in topics:
            self.tester.create_subscription(PoseArray, tp, self.poses[tp].append, 100)
        self.tester.create_subscription(MarkerArray, 'segment_markers', self.markers.append, 100)
        self.tester.create_subscription(DiagnosticArray, '/diagnostics', self.diagnostics.append,
                                        100)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.tester)
        # Instrumentation (in this process, on the node's own objects): what it receives and
        # what every tick publishes, measured with the core's maths.
        core: NodeCore = self.node.core
        self._received = 0
        #: Per published tick: (t_ns, per chain (origins, orientations), markers published).
        self._ticks: list[tuple[int, list[tuple[np.ndarray, np.ndarray]], bool]] = []
        self._tick_calls = 0
        self._last_tick_ns: int | None = None
        self._builder = TraceBuilder(self.config)
        push_head, push_frame, tick = core.push_head, core.push_frame, core.tick
        push_frames = core.push_frames

        def counting_push(*args: Any, **kwargs: Any) -> None:
            self._received += 1
            push_head(*args, **kwargs)

        def counting_push_frame(*args: Any, **kwargs: Any) -> None:
            self._received += 1
            push_frame(*args, **kwargs)

        def measured_tick(t_ns: int) -> NodeTick | None:
            result = tick(t_ns)
            self._tick_calls += 1
            self._last_tick_ns = t_ns
            if result is not None and self._measure:
                self._builder.record(core.runner, result.output, result.frame_id)
                model = core.runner.sim.model
                out = result.output
                arrays = [(out.origins[model.chain_slice(c)].copy(),
                           out.orientations[model.chain_slice(c)].copy())
                          for c in range(model.n_chains)]
                self._ticks.append((t_ns, arrays, result.segment_markers is not None))
            return result
        core.push_head = counting_push  # type: ignore[method-assign]
        def counting_push_frames(*args: Any, **kwargs: Any) -> None:
            self._received += 1
            push_frames(*args, **kwargs)
        core.push_frame = counting_push_frame  # type: ignore[method-assign]
        core.push_frames = counting_push_frames  # type: ignore[method-assign]
        core.tick = measured_tick  # type: ignore[method-assign]
        # Wall-clock head stream (sim_time=False): published at 100 Hz while set.
        self.head: HeadStream | None = None
        self.last_sent: float | None = None
        if not self.sim_time:
            self.tester.create_timer(0.01, self._publish_head)
        self._clock_ns = 0
        self._sent: int = 0
        self._checked: dict[str, int] = {}
        self._wall = 0.0          # s of wall time spent in run()

    # -- wall clock --------------------------------------------------------------------------
    def now(self) -> float:
        """The tester's clock (wall time, or the last ``/clock`` the harness sent), s."""
        if self.sim_time:
            return self._clock_ns * 1e-9
        return self.tester.get_clock().now().nanoseconds * 1e-9

    def _publish_head(self) -> None:
        if self.head is not None and not self.sim_time:
            t = self.now()
            p, q, frame = self.head(t)
            self.head_pub.publish(pose_msg(t, p, q, frame))
            self.last_sent = t

    def add(self, node: Node) -> Node:
        """Spin another node (built on :attr:`context`) in the executor; destroyed on close."""
        self.executor.add_node(node)
        self._extra.append(node)
        return node

    def spin_once(self, timeout: float = 0.005) -> None:
        self.executor.spin_once(timeout_sec=timeout)

    def spin_for(self, seconds: float) -> None:
        """Spin for ``seconds`` of wall time."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.005)

    def spin_until(self, pred: Callable[[], bool], timeout: float = 5.0) -> bool:
        """Spin until ``pred()`` is true (True) or ``timeout × TIMEOUT_SCALE`` s of wall time
        have passed (``pred()``'s last value)."""
        end = time.monotonic() + timeout * TIMEOUT_SCALE
        while time.monotonic() < end:
            if pred():
                return True
            self.executor.spin_once(timeout_sec=0.005)
        return bool(pred())

    def _wait(self, pred: Callable[[], bool], what: str,
              timeout: float | None = None) -> None:
        timeout = self.timeout if timeout is None else float(timeout)
        if not self.spin_until(pred, timeout):
            raise HarnessTimeout(f'timed out after {timeout * TIMEOUT_SCALE:g} s of wall '
                                 f'time waiting for {what}')

    def last_diagnostics(self, since: int = 0, timeout: float | None = None) -> dict[str, str]:
        """Values of the newest ``/diagnostics`` message received after ``since`` of them
        (waits up to ``timeout`` s, default the harness's, times ``TIMEOUT_SCALE``)."""
        self._wait(lambda: len(self.diagnostics) > since, 'a /diagnostics message', timeout)
        return diagnostic_values(self.diagnostics[-1])

    def fresh_diagnostics(self, timeout: float | None = None) -> dict[str, str]:
        """Values of a ``/diagnostics`` message whose whole window started after this call."""
        n = len(self.diagnostics)
        self._wait(lambda: len(self.diagnostics) > n + 1, 'two /diagnostics messages', timeout)
        return diagnostic_values(self.diagnostics[-1])

    # -- sim time ----------------------------------------------------------------------------
    @property
    def ticks(self) -> int:
        """Timer callbacks of the node so far (a tick publishes once the head is known)."""
        return self._tick_calls

    def publish_diagnostics(self) -> dict[str, str]:
        """Make the node publish ``/diagnostics`` now (its window since the last one) and wait
        for it; its values."""
        n = len(self.diagnostics)
        self.node._on_diagnostics()       # the node's own diagnostics callback
        self._wait(lambda: len(self.diagnostics) > n, 'the /diagnostics message')
        return diagnostic_values(self.diagnostics[-1])

    def run(self, head: HeadInput, duration: float, *, input_rate: float = 100.0,
            frame_id: str = 'world', frames: Mapping[str, HeadInput] | None = None) -> Trace:
        """Drive the node by ``/clock`` for ``duration`` s of sim time more, feeding ``head``.

        ``head``: samples (``PoseSample`` / ``(t, position, orientation)``, stamps in s of sim
        time; the ones up to the run's end are sent, each before the first tick at or after
        its stamp), a motion function ``t -> (position, orientation)`` sampled every
        ``1 / input_rate`` s from t = 0, or a bag's samples (:func:`bag_samples`).
        ``frames``: the extra kinematic frames' poses, frame name -> the same kinds of input
        (published on each frame's topic after the head's, as ``run_offline`` pushes them).
        Returns the whole run so far as a ``Trace`` (every message received, each checked to
        be the one this harness's node published at that tick: raises ``HarnessError`` on
        anything else, e.g. cross-talk from another run).
        """
        if not self.sim_time:
            raise HarnessError('run() drives /clock: build the Harness with sim_time=True')
        wall0 = time.perf_counter()
        period = tick_period_ns(self.config.rate)
        k0 = self._clock_ns // period
        end = stamp_ns(self._clock_ns * 1e-9 + duration)
        after = self._clock_ns if self._clock_ns > 0 else -1

        def window(inputs: list[_Sample]) -> list[_Sample]:
            return [s for s in inputs if after < stamp_ns(s.t) <= end]
        given = head_samples(head, end * 1e-9, input_rate)
        if self._sent == 0:
            check_samples_reach(given, end, 'Harness.run')
        feeds: list[tuple[Any, str, list[PoseSample] | list[_FramesSample]]] = [
            (self.head_pub, 'head pose', window(given))]
        per_frame = _frame_samples(self.config, frames, end * 1e-9, input_rate)
        if self.frames_pub is not None:
            feeds.append((self.frames_pub, 'poses of the frames',
                          window(_batched(self.config.frames, per_frame))))
        else:
            for name, pub, samples in zip(self.config.frames, self.frame_pubs, per_frame,
                                          strict=True):
                feeds.append((pub, f'pose of frame {name}', window(samples)))
        nexts = [0] * len(feeds)
        for k in range(k0 + 1, k0 + n_ticks(duration, self.config.rate) + 1):
            t_ns = k * period
            for j, (pub, what, rows) in enumerate(feeds):
                while nexts[j] < len(rows) and stamp_ns(rows[nexts[j]].t) <= t_ns:
                    s = rows[nexts[j]]
                    pub.publish(pose_array_msg(s.t, s.position, s.orientation, frame_id)
                                if isinstance(s, _FramesSample) else
                                pose_msg(s.t, s.position, s.orientation, frame_id))
                    self._sent += 1
                    nexts[j] += 1
                    self._wait(lambda: self._received >= self._sent,
                               f'the node to receive the {what} stamped {s.t:.6f} s')
            self._step_clock(t_ns)
        self._wall += time.perf_counter() - wall0
        return self.trace()

    def _step_clock(self, t_ns: int) -> None:
        n_published = len(self._ticks)
        self._clock_ns = t_ns
        self.clock_pub.publish(Clock(clock=time_msg(t_ns)))
        self._wait(lambda: self._last_tick_ns == t_ns,
                   f'the node to tick at /clock t = {t_ns * 1e-9:.6f} s')
        if len(self._ticks) > n_published:
            self._wait(self._delivered, f'the messages of the tick at t = {t_ns * 1e-9:.6f} s')

    def _delivered(self) -> bool:
        """Every message of every tick received, each equal to what the node published."""
        topics = list(self.poses)
        want_poses = len(self._ticks)
        want_markers = sum(1 for tk in self._ticks if tk[2])
        if any(len(self.poses[tp]) > want_poses for tp in topics) or \
                len(self.markers) > want_markers:
            self._check_content()
        return (all(len(self.poses[tp]) == want_poses for tp in topics)
                and len(self.markers) == want_markers)

    def _check_content(self) -> None:
        """Each received message is the one this harness's node published at that tick (same
        stamp, bit-identical poses): anything else came from elsewhere."""
        topics = list(self.poses)
        marker_stamps = [t_ns for t_ns, _, has in self._ticks if has]
        for c, tp in enumerate(topics):
            got = self.poses[tp]
            for j in range(self._checked.get(tp, 0), len(got)):
                msg = got[j]
                stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                ok = j < len(self._ticks) and stamp == self._ticks[j][0]
                if ok:
                    o, q = _pose_arrays(msg)
                    want_o, want_q = self._ticks[j][1][c]
                    ok = np.array_equal(o, want_o) and np.array_equal(q, want_q)
                if not ok:
                    raise HarnessError(
                        f'received a PoseArray on {tp} (stamp {stamp * 1e-9:.9f} s) that this '
                        f'harness\'s node did not publish as its tick {j + 1}: another run on '
                        f'the same graph?')
            self._checked[tp] = len(got)
        for j, msg in enumerate(self.markers):
            stamps = {m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
                      for m in msg.markers}
            if j >= len(marker_stamps) or stamps != {marker_stamps[j]}:
                raise HarnessError('received a MarkerArray this harness\'s node did not '
                                   f'publish as its marker message {j + 1}: another run?')

    def trace(self) -> Trace:
        """The run so far (sim time): every tick measured, every message received."""
        self._check_content()
        return self._builder.build(self.poses, self.markers, self.diagnostics, self._wall)

    # -- teardown ----------------------------------------------------------------------------
    def close(self) -> None:
        """Destroy the nodes and shut the context down (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.executor.shutdown()
            for n in self._extra:
                n.destroy_node()
            self.node.destroy_node()
            self.tester.destroy_node()
        finally:
            rclpy.try_shutdown(context=self.context)

    def __enter__(self) -> Harness:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
