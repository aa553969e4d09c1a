"""The ponytail node: head pose in, segment poses out, on every timer tick.

Run: ``ponytail_node --ros-args --params-file config/ponytail.yaml [-p key:=value]
[-r __ns:=/alice]`` (or ``python -m ponytail_ros.node --ros-args ...``: the node with recording
wired in, ``ponytail_ros/node.py``). Node name ``ponytail``.

Topics (all relative, so a namespace per character scales out; no global state):

* subscribes ``head_pose`` (``geometry_msgs/PoseStamped``), sensor-data QoS (best effort, so
  reliable and best-effort publishers both connect);
* subscribes, per extra kinematic frame named in ``frames``, ``<frame>.topic`` (default
  ``<frame>_pose``; ``geometry_msgs/PoseStamped``, sensor-data QoS): the pose of a body that
  chains can hang from and colliders can be fixed in (a forearm), in the head poses' frame;
  or, with ``frames_topic`` set, that one topic (``geometry_msgs/PoseArray``, sensor-data QoS):
  every frame's pose in one message, ``poses[i]`` that of ``frames[i]`` (many characters);
* publishes ``segment_poses`` (``geometry_msgs/PoseArray``, reliable, depth 10) when there is one
  chain, ``segment_poses/<chain>`` per chain when there are several: one pose per segment, origin
  at the proximal joint, local +X along the segment; ``header.frame_id`` = the head pose's frame
  (or parameter ``frame_id``), ``header.stamp`` = the tick time (node clock);
* publishes ``segment_markers`` (``visualization_msgs/MarkerArray``, reliable, depth 10) at up to
  ``markers.rate``: capsules or line strip + spheres (``markers.style``), one namespace per chain;
* records the run when ``record_path`` is set and the node was given a recorder
  (``recording_sink``; ``ponytail_node`` and ``ponytail_ros.node.PonytailNode`` give it
  ``recording/recorder.py``'s: head input, outputs, parameter changes, parameters in effect;
  replay it with ``ponytail_replay``). This module does not import ``recording/``: the
  recorder is one more ``TickSink`` (``app/sink.py``) next to the publishers;
* publishes ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``, every
  ``diagnostics_period`` s of wall time): one status named ``ponytail: <node FQN>`` with the
  solve time (and its compiled stages' means: integrate, contacts and the latter's rows,
  positions and velocities), joint gap, dropped inputs
  by reason, resets by reason, dropped time, head state and each frame's (``frame <name>``:
  none, stale or ok).
  ``/diagnostics`` is absolute by ROS convention (one aggregator for all characters); the status
  name carries the namespace;
* publishes ``/tf`` (``tf2_msgs/TFMessage``, reliable, volatile, depth 100: tf2's broadcaster
  QoS) when ``tf2_msgs`` is importable (a sourced ROS 2 workspace, or built into the venv; the
  PyPI wheels lack it) and ``tf.publish`` (default true): each segment as the frame
  ``<tf.prefix><chain>/<i>``, child of the outputs' frame (``fixed_frame`` with the head from
  TF), every tick. ``tf.prefix`` defaults to the namespace (``/alice`` -> ``alice/``, so
  ``alice/ponytail/3``; the root namespace -> none). Without ``tf2_msgs`` nothing is published
  and the node says so once at start-up; recordings hold ``/tf`` either way (the same bytes);
* with ``head_frame`` set, subscribes ``/tf`` (reliable, volatile, depth 100) and ``/tf_static``
  (reliable, transient local, depth 100), tf2's listener QoS, instead of ``head_pose``: the head
  pose is ``fixed_frame -> head_frame`` composed along the TF tree at the stamps of the moving
  transforms, interpolated (``app/tf_input.py``); likewise each frame with ``<frame>.tf_frame``.
  Missing frames, extrapolated and stale transforms are counted in ``/diagnostics`` and said on
  the terminal (throttled), naming the frames. It needs ``tf2_msgs`` (refused at start-up
  without it).

Start-up says on the terminal: parameter-file or ``-p`` names that are no parameter of the node
(with the closest known name), ``tf.publish`` without ``tf2_msgs``, another node with the same
name in the same namespace (it doubles every topic; checked for the first 5 s). Live changes
naming no parameter, or of the wrong type, are refused with a reason in words; head stamps on
another clock than the node's are said on the terminal with the fix (``stamp_source:=receive``).

Each tick advances the chains by the clock's elapsed time (``use_sim_time`` and ``/clock`` work;
late or skipped timer periods are caught up, at most ``solver.max_steps_per_call`` steps). The
per-tick logic (input checks, estimation, stepping) is ``ChainRunner`` (``app/runner.py``);
the parameters are in ``app/parameters.py``.

Note: no ``from __future__ import annotations`` here: rclpy passes ``TimerInfo`` to a timer
callback only if the parameter's annotation *is* the class.
"""
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.serialization import deserialize_message
from rclpy.timer import TimerInfo
from visualization_msgs.msg import MarkerArray

