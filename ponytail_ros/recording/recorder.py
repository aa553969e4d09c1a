"""Recording one run of the ponytail node (or of a replay) into an MCAP file in rosbag2's layout.

What is recorded (topic names as resolved in the node's namespace; types as published):

* the head input, ``head_pose`` (``geometry_msgs/msg/PoseStamped``) as received;
* each extra frame's pose topic (``frames``, ``<frame>.topic``; ``PoseStamped``) as received,
  like the head's;
* each chain's ``segment_poses`` / ``segment_poses/<chain>`` (``geometry_msgs/msg/PoseArray``);
* ``segment_markers`` (``visualization_msgs/msg/MarkerArray``) when published (markers on);
* ``/diagnostics`` (``diagnostic_msgs/msg/DiagnosticArray``);
* ``/tf`` (``tf2_msgs/msg/TFMessage``): every chain's segments as TF frames
  ``<tf_prefix><chain>/<i>`` (children of the ``PoseArray``'s frame, the head pose's), one
  message per chain per tick (``tf.py``; on by default, ``tf=False`` to leave it out);
* ``/parameter_events`` (``rcl_interfaces/msg/ParameterEvent``): one event per accepted live
  parameter change of the node (``changed_parameters``), at the time it was accepted;
* metadata ``ponytail_ros/parameters``: every parameter of the node at start-up, name -> value
  as JSON text (floats round-trip exactly) -- with the events above, enough to reproduce the
  run from the file alone;
* metadata ``ponytail_ros/recording``: the node's name, its chains and topic names (with the
  frames and their topics, ``frames``/``frame_topics``, when the node has frames: a recording
  without them has none), what wrote the file (``ponytail_node`` or ``ponytail_replay``).

Times: as in rosbag2, ``log_time`` is the receive time on the node clock (ns) -- for the node's
own outputs the node clock when they are published -- and ``publish_time`` is the message's
header stamp. The file order is the order in which the node handled the messages (one writer
queue), which is what a replay needs: a head (or frame) pose written before a tick's
``PoseArray`` was queued before that tick.

The node never waits on the disk: a write serialises the message and enqueues it (a tick's
poses, ``/tf`` and markers come as CDR bytes already, ``app/wire.py``, and are enqueued as they
are); a background thread (``BagWriter``) does the I/O. Failures never reach the node: opening
errors are logged and the node runs without recording; a later I/O error (disk full) is logged
once and recording stops. See ``bag.py`` for what a SIGKILL loses (at most the last ~0.5 s of
log time); SIGINT and SIGTERM end ``rclpy.spin`` and the node's ``destroy_node`` finalises the
file.
"""
from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, qos_profile_parameter_events

from ponytail_ros.app.messages import ReceivedPose, ReceivedPoses
from ponytail_ros.app.param_values import metadata_from_values

from .bag import PARAMETERS_METADATA, BagError, BagWriter, message_definition_of_text
from .cdr import serialize_canonical
from .tf import (
    TF_QOS_DEPTH,
    TF_TOPIC,
    TFMESSAGE_MSG,
    TFMESSAGE_TYPE,
    tf_from_pose_array,
    tfmessage_type_hash,
)

__all__ = ['RunRecorder', 'RunLayout', 'RECORDING_METADATA', 'PARAMETERS_METADATA',
           'PARAMETER_EVENTS_TOPIC', 'HEAD_TYPES', 'FRAMES_TYPE', 'stamp_ns', 'expand_record_path',
           'resolve_topic']

#: Metadata record describing the recording (str -> str, lists as JSON).
RECORDING_METADATA = 'ponytail_ros/recording'
#: Version of what ``RECORDING_METADATA`` describes.
FORMAT_VERSION = '1'
PARAMETER_EVENTS_TOPIC = '/parameter_events'
#: Message types accepted as head input (the node subscribes to the first).
HEAD_TYPES = ('geometry_msgs/msg/PoseStamped', 'geometry_msgs/msg/TransformStamped')
#: The type of ``frames_topic`` (every frame's pose in one message).
FRAMES_TYPE = 'geometry_msgs/msg/PoseArray'
#: The QoS recorded for the head topic: what a reliable publisher (the head demo) offers; both
#: reliable and best-effort subscriptions connect to a ``ros2 bag play`` using it.
HEAD_QOS = QoSProfile(depth=10)


