"""The input of ``ponytail_replay``: a recording opened, its head and frame topics resolved, and
what the node recorded with it (layout, parameters, live changes, clock).

``ReplayInput`` is shared by the offline replay (``offline.py``) and the live playback
(``live.py``); ``ReplayError`` is every one-line refusal of bad input or options.
"""
from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from rclpy.serialization import deserialize_message

from ponytail_ros.app.messages import TF_TOPIC
from ponytail_ros.app.parameters import frame_names
from ponytail_ros.app.tf_input import TF_STATIC_TOPIC
from ponytail_ros.app.wire import pose_stamped_fields

from .bag import PARAMETERS_METADATA, BagError, BagReader
from .bag.msgdefs import _message_class
from .recorder import HEAD_TYPES, RECORDING_METADATA, RunLayout, resolve_topic, stamp_ns
from .tf import TFMESSAGE_TYPE

__all__ = ['ReplayError', 'ReplayInput', 'head_pose', 'head_stamps', 'foreign_clock',
           'partial_note', 'recorded_value', 'used_frame_names', 'event_values', 'FOREIGN_CLOCK_S']


class ReplayError(Exception):
    """Bad input or options; the message is one line naming the file (and topic)."""


class ReplayInput:
    """An input recording: its topics, metadata, the head topic and what the node recorded.

    Raises:
        ReplayError: not readable, not MCAP, no head topic, or the head topic is not a pose
            (with ``head_required`` false, the last two are kept in :attr:`head_error` for
            :meth:`require_head`: the head may come from TF, ``use_tf_head``).
    """

    def __init__(self, path, head_topic: str | None = None, head_required: bool = True):
        self.path = Path(path)
        try:
            self.reader = BagReader(self.path)
            self.topics = self.reader.topics()
            self.metadata = self.reader.metadata()   # a full walk: finds a cut or damage
        except BagError as exc:
            raise ReplayError(str(exc)) from None
        self.truncated = not self.reader.finished
        #: "truncated at byte N of M: why" for a cut file, else None.
        self.truncation = self.reader.truncation if self.truncated else None
        self.layout = None
        if RECORDING_METADATA in self.metadata:
            try:
                self.layout = RunLayout.from_metadata(self.metadata[RECORDING_METADATA])
            except (KeyError, ValueError):
                self.layout = None  # not ours after all: treat as a plain recording
        #: Our recordings are replayed in the order the node handled the messages (file order,
        #: see recorder.py); any other bag in log-time order, as rosbag2 plays it.
        self.order = 'file' if self.layout is not None else 'log_time'
        self.recorded_parameters = self.metadata.get(PARAMETERS_METADATA)
        #: What to tell the user about the input (one file of a split bag, no metadata.yaml,
        #: an interrupted replay's output), one line each.
        self.notes = list(self.reader.notes) + [
            n for n in (partial_note(self.path, self.metadata),) if n]
        self.note = None
        #: Checked between messages (:meth:`messages`); :attr:`stopped`: it ended a read.
        self.stop: Any = None
        self.stopped = False
        if head_topic is None:
            head_topic = self.layout.head_topic if self.layout else '/head_pose'
            if head_topic not in self.topics:
                heads = sorted(t for t, ty in self.topics.items() if ty in HEAD_TYPES)
                if len(heads) == 1:
                    self.note = f'using {heads[0]}, the only head pose topic in {self.path}'
                    head_topic = heads[0]
        self.head_topic = head_topic
        #: Why the head topic cannot be read (None: it can).
        self.head_error = self._head_error(head_topic)
        self.head_type = self.topics.get(head_topic, HEAD_TYPES[0])
        if head_required:
            self.require_head()

    def _head_error(self, head_topic: str) -> ReplayError | None:
        """Why ``head_topic`` cannot be read as the head (None: it can)."""
        if head_topic not in self.topics:
            recorded = ', '.join(f'{t} ({ty})' for t, ty in sorted(self.topics.items()))
            if self.truncated:
                return ReplayError(
                    f'{self.path} is {self.truncation or "truncated (no footer)"}; the part '
                    f'that can be read has no topic {head_topic} (recorded: {recorded or "none"})')
            hint = (' or, for a head on /tf, head_frame (and fixed_frame) in the params file'
                    if TF_TOPIC in self.topics else '')
            return ReplayError(f'{self.path} has no topic {head_topic} (recorded: '
                               f'{recorded or "none"}); choose one with --head-topic{hint}')
        head_type = self.topics[head_topic]
        if head_type not in HEAD_TYPES:
            hint = ('; a head on TF needs head_frame (and fixed_frame) in the params file'
                    if head_type == TFMESSAGE_TYPE else '')
            return ReplayError(f'{self.path}: topic {head_topic} holds {head_type}, not a '
                               f'head pose ({" or ".join(HEAD_TYPES)}){hint}')
        return None

    def require_head(self) -> None:
        """Raise the reason the head topic cannot be read, if any."""
        if self.head_error is not None:
            raise self.head_error

    def use_tf_head(self, values) -> bool:
        """Take the head from the input's ``/tf`` and ``/tf_static`` (``head_frame`` set, and
        this is not a node recording holding the head it composed: that is replayed from its
        head topic). Then the composed poses are recorded on the node's ``head_pose``
        (:attr:`head_topic`, ``PoseStamped``). Raises ``ReplayError`` when the head can be read
        neither way."""
        if not values.get('head_frame') or (self.layout is not None
                                            and self.layout.head_topic in self.topics):
            self.require_head()
            return False
        if TF_TOPIC not in self.topics:
            raise ReplayError(f'{self.path} has no topic {TF_TOPIC} for the head from TF '
                              f'({values["fixed_frame"]} -> {values["head_frame"]}, head_frame)')
        for topic in (TF_TOPIC, TF_STATIC_TOPIC):
            if topic in self.topics and self.topics[topic] != TFMESSAGE_TYPE:
                raise ReplayError(f'{self.path}: topic {topic} holds {self.topics[topic]}, not '
                                  f'{TFMESSAGE_TYPE}')
        self.head_topic = resolve_topic(self.node, 'head_pose')
        self.head_type = HEAD_TYPES[0]
        self.head_error = None
        return True

    def messages(self, topics, raw=False):
        """``BagReader.messages`` in this input's order (:attr:`order`); ``raw``: as CDR
        bytes. Ends early, setting :attr:`stopped`, once :attr:`stop` is true (an
        ``interrupt.StopRequest``: SIGINT or SIGTERM arrived)."""
        for item in self.reader.messages(topics, order=self.order, raw=raw):
            if self.stop:
                self.stopped = True
                return
            yield item

    def truncated_warning(self) -> str:
        return (f'{self.path} is {self.truncation or "truncated (no footer)"}; replaying what '
                f'can be read (ponytail_replay repair makes it a complete, indexed file)')

    @property
    def node(self) -> str:
        return self.layout.node if self.layout else '/ponytail'

    def frame_topic(self, frame: str, configured: str) -> str:
        """Where frame ``frame``'s poses are: the recorded node's topic for it, else
        ``configured`` (``<frame>.topic``) resolved in the node's namespace."""
        if self.layout is not None and frame in self.layout.frames:
            return self.layout.frame_topics[self.layout.frames.index(frame)]
        return resolve_topic(self.node, configured)

    def tick_topic(self) -> str | None:
        """The node's first ``segment_poses`` topic, if this is a node recording with ticks."""
        if self.layout and self.layout.pose_topics[0] in self.topics:
            return self.layout.pose_topics[0]
        return None

    def message_count(self, topic: str) -> int:
        """Messages on ``topic`` by the final rosbag2 metadata (0 if unknown: truncated)."""
        try:
            bag = yaml.safe_load(self.metadata['rosbag2']['serialized_metadata'])
            return next(t['message_count'] for t in bag['topics_with_message_count']
                        if t['topic_metadata']['name'] == topic)
        except (KeyError, TypeError, StopIteration, yaml.YAMLError):
            return 0

    def span_ns(self) -> tuple[int, int] | None:
        """(first, last) log time of a finished bag, else None."""
        return self.reader.span_ns()