from ponytail_ros.app.messages import TF_QOS_DEPTH, TF_TOPIC, ReceivedPose, ReceivedPoses, tf_cdr
from ponytail_ros.app.node_core import OVERLOADED, NodeCore, NodeTick
from ponytail_ros.app.param_values import closest_name, unknown_parameter_warning
from ponytail_ros.app.parameters import (
    CHAIN_PARAMS,
    COLLIDER_PARAMS,
    DEFAULT_COLORS,
    FRAME_PARAMS,
    GLOBAL_PARAMS,
    NODE_PARAMS,
    ParameterError,
    chain_param_name,
    check_names,
    definition,
)
from ponytail_ros.app.sink import HEAD, Sinks
from ponytail_ros.app.tf_input import TF_STATIC_TOPIC
from ponytail_ros.app.wire import tf_message_fields
from ponytail_ros.core.compile import compile_kernels, say_compiles, stages_for
from ponytail_ros.core.stages import CONTACT_STAGES

from .spin import run_node, timer_callback

__all__ = ['PonytailNode', 'main', 'node_help', 'OUTPUT_QOS', 'INPUT_QOS', 'TF_QOS',
           'TF_STATIC_QOS', 'tf_prefix_of']

#: ``head_pose`` and frame subscriptions: the sensor-data preset (best effort, volatile, keep
#: last 5).
INPUT_QOS = qos_profile_sensor_data
#: ``/tf`` in and out: tf2's ``DynamicListenerQoS``/``DynamicBroadcasterQoS``.
TF_QOS = QoSProfile(depth=TF_QOS_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
#: ``/tf_static`` in: tf2's ``StaticListenerQoS`` (late joiners get the latched transforms).
TF_STATIC_QOS = QoSProfile(depth=TF_QOS_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL,
                           history=HistoryPolicy.KEEP_LAST)
#: ``segment_poses`` and ``segment_markers``: reliable, volatile, keep last 10.
OUTPUT_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)

_PARAM_TYPES = {
    'double': Parameter.Type.DOUBLE, 'int': Parameter.Type.INTEGER,
    'bool': Parameter.Type.BOOL, 'string': Parameter.Type.STRING,
    'double3': Parameter.Type.DOUBLE_ARRAY, 'double4': Parameter.Type.DOUBLE_ARRAY,
    'doubles': Parameter.Type.DOUBLE_ARRAY,
    'strings': Parameter.Type.STRING_ARRAY,
}


#: Parameter types in words, for refusals.
_TYPE_WORDS = {
    Parameter.Type.BOOL: 'a bool (true or false)',
    Parameter.Type.INTEGER: 'an integer',
    Parameter.Type.DOUBLE: 'a number (double, e.g. 0.5)',
    Parameter.Type.STRING: 'a string',
    Parameter.Type.BYTE_ARRAY: 'a list of bytes',
    Parameter.Type.BOOL_ARRAY: 'a list of bools',
    Parameter.Type.INTEGER_ARRAY: 'a list of integers',
    Parameter.Type.DOUBLE_ARRAY: 'a list of numbers (doubles, e.g. [0.0, 0.0, -9.81])',
    Parameter.Type.STRING_ARRAY: 'a list of strings',
}


def _descriptor(pdef):
    d = ParameterDescriptor(description=pdef.description,
                            additional_constraints=pdef.constraints(),
                            read_only=not pdef.live)
    d.type = _PARAM_TYPES[pdef.kind].value
    if pdef.kind == 'double' and pdef.lo is not None:
        d.floating_point_range = [FloatingPointRange(from_value=float(pdef.lo),
                                                     to_value=float(pdef.hi), step=0.0)]
    elif pdef.kind == 'int' and pdef.lo is not None:
        d.integer_range = [IntegerRange(from_value=int(pdef.lo), to_value=int(pdef.hi), step=1)]
    return d


def _plain(value):
    """Parameter value as plain Python (lists instead of array.array)."""
    if isinstance(value, (str, bool, int, float)) or value is None:
        return value
    return list(value)


def _coerce(param, kind):
    """An int given for a double (``length: 1``), ints for a double array, an integral double
    for an int: converted, so that params files and ``ros2 param set`` need no ``.0``."""
    t, v = param.type_, param.value
    if kind == 'double' and t == Parameter.Type.INTEGER:
        return Parameter(param.name, Parameter.Type.DOUBLE, float(v))
    if kind in ('double3', 'double4', 'doubles') and t == Parameter.Type.INTEGER_ARRAY:
        return Parameter(param.name, Parameter.Type.DOUBLE_ARRAY, [float(x) for x in v])
    if kind == 'int' and t == Parameter.Type.DOUBLE and float(v).is_integer():
        return Parameter(param.name, Parameter.Type.INTEGER, int(v))
    return param


def tf_prefix_of(namespace: str) -> str:
    """``tf.prefix``'s default: the namespace as a frame prefix (``/alice`` -> ``alice/``,
    ``/a/b`` -> ``a/b/``, ``/`` -> ``''``), so that characters in namespaces never share a
    frame name."""
    ns = namespace.strip('/')
    return f'{ns}/' if ns else ''


class _Input:
    """In place of a subscription for an input taken from TF: its topic name, as the recorder
    records the composed poses on it (a ``PoseStamped`` each)."""

    msg_type = None

    def __init__(self, topic_name):
        self.topic_name = topic_name


