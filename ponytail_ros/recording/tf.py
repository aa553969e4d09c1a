"""Segments as TF frames: ``tf2_msgs/msg/TFMessage`` on ``/tf``, written by hand.

Downstream users attach meshes (hair cards, a sword) to frames, the way ``robot_state_publisher``
feeds RViz and Foxglove. Each chain's ``PoseArray`` becomes one ``TFMessage``: one
``TransformStamped`` per segment, parent ``header.frame_id`` of the ``PoseArray`` (the outputs'
frame: ``fixed_frame`` with the head from TF, else the head poses'), child
``<prefix><chain>/<i>`` (``i`` from 0 at the root; the node's prefix defaults to its namespace,
``docs/tf.md``), stamp the tick's,
translation and rotation the segment pose's -- so Foxglove and RViz show a frame tree from a
recording alone.

``tf2_msgs`` is not among the ROS 2 PyPI wheels, so nothing here imports it: the ``ros2msg``
schema is the type's ``.msg`` text (:data:`TFMESSAGE_MSG`, as in ros2/geometry2) followed by its
dependencies from the installed ``geometry_msgs`` (``bag.message_definition_of_text``, exactly
as rosbag2 writes it), the CDR is laid out by hand (plain CDR, little endian, padding zeroed, as
``cdr.py`` makes rclpy's): a tick's by ``app/wire.py`` from its pose arrays
(``SegmentPoses.tf_cdr``), a ``PoseArray`` message's by :func:`tf_from_pose_array`, and the
``RIHS01`` type hash is computed from the type description as
``rosidl_generator_type_description`` does (:func:`tfmessage_type_hash`).
"""
from __future__ import annotations

import hashlib
import json
import struct
from collections.abc import Iterable, Sequence
from functools import cache
from typing import Any

from ponytail_ros.app.messages import TF_QOS_DEPTH, TF_TOPIC, segment_frame

__all__ = ['TFMESSAGE_TYPE', 'TFMESSAGE_MSG', 'TF_TOPIC', 'TF_QOS_DEPTH', 'tf_message_cdr',
           'segment_frame', 'tf_from_pose_array', 'tfmessage_type_hash',
           'type_description_hash', 'tf2_msgs_available']

TFMESSAGE_TYPE = 'tf2_msgs/msg/TFMessage'
#: ``tf2_msgs/msg/TFMessage.msg`` of ros2/geometry2, byte for byte.
TFMESSAGE_MSG = 'geometry_msgs/TransformStamped[] transforms\n'

_U32 = struct.Struct('<I')
_TIME = struct.Struct('<iI')
_POSE = struct.Struct('<7d')
_HEADER = b'\x00\x01\x00\x00'  # CDR little endian, options 0
# rosidl type ids (type_description_interfaces/msg/FieldType)
_NESTED_UNBOUNDED_SEQUENCE = 145


def _string(out: bytearray, text: str) -> None:
    data = text.encode('utf-8') + b'\x00'
    out += bytes(-len(out) % 4)
    out += _U32.pack(len(data)) + data


def tf_message_cdr(transforms: Iterable[tuple[int, int, str, str, Sequence[float],
                                              Sequence[float]]]) -> bytes:
    """CDR of a ``TFMessage`` holding ``(sec, nanosec, frame_id, child_frame_id, (x, y, z),
    (qx, qy, qz, qw))`` transforms. Alignment is relative to the end of the 4-byte
    encapsulation header; padding bytes are zero; the data ends padded to 4 bytes."""
    body = bytearray()
    items = list(transforms)
    body += _U32.pack(len(items))
    for sec, nanosec, frame_id, child, t, q in items:
        body += bytes(-len(body) % 4)
        body += _TIME.pack(sec, nanosec)
        _string(body, frame_id)
        _string(body, child)
        body += bytes(-len(body) % 8)
        body += _POSE.pack(float(t[0]), float(t[1]), float(t[2]),
                           float(q[0]), float(q[1]), float(q[2]), float(q[3]))
    body += bytes(-len(body) % 4)
    return _HEADER + bytes(body)


def tf_from_pose_array(msg, chain: str, prefix: str = '') -> bytes:
    """The ``TFMessage`` CDR of one chain's ``PoseArray``: segment ``i`` as frame
    ``<prefix><chain>/<i>`` in the array's frame, at its stamp."""
    stamp, parent = msg.header.stamp, msg.header.frame_id
    return tf_message_cdr(
        (stamp.sec, stamp.nanosec, parent, segment_frame(prefix, chain, i),
         (p.position.x, p.position.y, p.position.z),
         (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w))
        for i, p in enumerate(msg.poses))


def type_description_hash(type_name: str, fields: Sequence[dict]) -> str:
    """``RIHS01_<sha256>`` of a message type whose own fields are ``fields`` (type description
    dicts, as in the installed ``.json`` files) and whose nested types are installed: the
    referenced descriptions are read from their packages' ``.json`` files, then hashed as
    ``rosidl_generator_type_description.calculate_type_hash`` does. '' if a dependency has no
    type description installed."""
    from .bag.msgdefs import _interface_file
    described: dict[str, dict[str, Any]] = {
        type_name: {'type_name': type_name, 'fields': [dict(f) for f in fields]}}
    pending = [f['type']['nested_type_name'] for f in fields if f['type']['nested_type_name']]
    while pending:
        name = pending.pop()
        if name in described:
            continue
        try:
            data = json.loads(_interface_file(name, '.json').read_text(encoding='utf-8'))
        except (OSError, ValueError, Exception):  # noqa: BLE001 - BagError: not installed
            return ''
        msg = data['type_description_msg']
        for d in [msg['type_description'], *msg['referenced_type_descriptions']]:
            described.setdefault(d['type_name'], d)
        pending += [f['type']['nested_type_name'] for f in msg['type_description']['fields']
                    if f['type']['nested_type_name']]
    references, queue = set(), [type_name]
    while queue:
        for f in described[queue.pop()]['fields']:
            nested = f['type']['nested_type_name']
            if nested and nested not in references:
                references.add(nested)
                queue.append(nested)

    def strip(d):
        return {'type_name': d['type_name'],
                'fields': [{k: v for k, v in f.items() if k != 'default_value'}
                           for f in d['fields']]}
    hashable = {'type_description': strip(described[type_name]),
                'referenced_type_descriptions': [strip(described[n])
                                                 for n in sorted(references)]}
    text = json.dumps(hashable, ensure_ascii=True, separators=(', ', ': '), sort_keys=False)
    return 'RIHS01_' + hashlib.sha256(text.encode('utf-8')).hexdigest()


@cache
def tfmessage_type_hash() -> str:
    """The ``RIHS01`` hash of ``tf2_msgs/msg/TFMessage``."""
    return type_description_hash(TFMESSAGE_TYPE, [{
        'name': 'transforms',
        'type': {'type_id': _NESTED_UNBOUNDED_SEQUENCE, 'capacity': 0, 'string_capacity': 0,
                 'nested_type_name': 'geometry_msgs/msg/TransformStamped'},
        'default_value': ''}])


def tf2_msgs_available() -> bool:
    """Whether ``tf2_msgs`` (the Python message package) can be imported."""
    try:
        import tf2_msgs.msg  # noqa: F401
    except ImportError:
        return False
    return True