def head_pose(msg, head_type):
    """(position, orientation) tuples of a PoseStamped or TransformStamped."""
    if head_type == HEAD_TYPES[0]:
        p, q = msg.pose.position, msg.pose.orientation
    else:
        p, q = msg.transform.translation, msg.transform.rotation
    return (p.x, p.y, p.z), (q.x, q.y, q.z, q.w)


#: Head stamps further than this from their log times (median) are on another clock.
FOREIGN_CLOCK_S = 5.0
_STAMP_SAMPLE = 200


def head_stamps(inp: ReplayInput):
    """(header stamp, log time) ns of the first head poses."""
    out = []
    try:
        for _, _, data, log_ns in inp.messages({inp.head_topic: inp.head_type}, raw=True):
            # (a PoseStamped's stamp read from its bytes, as the replay reads its poses)
            fields = pose_stamped_fields(data) if inp.head_type == HEAD_TYPES[0] else None
            if fields is not None:
                out.append((fields[0] * 1_000_000_000 + fields[1], log_ns))
            else:
                msg: Any = deserialize_message(data, _message_class(inp.head_type))
                out.append((stamp_ns(msg.header.stamp), log_ns))
            if len(out) >= _STAMP_SAMPLE:
                break
    except BagError as exc:
        raise ReplayError(str(exc)) from None
    return out