def _received(data: bytes):
    """A raw input's ``ReceivedPose``, or its ``PoseStamped`` when the bytes are not plain
    little-endian CDR (``deserialize_message`` handles every case the decoder leaves)."""
    pose = ReceivedPose.decode(data)
    return pose if pose is not None else deserialize_message(data, PoseStamped)


class _Timing:
    """Wall-clock timing between two diagnostics messages (the rest is ``NodeCore``'s)."""

    def __init__(self):
        self.solve = []
        # the compiled step's stages per tick (``StepReport.timings``)
        self.integrate = []
        self.contacts = []
        # the contact stage's parts (``stages.CONTACT_STAGES``): rows, positions, velocities
        self.contact_parts = {name: [] for name in CONTACT_STAGES}
        self.tick_wall = []
        self.lateness = 0.0
        self.wall0 = time.monotonic()

    def add_tick(self, solve, timings):
        """One tick's solve time (s) and its ``StepReport.timings``."""
        self.solve.append(solve)
        self.integrate.append(timings.get('integrate', 0.0))
        self.contacts.append(timings.get('contacts', 0.0))
        for name, v in self.contact_parts.items():
            v.append(timings.get(f'contact_{name}', 0.0))

    def values(self):
        solve = np.array(self.solve) if self.solve else np.zeros(1)
        return {
            'solve time mean (ms)': f'{1e3 * float(np.mean(solve)):.3f}',
            'solve time max (ms)': f'{1e3 * float(np.max(solve)):.3f}',
            'integrate time mean (ms)': f'{1e3 * float(np.mean(self.integrate or [0.0])):.3f}',
            'contact time mean (ms)': f'{1e3 * float(np.mean(self.contacts or [0.0])):.3f}',
            **{f'contact {name} time mean (ms)': f'{1e3 * float(np.mean(v or [0.0])):.3f}'
               for name, v in self.contact_parts.items()},
            # of the window's ticks (~120 at 120 Hz and a 1 s period: its second largest)
            'tick time p99 (ms)': f'{1e3 * float(np.percentile(self.tick_wall or [0.0], 99)):.3f}',
            'tick time max (ms)': f'{1e3 * max(self.tick_wall, default=0.0):.3f}',
            'timer lateness max (ms)': f'{1e3 * self.lateness:.3f}',
        }


class _Publishers:
    """The node's publishers as a ``TickSink``: a tick's poses (then ``/tf``, when live) and
    markers, and the diagnostics; inputs and parameter changes publish nothing."""

    def __init__(self, node, poses, markers, diagnostics, tf=None):
        self._node = node
        self.poses = poses
        self.markers = markers
        self.diagnostics = diagnostics
        self.tf = tf
        #: ``perf_counter`` when the last tick's poses were out (the node's ``tick_hook``).
        self.poses_published_at = 0.0

    def on_input(self, source, msg, log_time_ns):
        pass

    def on_tick(self, tick, log_time_ns):
        # The poses as encoded by the core (CDR bytes): rclpy publishes them raw.
        for pub, poses in zip(self.poses, tick.segments, strict=True):
            pub.publish(poses.cdr)
        self.poses_published_at = time.perf_counter()
        if self.tf is not None:
            self.tf.publish(tf_cdr(tick.segments, self._node._tf_prefix))
        if tick.segment_markers is not None:
            self.markers.publish(tick.segment_markers.wire)

    def on_diagnostics(self, msg, log_time_ns):
        self.diagnostics.publish(msg)

    def on_parameters(self, changed, log_time_ns):
        pass

    def close(self):
        pass