def stamp_ns(stamp) -> int:
    """A ``builtin_interfaces/Time`` as integer nanoseconds."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def _publish_time(msg, default: int) -> int:
    """Header stamp of a message (ns), ``default`` when it has none or it is negative."""
    header = getattr(msg, 'header', None)
    if header is None:
        markers = getattr(msg, 'markers', None)
        header = markers[0].header if markers else None
    if header is None:
        stamp = getattr(msg, 'stamp', None)
    else:
        stamp = header.stamp
    if stamp is None:
        return default
    ns = stamp_ns(stamp)
    return ns if ns >= 0 else default


def expand_record_path(path: str) -> Path:
    """``~`` and ``$VAR`` expanded; ``%`` codes as ``time.strftime`` (one file per run:
    ``runs/ponytail_%Y%m%d_%H%M%S.mcap``)."""
    path = os.path.expandvars(os.path.expanduser(path))
    if '%' in path:
        path = time.strftime(path)
    return Path(path)


@dataclass(frozen=True)
class RunLayout:
    """Who recorded and on which topics.

    Attributes:
        node: fully qualified node name, e.g. ``/alice/ponytail``.
        chains: chain names, in parameter order.
        head_topic: the head input topic.
        pose_topics: one ``PoseArray`` topic per chain, same order; the first one's header
            stamps are the tick times.
        marker_topic, diagnostics_topic, parameter_events_topic: the other topics.
        frames: the extra kinematic frames' names (``frames``), in parameter order.
        frame_topics: their pose topics (resolved), same order.
    """

    node: str
    chains: tuple
    head_topic: str
    pose_topics: tuple
    marker_topic: str
    diagnostics_topic: str = '/diagnostics'
    parameter_events_topic: str = PARAMETER_EVENTS_TOPIC
    frames: tuple = ()
    frame_topics: tuple = ()

    @classmethod
    def for_node(cls, node_fqn: str, chains: Sequence[str],
                 head_topic: str | None = None, frames: Sequence[str] = (),
                 frame_topics: Sequence[str] = ()) -> RunLayout:
        """The topics of a ``PonytailNode`` named ``node_fqn`` (relative names resolved in its
        namespace, as the node does); ``frame_topics`` as configured (``<frame>.topic``)."""
        namespace = node_fqn.rsplit('/', 1)[0]
        chains = tuple(chains)
        poses: tuple[str, ...]
        if len(chains) == 1:
            poses = (f'{namespace}/segment_poses',)
        else:
            poses = tuple(f'{namespace}/segment_poses/{c}' for c in chains)
        return cls(node=node_fqn, chains=chains,
                   head_topic=head_topic or f'{namespace}/head_pose', pose_topics=poses,
                   marker_topic=f'{namespace}/segment_markers', frames=tuple(frames),
                   frame_topics=tuple(resolve_topic(node_fqn, t) for t in frame_topics))

    def to_metadata(self) -> dict[str, str]:
        meta = {'node': self.node, 'chains': json.dumps(list(self.chains)),
                'head_topic': self.head_topic, 'pose_topics': json.dumps(list(self.pose_topics)),
                'tick_topic': self.pose_topics[0], 'marker_topic': self.marker_topic,
                'diagnostics_topic': self.diagnostics_topic,
                'parameter_events_topic': self.parameter_events_topic}
        if self.frames:
            meta.update(frames=json.dumps(list(self.frames)),
                        frame_topics=json.dumps(list(self.frame_topics)))
        return meta

    @classmethod
    def from_metadata(cls, record: Mapping[str, str]) -> RunLayout:
        """Inverse of :meth:`to_metadata` (raises ``KeyError``/``ValueError`` if malformed); a
        recording without frames (older ones too) has none."""
        frames = tuple(json.loads(record.get('frames', '[]')))
        frame_topics = tuple(json.loads(record.get('frame_topics', '[]')))
        if len(frame_topics) != len(frames):
            raise ValueError('frames and frame_topics differ in length')
        chains = tuple(json.loads(record['chains']))
        pose_topics = tuple(json.loads(record['pose_topics']))
        if len(pose_topics) != len(chains):
            raise ValueError('chains and pose_topics differ in length')
        return cls(node=record['node'], chains=chains, head_topic=record['head_topic'],
                   pose_topics=pose_topics,
                   marker_topic=record['marker_topic'],
                   diagnostics_topic=record.get('diagnostics_topic', '/diagnostics'),
                   parameter_events_topic=record.get('parameter_events_topic',
                                                     PARAMETER_EVENTS_TOPIC),
                   frames=frames, frame_topics=frame_topics)


def resolve_topic(node_fqn: str, topic: str) -> str:
    """A topic name as a node named ``node_fqn`` resolves it: absolute as is, ``~/x`` under the
    node's name, relative names in its namespace (no remapping, no substitutions)."""
    if topic.startswith('/'):
        return topic
    if topic.startswith('~'):
        return node_fqn.rstrip('/') + topic[1:]
    namespace = node_fqn.rsplit('/', 1)[0]
    return f'{namespace}/{topic}'