def partial_note(path, metadata) -> str | None:
    """A line saying that ``path`` is the output of an interrupted replay (and up to which
    time it holds the run), or None."""
    record = metadata.get(RECORDING_METADATA) or {}
    if record.get('partial') != 'true':
        return None
    return (f'{path} is partial: {record.get("partial_reason", "its run was interrupted")}; it '
            f'holds the run up to log time {record.get("complete_until_ns", "?")} ns only')


def foreign_clock(inp: ReplayInput, head_stamps, stamp_source: str) -> str | None:
    """Why the head stamps cannot be used if they are on another clock than the log times (a
    bag stamped by a simulator clock from 0, or from another epoch) and would be used
    (``stamp_source: header``): the head motion would be estimated on one clock and simulated
    on the other. None if they are on the same clock (or not used)."""
    if stamp_source != 'header':
        return None
    pairs = [(s, l) for s, l in head_stamps if s]
    if not pairs:
        return None
    offset = float(np.median([s - l for s, l in pairs])) * 1e-9
    if abs(offset) <= FOREIGN_CLOCK_S:
        return None
    return (f'{inp.path}: the head pose stamps on {inp.head_topic} are {offset:+.6g} s off their '
            f'log times (another clock: a simulator from 0, or another machine); replaying by '
            f'them would be physically wrong. Use --stamp-source receive (stamp_source: receive '
            f'in the params file) to time the poses by their log times, or --stamp-source '
            f'header to use the stamps anyway')


def recorded_value(recorded: Mapping[str, str] | None, name: str, default: Any) -> Any:
    """A parameter's value in a recording's parameters metadata (JSON), else ``default``."""
    if recorded is None:
        return default
    try:
        return json.loads(recorded[name])
    except (KeyError, TypeError, ValueError):
        return default


def used_frame_names(values) -> set:
    """The frames some chain hangs from or some collider is fixed in."""
    frames = set(frame_names(values))
    used = {values[f'{c}.anchor'] for c in values['chains']}
    used |= {values[f'{c}.frame'] for c in values.get('colliders', ())}
    return frames & used


def event_values(event) -> dict[str, Any]:
    """The values a recorded ``ParameterEvent`` sets (new and changed), as plain Python."""
    from rclpy.parameter import Parameter
    changed = {}
    for p in list(event.new_parameters) + list(event.changed_parameters):
        value = Parameter.from_parameter_msg(p).value
        changed[p.name] = value if isinstance(value, (str, bool, int, float)) else list(value)
    return changed