class PonytailNode(Node):
    """Simulates the configured chains hanging from the head given on ``head_pose`` (and from
    the extra frames given on their own topics).

    ``node_name``/``context``/``**kwargs`` go to ``rclpy.node.Node`` (e.g. ``namespace``,
    ``parameter_overrides``, ``cli_args``). ``recording_sink``: called as
    ``RunRecorder.for_node`` is when ``record_path`` is set, returns the ``TickSink`` that
    records the run (or None: not recording); without it ``record_path`` is refused with a
    start-up warning (``ponytail_ros.node.PonytailNode`` passes the recorder). Raises
    ``ParameterError`` (or rclpy's ``ParameterException``) if the parameters are invalid at
    start-up.
    """

    def __init__(self, node_name='ponytail', *, context=None, recording_sink=None, **kwargs):
        super().__init__(node_name, context=context, **kwargs)
        self._declare_parameters()
        values = {name: self._value(name) for name in self._param_names}
        # The simulators compile (or load) the kernels their scenes use when built, saying
        # so, rather than stalling the first tick.
        say_compiles(self.get_logger().info)
        #: What the node does, without rclpy (shared with ``ponytail_replay``).
        self.core = NodeCore(values)
        self.core.runner.on_drop = self._on_drop
        # The runner builds its Simulator at the first head pose: its stages are loaded (or
        # compiled) now, or that first tick would stall and drop simulated time.
        compile_kernels(stages_for(self.core.runner.scene), self.get_logger().info)
        # A sparse head stream, a gap in it (NodeCore throttles them on the node clock).
        self.core.on_notice = lambda key, text: self._log_throttled(f'notice:{key}', 0.0,
                                                                    'warning', text)
        self._check_input_topics()
        #: Warnings said at start-up about the parameters given (unknown names; tf).
        self.startup_warnings = []
        self._declare_tf_parameters()
        if self.core.tf is not None:      # (its own segments come back on /tf: not inputs)
            self.core.tf.ignore_prefixes = tuple(f'{self._tf_prefix}{c}/' for c in self._chains)
        self._warn_unknown_overrides()

        if len(self._chains) == 1:
            topics = ['segment_poses']
        else:
            topics = [f'segment_poses/{c}' for c in self._chains]
        self._pose_pubs = [self.create_publisher(PoseArray, tp, OUTPUT_QOS) for tp in topics]
        self._marker_pub = self.create_publisher(MarkerArray, 'segment_markers', OUTPUT_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        # Inputs taken raw (CDR bytes) and decoded with struct: rclpy's conversion of each
        # message into Python objects costs more than the rest of handling it.
        tf_in = self.core.tf
        if tf_in is not None:
            self._head_sub = _Input(self.resolve_topic_name('head_pose'))
            self._tf_subs = self._make_tf_subscriptions()
        else:
            self._head_sub = self.create_subscription(PoseStamped, 'head_pose',
                                                      self._on_head_cdr, INPUT_QOS, raw=True)
        #: The first head pose's frame is checked against fixed_frame (said once).
        self._head_frame_checked = tf_in is not None
        if self.core.frames_topic and self._frames:
            # All the frames in one PoseArray: one subscription (one callback per input period
            # however many frames), the same one for every frame.
            batch = self.create_subscription(PoseArray, self.core.frames_topic,
                                             self._on_frames_cdr, INPUT_QOS, raw=True)
            self._frame_subs = [batch] * len(self._frames)
        else:
            from_tf = tf_in.sources if tf_in is not None else {}
            self._frame_subs = [
                _Input(self.resolve_topic_name(topic)) if i in from_tf else
                self.create_subscription(
                    PoseStamped, topic, lambda data, i=i: self._on_frame_pose(i, _received(data)),
                    INPUT_QOS, raw=True)
                for i, topic in enumerate(self.core.frame_topics)]
        #: Input name ('head' or a frame's) -> its resolved topic (log messages).
        self._input_topics = {'head': self._head_sub.topic_name,
                              **{f: sub.topic_name
                                 for f, sub in zip(self._frames, self._frame_subs, strict=True)}}
        tf_frames = set()
        if tf_in is not None:
            for source in tf_in.sources:
                name = 'head' if source == 'head' else self._frames[source]
                self._input_topics[name] = tf_in.describe(source)
                tf_frames.add(name)
        if self._frame_subs:
            self._input_topics['frames'] = self._frame_subs[0].topic_name
        #: /tf live (tf2_msgs importable and tf.publish), else None.
        self._tf_pub = self._make_tf_publisher()
        self._timer = self.create_timer(1.0 / values['rate'], timer_callback(self._on_tick))
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._diag_timer = self.create_timer(values['diagnostics_period'],
                                             self._on_diagnostics, clock=self._steady)
        self._log_times = {}
        self._timing = _Timing()
        #: Optional ``hook(output, wall_start, wall_poses_published, wall_end)`` (perf_counter
        #: times) called after every published tick (benchmarks, tests).
        self.tick_hook = None
        self.add_pre_set_parameters_callback(self._pre_set_parameters)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._post_set_parameters)
        # Where the tick's output goes (app/sink.py): the recorder first (record_path), so
        # that nothing reaches a subscriber that the file lacks, then the publishers.
        self._publisher_sink = _Publishers(self, self._pose_pubs, self._marker_pub, self._diag_pub,
                                       self._tf_pub)
        self._recorder = None
        if values['record_path']:
            if recording_sink is None:
                self._startup_warning(
                    'Not recording: record_path is set but this node was built without a '
                    'recorder (use ponytail_node or ponytail_ros.node.PonytailNode)')
            else:
                self._recorder = recording_sink(
                    self, values['record_path'], self._chains, self._head_sub,
                    self._pose_pubs, self._marker_pub, self._diag_pub,
                    frames=self._frames, frame_subscriptions=self._frame_subs,
                    tf_prefix=self._tf_prefix)
        self._sinks = Sinks([s for s in (self._recorder, self._publisher_sink) if s is not None])
        scene = self.core.scene
        inputs = ', '.join([tf_in.describe('head') if tf_in is not None else 'head_pose']
                           + list(dict.fromkeys(self._input_topics[f] if f in tf_frames else t
                                                for f, t in zip(self._frames,
                                                                self.core.frame_topics,
                                                                strict=True))))
        #: Set (and logged once) when another node with this node's name is in the graph.
        self.duplicate_name_warning = None
        self._name_checks = 0
        self._name_timer = self.create_timer(1.0, self._check_duplicate_name, clock=self._steady)
        self.get_logger().info(
            f'Simulating {len(self._chains)} chain(s) {self._chains} '
            f'({scene.n_segments} segments, {len(scene.colliders)} collider(s)) at '
            f'{values["rate"]:g} Hz; {inputs} -> {", ".join(topics)}, segment_markers')

    # -- start-up checks ------------------------------------------------------------------
    def _declare_tf_parameters(self):
        """``tf.publish`` / ``tf.prefix``: the segments as TF frames ``<prefix><chain>/<i>``
        (children of the outputs' frame) on ``/tf`` live, when ``tf2_msgs`` is importable, and
        always in recordings. Node-only (they do not change the simulation)."""
        publish, prefix = NODE_PARAMS
        self.declare_parameter('tf.publish', publish.default, ParameterDescriptor(
            description=publish.description, read_only=True))
        self.declare_parameter('tf.prefix', tf_prefix_of(self.get_namespace()),
                               ParameterDescriptor(description=prefix.description,
                                                   read_only=True))
        self._tf_prefix = str(self.get_parameter('tf.prefix').value)

    def _make_tf_publisher(self):
        if not self.get_parameter('tf.publish').value:
            return None
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self._startup_warning(
                'Live TF is off: tf2_msgs is not installed (the ROS 2 PyPI wheels do not ship '
                'it), so the segments are not published on /tf. Source a ROS 2 workspace that '
                'has tf2_msgs (or build it into this Python environment); recordings '
                '(record_path) hold /tf regardless. tf.publish:=false silences this')
            return None
        return self.create_publisher(TFMessage, TF_TOPIC, TF_QOS)

    def _make_tf_subscriptions(self):
        """``/tf`` and ``/tf_static`` (raw bytes, read with ``wire.tf_message_fields``) for the
        head from TF; refused without ``tf2_msgs`` (the subscription needs its type)."""
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            raise ParameterError('head_frame', f'head_frame = {self.core.values["head_frame"]!r}'
                                 f' needs tf2_msgs to subscribe /tf and /tf_static, and it is '
                                 f'not installed (the ROS 2 PyPI wheels do not ship it): source '
                                 f'a ROS 2 workspace that has it, or give the head on head_pose '
                                 f'(head_frame:="")') from None
        self._tf_message = TFMessage
        return [self.create_subscription(TFMessage, TF_TOPIC,
                                         lambda data: self._on_tf(data, False), TF_QOS, raw=True),
                self.create_subscription(TFMessage, TF_STATIC_TOPIC,
                                         lambda data: self._on_tf(data, True), TF_STATIC_QOS,
                                         raw=True)]

    def _startup_warning(self, text):
        self.startup_warnings.append(text)
        self.get_logger().warning(text)

    def _warn_unknown_overrides(self):
        """Overrides (params file, ``-p``) that name no parameter of this node are ignored by
        rclpy without a word: say so, with the closest known name (a typo)."""
        known = set(self._param_names) | {'tf.publish', 'tf.prefix'}
        for name in sorted(self._parameter_overrides):
            if name in known or self.has_parameter(name):
                continue
            self._startup_warning(
                f'{unknown_parameter_warning(name, known)}: not a parameter of '
                f'{self.get_fully_qualified_name()} (params file or -p)')

    def _check_duplicate_name(self):
        """Another node with this name in this namespace doubles every topic: warn once.
        Checked every second for the first 5 s (discovery takes a moment)."""
        self._name_checks += 1
        try:
            same = [1 for name, ns in self.get_node_names_and_namespaces()
                    if name == self.get_name() and ns == self.get_namespace()]
        except Exception:  # noqa: BLE001 - the graph is unavailable during shutdown
            same = []
        if len(same) > 1:
            fqn = self.get_fully_qualified_name()
            self.duplicate_name_warning = (
                f'{len(same)} nodes named {fqn} are running: each publishes on the same '
                f'topics, so every topic is doubled. Give each character its own namespace '
                f'(-r __ns:=/bob) or node name (-r __node:=ponytail_bob)')
            self.get_logger().warning(self.duplicate_name_warning)
        if self.duplicate_name_warning is not None or self._name_checks >= 5:
            self._name_timer.cancel()

    def _check_input_topics(self):
        """Every frame reads its own topic, not the head's nor another frame's (as resolved
        in this node's namespace, remappings applied); or all read ``frames_topic``, not the
        head's."""
        seen = {self.resolve_topic_name('head_pose'): 'the head (head_pose)'}
        if self.core.frames_topic:
            resolved = self.resolve_topic_name(self.core.frames_topic)
            if resolved in seen:
                raise ParameterError('frames_topic', f'frames_topic = '
                                     f'{self.core.frames_topic!r} is not allowed: it resolves '
                                     f'to {resolved}, which the head (head_pose) already reads')
            return
        for frame, topic in zip(self.core.frames, self.core.frame_topics, strict=True):
            resolved = self.resolve_topic_name(topic)
            name = chain_param_name(frame, 'topic')
            if resolved in seen:
                raise ParameterError(name, f'{name} = {topic!r} is not allowed: it resolves to '
                                           f'{resolved}, which {seen[resolved]} already reads')
            seen[resolved] = f'frame {frame}'

    @property
    def runner(self):
        """The ``ChainRunner`` (head estimation and simulator)."""
        return self.core.runner

    @property
    def _values(self):
        return self.core.values

    # -- parameters ------------------------------------------------------------------------
    def _declare(self, pdef, name, default):
        override = self._parameter_overrides.get(name)
        if override is not None:
            self._parameter_overrides[name] = _coerce(override, pdef.kind)
        descriptor = _descriptor(pdef)
        if isinstance(default, list) and not default:
            # rclpy types an empty list as BYTE_ARRAY, which would refuse a list of strings or
            # doubles: such a parameter (``colliders``, ``<chain>.segment_lengths``) is
            # declared dynamically typed (its values are type-checked in ``check_values``).
            descriptor.dynamic_typing = True
        self.declare_parameter(name, default, descriptor)
        self._param_names.append(name)

    def _value(self, name):
        return _plain(self.get_parameter(name).value)

    def _declare_parameters(self):
        self._param_names = []
        for pdef in GLOBAL_PARAMS:
            self._declare(pdef, pdef.name, pdef.default)
        self._chains = [str(c) for c in self.get_parameter('chains').value]
        self._colliders = [str(c) for c in self._value('colliders')]
        self._frames = [str(f) for f in self._value('frames')]
        check_names(self._chains, self._colliders, self._frames)
        # (anchor/frame: described with the frame names among their choices)
        for i, chain in enumerate(self._chains):
            for pdef in CHAIN_PARAMS:
                default = pdef.default
                if pdef.name == 'color':
                    default = list(DEFAULT_COLORS[i % len(DEFAULT_COLORS)])
                name = chain_param_name(chain, pdef.name)
                self._declare(self._definition(name), name, default)
        for collider in self._colliders:
            for pdef in COLLIDER_PARAMS:
                name = chain_param_name(collider, pdef.name)
                self._declare(self._definition(name), name, pdef.default)
        for frame in self._frames:
            for pdef in FRAME_PARAMS:
                self._declare(pdef, chain_param_name(frame, pdef.name), pdef.default)

    def _definition(self, name):
        return definition(name, self._chains, self._colliders, self._frames)

    def set_parameters_atomically(self, parameter_list):
        """As rclpy's, but an unknown name or a wrong type is refused with a reason in words
        (rclpy says "Wrong parameter type, expected '2' got '4'" and "Invalid access to
        undeclared parameter(s)"); this is what ``ros2 param set`` calls."""
        reason = self._refusal(self._pre_set_parameters(list(parameter_list)))
        if reason is not None:
            self.get_logger().warning(f'Rejected parameter change: {reason}')
            return SetParametersResult(successful=False, reason=reason)
        return super().set_parameters_atomically(parameter_list)

    def _refusal(self, params):
        for p in params:
            if not self.has_parameter(p.name):
                close = closest_name(p.name, self._parameters)
                hint = f' (did you mean {close!r}?)' if close else ''
                return (f'{p.name!r} is not a parameter of {self.get_fully_qualified_name()}'
                        f'{hint}')
            descriptor = self.describe_parameter(p.name)
            if (descriptor.dynamic_typing or p.type_ == Parameter.Type.NOT_SET
                    or p.type_.value == descriptor.type):
                continue
            want = _TYPE_WORDS.get(Parameter.Type(descriptor.type), 'another type')
            got = _TYPE_WORDS.get(p.type_, p.type_.name.lower())
            return f'{p.name} must be {want}, not {got} ({p.value!r})'
        return None

    def _pre_set_parameters(self, params):
        out = []
        for p in params:
            pdef = self._definition(p.name)
            out.append(_coerce(p, pdef.kind) if pdef is not None else p)
        return out

    def _on_set_parameters(self, params):
        changed = self.core.ours({p.name: _plain(p.value) for p in params})
        if not changed:
            return SetParametersResult(successful=True)
        try:
            self.core.check_change(changed)
        except ParameterError as err:
            self.get_logger().warning(f'Rejected parameter change: {err}')
            return SetParametersResult(successful=False, reason=str(err))
        return SetParametersResult(successful=True)

    def _post_set_parameters(self, params):
        changed = self.core.ours({p.name: _plain(p.value) for p in params})
        if not changed:
            return
        self._sinks.on_parameters(changed, self.get_clock().now().nanoseconds)
        self.core.apply_change(changed)
        if 'rate' in changed:
            self._timer.timer_period_ns = int(round(1e9 / self._values['rate']))
        self.get_logger().info('Parameters changed: ' + ', '.join(
            f'{k}={v}' for k, v in sorted(changed.items())))

    # -- input -----------------------------------------------------------------------------
    def _on_head_cdr(self, data):
        self._on_head_pose(_received(data))

    def _on_tf(self, data, static):
        """A ``TFMessage`` on ``/tf`` (or ``/tf_static``): the head (and frames) now due from
        TF go the way of poses on their topics."""
        tf_in = self.core.tf
        try:
            transforms = tf_message_fields(data)
        except ValueError:
            msg = deserialize_message(data, self._tf_message)
            transforms = [(t.header.stamp.sec, t.header.stamp.nanosec, t.header.frame_id,
                           t.child_frame_id,
                           (t.transform.translation.x, t.transform.translation.y,
                            t.transform.translation.z),
                           (t.transform.rotation.x, t.transform.rotation.y,
                            t.transform.rotation.z, t.transform.rotation.w))
                          for t in msg.transforms]
        for source, pose in tf_in.add(transforms, static):
            if source == 'head':
                self._on_head_pose(pose)
            else:
                self._on_frame_pose(source, pose)
        for key, text in tf_in.news():
            self._log_throttled(key, 5.0, 'warning', text)

    def _check_head_frame(self, frame_id):
        """Said once: head poses whose frame is empty (taken as ``fixed_frame``) or another
        than ``fixed_frame`` (the simulation then runs in theirs)."""
        self._head_frame_checked = True
        fixed = self.core.values['fixed_frame']
        topic = self._input_topics['head']
        if not frame_id:
            self.get_logger().info(f'Head poses on {topic} have an empty header.frame_id: taken '
                                   f'as fixed_frame {fixed!r}')
        elif frame_id != fixed and not self.core.values['frame_id']:
            self.get_logger().warning(
                f'Head poses on {topic} are in frame {frame_id!r}, not fixed_frame {fixed!r}: '
                f'the simulation (gravity, wind) runs in {frame_id!r}, which must be inertial, '
                f'and the segments are published in it. Set fixed_frame:={frame_id} to say so')

    def _on_head_pose(self, msg):
        """A head pose: a ``PoseStamped`` or a ``ReceivedPose`` (the same fields)."""
        now_ns = self.get_clock().now().nanoseconds  # the receive time (recorded as log time)
        self._sinks.on_input(HEAD, msg, now_ns)
        if not self._head_frame_checked:
            self._check_head_frame(msg.frame_id if isinstance(msg, ReceivedPose)
                                   else msg.header.frame_id)
        if isinstance(msg, ReceivedPose):
            self.core.push_head(msg.stamp, now_ns, msg.position, msg.orientation, msg.frame_id)
            return
        p, q = msg.pose.position, msg.pose.orientation
        self.core.push_head(msg.header.stamp, now_ns, (p.x, p.y, p.z), (q.x, q.y, q.z, q.w),
                            msg.header.frame_id)

    def _on_frame_pose(self, i, msg):
        now_ns = self.get_clock().now().nanoseconds  # the receive time (recorded as log time)
        self._sinks.on_input(i, msg, now_ns)
        if isinstance(msg, ReceivedPose):
            self.core.push_frame(i, msg.stamp, now_ns, msg.position, msg.orientation,
                                 msg.frame_id)
            return
        p, q = msg.pose.position, msg.pose.orientation
        self.core.push_frame(i, msg.header.stamp, now_ns, (p.x, p.y, p.z),
                             (q.x, q.y, q.z, q.w), msg.header.frame_id)

    def _on_frames_cdr(self, data):
        """A ``PoseArray`` of every frame's pose (``frames_topic``)."""
        now_ns = self.get_clock().now().nanoseconds  # the receive time (recorded as log time)
        msg = ReceivedPoses.decode(data)
        if msg is None:
            msg = ReceivedPoses.of_message(deserialize_message(data, PoseArray))
        self._sinks.on_input(0, msg, now_ns)
        self.core.push_frames(msg.stamp, now_ns, msg.poses, msg.frame_id)

    def _on_drop(self, reason, t, source='head'):
        what = ('a head pose' if source == 'head' else
                f'the frames\' poses (a PoseArray of another length than frames, '
                f'{len(self._frames)})' if source == 'frames' else f'a pose of frame {source}')
        self._log_throttled(
            f'drop:{source}:{reason}', 2.0, 'warning',
            f'Dropped {what} ({reason}, stamp {t}, {self._input_topics[source]}); '
            f'{self.runner.dropped[reason]} inputs dropped for this reason so far')

    def _log_throttled(self, key, period, level, text):
        now = time.monotonic()
        last = self._log_times.get(key)
        if last is not None and now - last < period:
            return
        self._log_times[key] = now
        # One call site per severity: rclpy refuses a severity change at one call site.
        logger = self.get_logger()
        if level == 'info':
            logger.info(text)
        elif level == 'error':
            logger.error(text)
        else:
            logger.warning(text)

    # -- the tick --------------------------------------------------------------------------
    def _on_tick(self, info: TimerInfo | None = None) -> None:
        wall0 = time.perf_counter()
        timing = self._timing
        if info is not None:
            late = (info.actual_call_time.nanoseconds - info.expected_call_time.nanoseconds)
            timing.lateness = max(timing.lateness, late * 1e-9)
        now_ns = self.get_clock().now().nanoseconds
        tick = self.core.tick(now_ns)
        wall1 = time.perf_counter()
        if tick is None:
            missing = self.runner.missing_inputs()
            if now_ns != 0 and missing:
                topics = ', '.join(dict.fromkeys(self._input_topics[m] for m in missing))
                what = ('No head pose received' if missing == ['head']
                        else 'No pose received')
                self._log_throttled('no_head', 5.0, 'warning',
                                    f'{what} on {topics} yet: nothing is published')
            return
        self._emit(tick)
        wall_published = self._publisher_sink.poses_published_at
        out, rep = tick.output, tick.output.report
        timing.add_tick(wall1 - wall0, rep.timings)
        timing.tick_wall.append(time.perf_counter() - wall0)
        if out.reset_reason is not None:
            level = 'warning' if out.reset_reason in ('guard', 'clock_backwards') else 'info'
            self._log_throttled('reset:' + out.reset_reason, 2.0, level,
                                f'Chain reset at rest ({self.runner.last_reset})')
        if out.frames_reset:
            self._log_throttled('reset:frames', 2.0, 'info',
                                f'Chains on {", ".join(out.frames_reset)} reset at rest '
                                '(teleport)')
        if out.head_stale and self.runner.needs_head:
            self._log_throttled('stale', 5.0, 'warning',
                                'Head pose stale (no pose accepted for over '
                                f'{self.runner.settings.stale_timeout:g} s): holding the last '
                                'pose')
        for i in self.runner.stale_frames(out.t):
            f = self._frames[i]
            self._log_throttled(f'stale:{f}', 5.0, 'warning',
                                f'Frame {f} pose stale on {self._input_topics[f]} (no pose '
                                f'accepted for over {self.runner.settings.stale_timeout:g} '
                                's): holding its last pose')
        if rep.dropped_time > 0.0:
            self._log_throttled('dropped_time', 5.0, 'warning',
                                f'Dropped {rep.dropped_time:.3f} s of simulation time '
                                f'(solver.max_steps_per_call reached)')
        if self.tick_hook is not None:
            self.tick_hook(out, wall0, wall_published, time.perf_counter())

    # -- diagnostics -----------------------------------------------------------------------
    def _emit(self, tick: NodeTick) -> None:
        """The tick's messages to every sink, at the node clock's time of publishing."""
        self._sinks.on_tick(tick, self.get_clock().now().nanoseconds)

    def diagnostic_status(self):
        """The node's ``DiagnosticStatus`` over the window since the last call (resets it)."""
        timing, self._timing = self._timing, _Timing()
        return self.core.diagnostic_status(
            self.get_clock().now().nanoseconds, time.monotonic() - timing.wall0,
            self.get_fully_qualified_name(), timing.values())

    def _on_diagnostics(self):
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [self.diagnostic_status()]
        self._sinks.on_diagnostics(msg, self.get_clock().now().nanoseconds)
        # Said on the terminal too, with the fix, not only inside /diagnostics (throttled).
        status = msg.status[0]
        values = {kv.key: kv.value for kv in status.values}
        if 'clocks differ' in status.message:
            self._log_throttled(
                'clock', 30.0, 'warning',
                f'Head pose stamps on {self._input_topics["head"]} are '
                f'{values.get("head input age (s)", "?")} s off this node\'s clock (another '
                f'clock: a simulator, another machine, use_sim_time on one side only): the '
                f'motion is estimated wrongly. Fix: stamp_source:=receive (time poses by their '
                f'arrival), or run both on the same clock (use_sim_time)')
        if OVERLOADED in status.message:
            # A node that cannot keep its rate falls further behind.
            self._log_throttled(
                'overload', 30.0, 'warning',
                f'Ticking at {values.get("tick rate (Hz)", "?")} Hz, below rate '
                f'{self.core.values["rate"]:g} Hz: each tick takes longer than its period, so '
                f'this node falls behind. Run one node per group of characters (each in its '
                f'own namespace: -r __ns:=/group1), or lower rate, or raise solver.dt')

    def destroy_node(self):
        """Finalise the recording (if any), then destroy the node."""
        recorder, self._recorder = getattr(self, '_recorder', None), None
        if recorder is not None:
            recorder.close()
        return super().destroy_node()


def node_help() -> str:
    """``ponytail_node --help``: usage, topics and every parameter (``app/param_docs.py``)."""
    from ponytail_ros.app.param_docs import help_text
    lines = [
        'usage: ponytail_node [-h] [--ros-args --params-file config/ponytail.yaml '
        '-p name:=value -r __ns:=/alice]',
        '',
        'Simulates chains (ponytails, tails, ropes, swords) hanging from the head pose on '
        'head_pose (geometry_msgs/PoseStamped); publishes segment_poses (PoseArray), '
        'segment_markers, /diagnostics and, with tf2_msgs installed, /tf. record_path:=run.mcap '
        'records the run for ponytail_replay.',
        '',
        help_text(),
        '',
        'Exit status: 0 on Ctrl-C/SIGTERM, 2 for invalid parameters (one line naming the '
        'parameter and the allowed values).']
    return '\n'.join(lines)


def main(args=None, node_class=PonytailNode):
    """Run ``node_class`` as ``ponytail_node`` does; returns the exit code (``ponytail_node``
    itself runs ``ponytail_ros.node:main``, which passes the node with recording)."""
    return run_node('ponytail_node', node_class, args,
                    bad_input=(ParameterError, ParameterException), help_text=node_help())