class RunRecorder:
    """Writes one run: head input, chain poses, markers, diagnostics, parameter changes and the
    parameters in effect, with the node clock's times.

    Every method returns at once (serialise + enqueue) and never raises once the file is open:
    after an I/O error recording stops and ``on_error`` is called once with the reason.

    Args:
        path: the ``.mcap`` file to create (never overwritten unless ``overwrite``).
        layout: node name and topics (:class:`RunLayout`).
        parameters: every parameter name -> plain value at start.
        head_type: type of the head topic (``HEAD_TYPES``).
        frame_types: type of each frame topic (``layout.frame_topics``; default
            ``PoseStamped``).
        qos: topic -> the publisher's ``QoSProfile`` (defaults: depth 10, reliable).
        info: extra entries for the ``ponytail_ros/recording`` metadata (str -> str).
        on_error: called once with a message when recording stops on an I/O error.
        canonical: write canonical CDR (``cdr.zero_padding``: alignment gaps zeroed, the
            slack rclpy leaves after the data cut): equal messages are equal bytes and readers
            that check the length (rosbags) accept every type. On by default; off writes
            ``serialize_message``'s bytes as they are (the segment poses of a tick come as
            canonical CDR already, ``app/wire.py``, and are written as they come either way).
        overwrite, chunk_size, chunk_duration_ns, background: of ``BagWriter``.
        tf: also record every chain's segments on ``/tf`` (``tf2_msgs/msg/TFMessage``, one
            message per chain per tick, written with its ``PoseArray``; see ``tf.py``).
        tf_prefix: the segment frames are ``<tf_prefix><chain>/<i>``.

    Raises:
        BagError: the file cannot be created (exists, folder missing, not writable).
    """

    def __init__(self, path: str | os.PathLike, layout: RunLayout,
                 parameters: Mapping[str, Any], *, head_type: str = HEAD_TYPES[0],
                 frame_types: Sequence[str] | None = None,
                 qos: Mapping[str, QoSProfile] | None = None,
                 info: Mapping[str, str] | None = None,
                 on_error: Callable[[str], None] | None = None,
                 canonical: bool = True, overwrite: bool = False, chunk_size: int = 64 * 1024,
                 chunk_duration_ns: int = 500_000_000, tf: bool = True, tf_prefix: str = '',
                 background: bool = True):
        path = Path(path)
        if path.is_dir():
            raise BagError(f'cannot create bag {path}: it is a directory')
        self.layout = layout
        self.on_error = on_error
        self._error_reported = False
        self._canonical = canonical
        self._closed = False
        self._writer = BagWriter(path, overwrite=overwrite, chunk_size=chunk_size,
                                 chunk_duration_ns=chunk_duration_ns, background=background)
        #: pose topic -> chain name, for the chains' TF frames (empty without tf)
        self._tf_chains = dict(zip(layout.pose_topics, layout.chains, strict=True)) if tf else {}
        self._tf_prefix = tf_prefix
        self.path = self._writer.path
        qos = dict(qos or {})
        try:
            # Metadata first: a file cut short by a SIGKILL still says how to reproduce it.
            self._writer.write_metadata(PARAMETERS_METADATA, metadata_from_values(parameters))
            meta = layout.to_metadata()
            meta.update({'format': FORMAT_VERSION, 'head_type': head_type})
            if tf:
                meta.update({'tf_topic': TF_TOPIC, 'tf_prefix': tf_prefix})
            meta.update(info or {})
            self._meta = meta
            self._writer.write_metadata(RECORDING_METADATA, meta)
            self._writer.add_topic(layout.head_topic, head_type, qos.get(layout.head_topic,
                                                                         HEAD_QOS))
            types = list(frame_types or [HEAD_TYPES[0]] * len(layout.frame_topics))
            added = {layout.head_topic}
            for topic, type_name in zip(layout.frame_topics, types, strict=True):
                if topic not in added:        # (two inputs on one topic: one channel)
                    added.add(topic)
                    self._writer.add_topic(topic, type_name, qos.get(topic, HEAD_QOS))
            for topic in layout.pose_topics:
                self._writer.add_topic(topic, 'geometry_msgs/msg/PoseArray',
                                       qos.get(topic, 10))
            self._writer.add_topic(layout.marker_topic, 'visualization_msgs/msg/MarkerArray',
                                   qos.get(layout.marker_topic, 10))
            self._writer.add_topic(layout.diagnostics_topic,
                                   'diagnostic_msgs/msg/DiagnosticArray',
                                   qos.get(layout.diagnostics_topic, 10))
            self._writer.add_topic(layout.parameter_events_topic,
                                   'rcl_interfaces/msg/ParameterEvent',
                                   qos.get(layout.parameter_events_topic,
                                           qos_profile_parameter_events))
            if tf:
                self._writer.add_topic(
                    TF_TOPIC, TFMESSAGE_TYPE, qos.get(TF_TOPIC, QoSProfile(depth=TF_QOS_DEPTH)),
                    definition=message_definition_of_text(TFMESSAGE_TYPE, TFMESSAGE_MSG),
                    type_hash_=tfmessage_type_hash())
        except BaseException:
            self._writer.close()
            raise

    # -- writing -------------------------------------------------------------------------------
    @property
    def error(self) -> BagError | None:
        """The I/O error that stopped recording, or None."""
        return self._writer.error

    def _writable(self) -> bool:
        if self._closed:
            return False  # a callback after destroy_node: nothing to record any more
        if self._writer.error is not None:
            self._report_error()
            return False
        return True

    def _failed(self, exc: BagError) -> None:
        # A negative time, or closed by another thread meanwhile: never the node's problem;
        # reported once like an I/O error.
        if not self._closed:
            self._report_error(str(exc))

    def write(self, topic: str, msg: Any, log_time_ns: int) -> None:
        """Record ``msg`` on ``topic`` at ``log_time_ns``; publish time = its header stamp."""
        if not self._writable():
            return
        try:
            if self._canonical:
                self._writer.write_serialized(topic, serialize_canonical(msg), log_time_ns,
                                              _publish_time(msg, log_time_ns))
            else:
                self._writer.write(topic, msg, log_time_ns, _publish_time(msg, log_time_ns))
            chain = self._tf_chains.get(topic)
            if chain is not None:
                self._writer.write_serialized(TF_TOPIC, tf_from_pose_array(msg, chain,
                                                                           self._tf_prefix),
                                              log_time_ns, _publish_time(msg, log_time_ns))
        except BagError as exc:
            self._failed(exc)

    def segment_poses(self, chain_index: int, poses: Any, log_time_ns: int) -> None:
        """Chain ``chain_index``'s ``SegmentPoses`` (``app/messages.py``): its ``PoseArray``
        bytes as they are (already canonical CDR), then its ``/tf``, without a message object
        or a second serialisation. Publish time = the stamp (the log time if negative)."""
        if not self._writable():
            return
        topic = self.layout.pose_topics[chain_index]
        publish_ns = poses.stamp_ns if poses.stamp_ns >= 0 else log_time_ns
        try:
            self._writer.write_serialized(topic, poses.cdr, log_time_ns, publish_ns)
            if topic in self._tf_chains:
                self._writer.write_serialized(TF_TOPIC, poses.tf_cdr(self._tf_prefix),
                                              log_time_ns, publish_ns)
        except BagError as exc:
            self._failed(exc)

    def head(self, msg: Any, log_time_ns: int) -> None:
        """A head pose as received (a message or a ``ReceivedPose``), at its receive time."""
        self._input(self.layout.head_topic, msg, log_time_ns)

    def frame(self, frame_index: int, msg: Any, log_time_ns: int) -> None:
        """A pose of frame ``frame_index`` as received, at its receive time (as ``head``); or,
        on ``frames_topic``, a ``ReceivedPoses`` of every frame (recorded once)."""
        self._input(self.layout.frame_topics[frame_index], msg, log_time_ns)

    def _input(self, topic: str, msg: Any, log_time_ns: int) -> None:
        if not isinstance(msg, (ReceivedPose, ReceivedPoses)):
            self.write(topic, msg, log_time_ns)
        elif self._writable():
            # Its fields re-encoded as canonical CDR: no message object, no serialisation.
            stamp = msg.stamp
            publish_ns = stamp.sec * 1_000_000_000 + stamp.nanosec   # (as _publish_time)
            try:
                self._writer.write_serialized(topic, msg.canonical_cdr(), log_time_ns,
                                              publish_ns if publish_ns >= 0 else log_time_ns)
            except BagError as exc:
                self._failed(exc)

    def poses(self, chain_index: int, msg: Any, log_time_ns: int) -> None:
        self.write(self.layout.pose_topics[chain_index], msg, log_time_ns)

    def markers(self, msg: Any, log_time_ns: int) -> None:
        self.write(self.layout.marker_topic, msg, log_time_ns)

    def diagnostics(self, msg: Any, log_time_ns: int) -> None:
        self.write(self.layout.diagnostics_topic, msg, log_time_ns)

    def parameters_changed(self, changed: Mapping[str, Any], log_time_ns: int) -> None:
        """An accepted live change (name -> new plain value), as a ``ParameterEvent``."""
        from builtin_interfaces.msg import Time
        from rcl_interfaces.msg import ParameterEvent
        event = ParameterEvent(node=self.layout.node)
        event.stamp = Time(sec=log_time_ns // 1_000_000_000, nanosec=log_time_ns % 1_000_000_000)
        event.changed_parameters = [Parameter(name, value=value).to_parameter_msg()
                                    for name, value in sorted(changed.items())]
        self.write(self.layout.parameter_events_topic, event, log_time_ns)

    # -- the tick's output interface (app/sink.py: TickSink) -----------------------------------
    def on_input(self, source: int | None, msg: Any, log_time_ns: int) -> None:
        """The head pose (``source`` None) or frame ``source``'s, as received (a message, or
        a ``ReceivedPose``: recorded from its fields)."""
        if source is None:
            self.head(msg, log_time_ns)
        else:
            self.frame(source, msg, log_time_ns)

    def on_tick(self, tick: Any, log_time_ns: int) -> None:
        """A tick's ``PoseArray`` per chain (each with its ``/tf``), then its markers."""
        for c, poses in enumerate(tick.segments):
            self.segment_poses(c, poses, log_time_ns)
        markers = tick.segment_markers
        if markers is not None and self._writable():
            try:
                self._writer.write_serialized(
                    self.layout.marker_topic, markers.cdr, log_time_ns,
                    markers.stamp_ns if markers.stamp_ns >= 0 else log_time_ns)
            except BagError as exc:
                self._failed(exc)

    def on_diagnostics(self, msg: Any, log_time_ns: int) -> None:
        self.diagnostics(msg, log_time_ns)

    def on_parameters(self, changed: Mapping[str, Any], log_time_ns: int) -> None:
        self.parameters_changed(changed, log_time_ns)

    def mark_partial(self, reason: str, until_ns: int | None) -> None:
        """Say in the file that it holds only part of the run: ``reason`` (e.g. "interrupted by
        SIGINT") and the log time (ns) up to which it is complete. Written as a new
        ``ponytail_ros/recording`` record (the last of a name wins) with ``partial: true``,
        ``partial_reason``, ``complete_until_ns``, and in rosbag2's ``custom_data`` of the
        final ``rosbag2`` record (``ponytail_ros.partial`` ...). Call before :meth:`close`."""
        until = '' if until_ns is None else str(int(until_ns))
        if self._closed:
            return
        self._meta = {**self._meta, 'partial': 'true', 'partial_reason': reason,
                      'complete_until_ns': until}
        try:
            self._writer.write_metadata(RECORDING_METADATA, self._meta)
        except BagError as exc:
            self._failed(exc)
        self._writer.custom_data.update({'ponytail_ros.partial': 'true',
                                         'ponytail_ros.partial_reason': reason,
                                         'ponytail_ros.complete_until_ns': until})

    def close(self) -> None:
        """Finalise the file (idempotent)."""
        self._closed = True
        self._writer.close()
        if self._writer.error is not None:
            self._report_error()

    def _report_error(self, text: str | None = None) -> None:
        if self._error_reported:
            return
        self._error_reported = True
        if self.on_error is not None:
            self.on_error(text or str(self._writer.error))

    # -- the node ------------------------------------------------------------------------------
    @classmethod
    def for_node(cls, node, record_path: str, chains: Sequence[str], head_subscription,
                 pose_publishers: Sequence[Any], marker_publisher, diagnostics_publisher,
                 frames: Sequence[str] = (), frame_subscriptions: Sequence[Any] = (),
                 tf_prefix: str = '') -> RunRecorder | None:
        """A recorder for a running ``PonytailNode``, or None (error logged) if the file cannot
        be created; the node then goes on without recording.

        Records every parameter of the node (``list_parameters``) as it is now, the topics as
        resolved by the node (the frames' from ``frame_subscriptions``, same order as
        ``frames``), the publishers' QoS.
        """
        logger = node.get_logger()
        path = expand_record_path(record_path)
        layout = RunLayout(
            node=node.get_fully_qualified_name(), chains=tuple(chains),
            head_topic=head_subscription.topic_name,
            pose_topics=tuple(p.topic_name for p in pose_publishers),
            marker_topic=marker_publisher.topic_name,
            diagnostics_topic=diagnostics_publisher.topic_name,
            frames=tuple(frames), frame_topics=tuple(s.topic_name for s in frame_subscriptions))
        names = node.list_parameters([], 0).names
        parameters = {p.name: _plain(p.value) for p in node.get_parameters(names)}
        qos = {p.topic_name: p.qos_profile
               for p in (*pose_publishers, marker_publisher, diagnostics_publisher)}
        frame_types = [FRAMES_TYPE if getattr(s, 'msg_type', None) is not None
                       and s.msg_type.__name__ == 'PoseArray' else HEAD_TYPES[0]
                       for s in frame_subscriptions]
        try:
            recorder = cls(path, layout, parameters, qos=qos, tf_prefix=tf_prefix,
                           frame_types=frame_types,
                           info={'source': 'ponytail_node'},
                           on_error=lambda text: logger.error(
                               f'Recording stopped: {text}; the simulation goes on'))
        except BagError as exc:
            text = str(exc)
            if 'already exists' in text:
                text = (f'{path} already exists: an existing recording is never overwritten '
                        f'(remove it, or use a new record_path, e.g. with %Y%m%d_%H%M%S)')
            logger.error(f'Not recording: {text}; the simulation goes on without recording')
            return None
        logger.info(f'Recording to {recorder.path}')
        return recorder


def _plain(value):
    if isinstance(value, (str, bool, int, float)) or value is None:
        return value
    return list(value)
