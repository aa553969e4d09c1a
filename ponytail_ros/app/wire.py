"""The tick's output as CDR bytes, laid out with NumPy: ``geometry_msgs/msg/PoseArray``,
``tf2_msgs/msg/TFMessage`` and ``visualization_msgs/msg/MarkerArray``, straight from the pose
arrays (no message objects).

What the node publishes (``Publisher.publish(bytes)``, rclpy's ``publish_raw``) and what the
recorder writes are these bytes: one encoding per tick, vectorised over the segments. They are
the bytes ``rclpy.serialization.serialize_message`` gives for the equivalent message with its
alignment gaps zeroed (``recording/cdr.py``'s canonical CDR; a test checks it byte for byte).

Layout (plain CDR, XCDR1, little endian, as ROS 2 uses it): a 4-byte encapsulation header
``00 01 00 00``, then the fields in order, each primitive aligned to its size relative to the
end of that header; a string is a ``uint32`` length counting its terminating NUL, the bytes,
the NUL; a sequence a ``uint32`` count, then its elements. Padding bytes are zero; the data
ends padded to a multiple of 4 bytes.

* ``PoseArray``: ``header.stamp`` (``int32`` sec, ``uint32`` nanosec), ``header.frame_id``,
  the count, then (aligned to 8) one block of 7 ``float64`` per pose: position x, y, z,
  orientation x, y, z, w;
* ``TFMessage``: the count, then per ``TransformStamped`` (aligned to 4) its stamp, the
  parent's ``frame_id``, the ``child_frame_id``, then (aligned to 8) translation x, y, z and
  rotation x, y, z, w;
* ``MarkerArray``: the count, then per ``Marker`` (aligned to 4) its header, ``ns``, ``id``,
  ``type``, ``action``, (aligned to 8) ``pose`` and ``scale`` (``float64``), ``color`` (4
  ``float32``), ``lifetime``, ``frame_locked``, ``points`` (count, then aligned to 8 three
  ``float64`` each), and the fields the node leaves empty (``colors``, ``texture_resource``,
  ``texture``, ``uv_coordinates``, ``text``, ``mesh_resource``, ``mesh_file``,
  ``mesh_use_embedded_materials``). What changes from tick to tick (stamps, poses, points) is
  a :class:`MarkerSpec`'s numbers; the rest is its layout's template.

Nothing here imports ROS: the layouts depend on the frame names and the segment count only,
so each is computed once (cached) and a tick fills in the stamp and the numbers.
"""
from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

__all__ = ['ENCAPSULATION', 'POSE_FLOATS', 'PoseArrayLayout', 'TFLayout', 'MarkerSpec',
           'MarkerArrayLayout', 'pose_array_layout', 'tf_layout', 'pose_array_cdr', 'pose_block',
           'pose_array_fields',
           'pose_stamped_fields', 'pose_stamped_cdr', 'is_canonical_pose_stamped',
           'tf_message_fields']

#: CDR little endian, options 0.
ENCAPSULATION = b'\x00\x01\x00\x00'
#: float64 numbers per pose: position x, y, z, orientation x, y, z, w.
POSE_FLOATS = 7

_U32 = struct.Struct('<I')
_I32X3 = struct.Struct('<3i')
_TIME = struct.Struct('<iI')
_VEC3 = struct.Struct('<3d')
_RGBA = struct.Struct('<4f')
_POSE = struct.Struct('<7d')
_F8 = np.dtype('<f8')
_U8 = np.dtype('<u8')


def _string(body: bytearray, text: str) -> None:
    """Append a CDR string at the end of ``body`` (its offsets relative to the CDR origin)."""
    data = text.encode('utf-8') + b'\x00'
    body += bytes(-len(body) % 4)
    body += _U32.pack(len(data)) + data


def pose_block(origins: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """The ``(n, 7)`` little-endian float64 block of ``origins`` ``(n, 3)`` and ``quats``
    ``(n, 4)`` (x, y, z, w), a pose per row as CDR lays poses out."""
    block = np.concatenate((origins, quats), axis=1)
    return block if block.dtype == _F8 else block.astype(_F8)


def _gather(size: int, at: np.ndarray, points_at: np.ndarray | None = None) -> np.ndarray:
    """The byte indices that make a message of a template of ``size`` bytes in one ``take``:
    from the template followed by the stamp (8 bytes), the poses (``(n, 7)`` float64, ``n =
    len(at)``) and the points (``(p, 3)`` float64); ``at`` ``(n, 64)``: where each row's stamp
    (8 bytes) and pose (56) go, ``points_at`` ``(p, 24)``: where each point goes."""
    gather = np.arange(size, dtype=np.intp)
    n = len(at)
    gather[at[:, :8]] = size + np.arange(8)
    gather[at[:, 8:]] = size + 8 + np.arange(8 * POSE_FLOATS * n).reshape(n, 8 * POSE_FLOATS)
    if points_at is not None and points_at.size:
        gather[points_at] = (size + 8 + 8 * POSE_FLOATS * n
                             + np.arange(points_at.size).reshape(points_at.shape))
    return gather


class PoseArrayLayout:
    """The CDR layout of a ``PoseArray`` of ``n`` poses in frame ``frame_id``.

    Attributes:
        n: the number of poses.
        frame_id: the header's frame.
        data_offset: byte offset of the first pose's block in the data (from its first byte,
            the encapsulation header's).
        size: length of the data, bytes.
    """

    def __init__(self, frame_id: str, n: int):
        self.frame_id = frame_id
        self.n = int(n)
        body = bytearray(8)                    # the stamp, filled in per message
        _string(body, frame_id)
        body += bytes(-len(body) % 4)
        body += _U32.pack(self.n)
        if self.n:
            body += bytes(-len(body) % 8)
        #: what follows the stamp up to the first pose (the frame, the count, padding)
        self._middle = bytes(body[8:])
        self.data_offset = len(ENCAPSULATION) + len(body)
        self.size = self.data_offset + 8 * POSE_FLOATS * self.n   # (a multiple of 4)

    def encode(self, sec: int, nanosec: int, block: np.ndarray) -> bytes:
        """The CDR of the message stamped ``(sec, nanosec)`` with poses ``block`` ``(n, 7)``
        (:func:`pose_block`; any float array of that shape, converted to little-endian
        float64)."""
        block = np.ascontiguousarray(block, dtype=_F8)
        if block.shape != (self.n, POSE_FLOATS):
            raise ValueError(f'expected poses of shape ({self.n}, {POSE_FLOATS}), '
                             f'got {block.shape}')
        return b''.join((ENCAPSULATION, _TIME.pack(sec, nanosec), self._middle,
                         block.tobytes()))

    def poses(self, data: bytes) -> np.ndarray:
        """The ``(n, 7)`` poses of ``data`` (this layout's CDR) as a read-only view."""
        return np.frombuffer(data, dtype=_F8, count=POSE_FLOATS * self.n,
                             offset=self.data_offset).reshape(self.n, POSE_FLOATS)


@lru_cache(maxsize=256)
def pose_array_layout(frame_id: str, n: int) -> PoseArrayLayout:
    """The (cached) :class:`PoseArrayLayout` of ``n`` poses in ``frame_id``."""
    return PoseArrayLayout(frame_id, n)


def pose_array_cdr(origins: np.ndarray, quats: np.ndarray, sec: int, nanosec: int,
                   frame_id: str) -> bytes:
    """CDR of the ``PoseArray`` with poses ``origins`` ``(n, 3)``, ``quats`` ``(n, 4)`` (x, y,
    z, w), stamped ``(sec, nanosec)``, in ``frame_id``."""
    return pose_array_layout(frame_id, len(origins)).encode(sec, nanosec,
                                                             pose_block(origins, quats))


class TFLayout:
    """The CDR layout of a ``TFMessage`` of one transform per child frame in ``children``, all
    children of ``parent`` with one stamp (a chain's segments as TF frames)."""

    def __init__(self, parent: str, children: Sequence[str]):
        self.parent = parent
        self.children = tuple(children)
        self.n = len(self.children)
        body = bytearray(_U32.pack(self.n))
        stamps, poses = [], []
        for child in self.children:
            body += bytes(-len(body) % 4)
            stamps.append(len(body))
            body += bytes(8)
            _string(body, parent)
            _string(body, child)
            body += bytes(-len(body) % 8)
            poses.append(len(body))
            body += bytes(8 * POSE_FLOATS)
        body += bytes(-len(body) % 4)
        self._template = np.frombuffer(ENCAPSULATION + bytes(body), dtype=np.uint8)
        h = len(ENCAPSULATION)
        #: byte indices ``(n, 64)`` of each transform's stamp (8 bytes) and numbers (56)
        self._at = np.concatenate([
            (h + np.array(stamps, dtype=np.intp)).reshape(-1, 1) + np.arange(8),
            (h + np.array(poses, dtype=np.intp)).reshape(-1, 1) + np.arange(8 * POSE_FLOATS)],
            axis=1)
        self.size = len(self._template)
        self._head = self._template.tobytes()
        self._gather = _gather(self.size, self._at)

    def encode(self, sec: int, nanosec: int, block: np.ndarray) -> bytes:
        """The CDR of the message stamped ``(sec, nanosec)``; transform ``i`` is row ``i`` of
        ``block`` ``(n, 7)`` (translation, rotation x, y, z, w)."""
        block = np.ascontiguousarray(block, dtype=_F8)
        if block.shape != (self.n, POSE_FLOATS):
            raise ValueError(f'expected poses of shape ({self.n}, {POSE_FLOATS}), '
                             f'got {block.shape}')
        return self.encode_raw(_TIME.pack(sec, nanosec), block.tobytes())

    def encode_raw(self, stamp: bytes, poses: bytes) -> bytes:
        """:meth:`encode` of the stamp's 8 CDR bytes (``int32`` sec, ``uint32`` nanosec) and
        the poses' ``n * 56`` (little-endian float64, a pose per 7; a ``PoseArray``'s block):
        one gather from the template and them."""
        src = np.frombuffer(b''.join((self._head, stamp, poses)), dtype=np.uint8)
        return src.take(self._gather).tobytes()


@lru_cache(maxsize=256)
def tf_layout(parent: str, children: tuple[str, ...]) -> TFLayout:
    """The (cached) :class:`TFLayout` of ``children`` (a tuple) under ``parent``."""
    return TFLayout(parent, children)


@dataclass(frozen=True)
class MarkerSpec:
    """What stays the same of a ``visualization_msgs/Marker`` from tick to tick: the header's
    stamp, the pose and the points (``n_points`` of them) are the tick's numbers; every field
    not named here keeps its default (empty, zero, false)."""

    ns: str
    id: int
    type: int
    action: int
    scale: tuple[float, float, float] = (0.0, 0.0, 0.0)
    color: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    n_points: int = 0


def _align(body: bytearray, n: int) -> None:
    body += bytes(-len(body) % n)


class MarkerArrayLayout:
    """The CDR layout of a ``MarkerArray`` of ``specs`` (:class:`MarkerSpec`), every marker in
    ``frame_id`` with one stamp: a template, and where each marker's stamp and pose and each
    point go."""

    def __init__(self, frame_id: str, specs: Sequence[MarkerSpec]):
        self.frame_id = frame_id
        self.specs = tuple(specs)
        self.n = len(self.specs)
        self.n_points = sum(s.n_points for s in self.specs)
        body = bytearray(_U32.pack(self.n))
        stamps: list[int] = []
        poses: list[int] = []
        points: list[int] = []
        for spec in self.specs:
            _align(body, 4)
            stamps.append(len(body))
            body += bytes(8)                                   # header.stamp
            _string(body, frame_id)                            # header.frame_id
            _string(body, spec.ns)
            _align(body, 4)
            body += _I32X3.pack(spec.id, spec.type, spec.action)
            _align(body, 8)
            poses.append(len(body))
            body += bytes(8 * POSE_FLOATS)                     # pose
            body += _VEC3.pack(*spec.scale)                    # scale
            body += _RGBA.pack(*spec.color)                    # color (float32)
            body += bytes(8)                                   # lifetime
            body += b'\x00'                                    # frame_locked
            _align(body, 4)
            body += _U32.pack(spec.n_points)                   # points
            if spec.n_points:
                _align(body, 8)
                points.extend(len(body) + 24 * k for k in range(spec.n_points))
                body += bytes(24 * spec.n_points)
            _align(body, 4)
            body += bytes(4)                                   # colors: []
            _string(body, '')                                  # texture_resource
            _align(body, 4)
            body += bytes(8)                                   # texture.header.stamp
            _string(body, '')                                  # texture.header.frame_id
            _string(body, '')                                  # texture.format
            _align(body, 4)
            body += bytes(4)                                   # texture.data: []
            body += bytes(4)                                   # uv_coordinates: []
            _string(body, '')                                  # text
            _string(body, '')                                  # mesh_resource
            _string(body, '')                                  # mesh_file.filename
            _align(body, 4)
            body += bytes(4)                                   # mesh_file.data: []
            body += b'\x00'                                    # mesh_use_embedded_materials
        #: Length of the data without the trailing padding to 4 bytes (as rmw serialises it).
        self.unpadded_size = len(ENCAPSULATION) + len(body)
        _align(body, 4)
        self._template = np.frombuffer(ENCAPSULATION + bytes(body), dtype=np.uint8)
        h = len(ENCAPSULATION)
        at = [(h + np.array(stamps, dtype=np.intp)).reshape(-1, 1) + np.arange(8),
              (h + np.array(poses, dtype=np.intp)).reshape(-1, 1) + np.arange(8 * POSE_FLOATS)]
        #: byte indices of the stamps and poses ``(n, 64)`` and of the points ``(p, 24)``
        self._at = np.concatenate(at, axis=1)
        self._points_at = (h + np.array(points, dtype=np.intp)).reshape(-1, 1) + np.arange(24)
        self.size = len(self._template)
        self._head = self._template.tobytes()
        self._gather = _gather(self.size, self._at, self._points_at)

    def encode(self, sec: int, nanosec: int, poses: np.ndarray, points: np.ndarray) -> bytes:
        """The CDR of the array stamped ``(sec, nanosec)``: marker ``i``'s pose is row ``i`` of
        ``poses`` ``(n, 7)``; its points are the next ``n_points`` rows of ``points``
        ``(p, 3)``, markers in order."""
        poses = np.ascontiguousarray(poses, dtype=_F8)
        points = np.ascontiguousarray(points, dtype=_F8)
        if poses.shape != (self.n, POSE_FLOATS) or points.shape != (self.n_points, 3):
            raise ValueError(f'expected poses ({self.n}, {POSE_FLOATS}) and points '
                             f'({self.n_points}, 3), got {poses.shape} and {points.shape}')
        src = np.frombuffer(b''.join((self._head, _TIME.pack(sec, nanosec), poses.tobytes(),
                                      points.tobytes())), dtype=np.uint8)
        return src.take(self._gather).tobytes()


def pose_stamped_fields(data: bytes) -> tuple[int, int, str, tuple[float, ...],
                                              tuple[float, ...]] | None:
    """``(sec, nanosec, frame_id, (x, y, z), (qx, qy, qz, qw))`` of the CDR of a
    ``geometry_msgs/msg/PoseStamped`` (what a raw subscription receives); None if ``data`` is
    not plain little-endian CDR of that layout, or its frame is not plain UTF-8 without a
    NUL inside (then deserialise it the usual way)."""
    if len(data) < 16 or data[0] != 0 or data[1] != 1:
        return None
    sec, nanosec = _TIME.unpack_from(data, 4)
    (length,) = _U32.unpack_from(data, 12)
    end = 16 + length                               # after the frame's NUL
    at = end + (-(end - len(ENCAPSULATION)) % 8)    # the pose, aligned to 8
    if length == 0 or at + 8 * POSE_FLOATS > len(data) or data[end - 1] != 0:
        return None
    frame = data[16:end - 1]
    if b'\x00' in frame:
        return None
    try:
        frame_id = frame.decode('utf-8')
    except UnicodeDecodeError:
        return None
    pose = _POSE.unpack_from(data, at)
    return sec, nanosec, frame_id, pose[:3], pose[3:]


def pose_array_fields(data: bytes) -> tuple[int, int, str, np.ndarray] | None:
    """``(sec, nanosec, frame_id, poses)`` of the CDR of a ``geometry_msgs/msg/PoseArray``,
    ``poses`` ``(n, 7)`` (x, y, z, qx, qy, qz, qw; a read-only view of ``data``); None if
    ``data`` is not plain little-endian CDR of that layout, or its frame is not plain UTF-8
    without a NUL inside (then deserialise it the usual way). The inverse of
    ``PoseArrayLayout.encode``."""
    if len(data) < 20 or data[0] != 0 or data[1] != 1:
        return None
    sec, nanosec = _TIME.unpack_from(data, 4)
    (length,) = _U32.unpack_from(data, 12)
    end = 16 + length                               # after the frame's NUL
    at = end + (-(end - len(ENCAPSULATION)) % 4)    # the count, aligned to 4
    if length == 0 or at + 4 > len(data) or data[end - 1] != 0:
        return None
    frame = data[16:end - 1]
    if b'\x00' in frame:
        return None
    try:
        frame_id = frame.decode('utf-8')
    except UnicodeDecodeError:
        return None
    (n,) = _U32.unpack_from(data, at)
    layout = pose_array_layout(frame_id, n)
    if layout.size > len(data):
        return None
    return sec, nanosec, frame_id, layout.poses(data)


def pose_stamped_cdr(sec: int, nanosec: int, frame_id: str, position, orientation) -> bytes:
    """The canonical CDR of a ``geometry_msgs/msg/PoseStamped`` (alignment gaps zeroed, no
    slack after the data: what ``recording.cdr.serialize_canonical`` gives): the inverse of
    ``pose_stamped_fields``, so a pose received as bytes is recorded without a message object."""
    body = bytearray(ENCAPSULATION)
    body += _TIME.pack(sec, nanosec)
    _string(body, frame_id)
    body += bytes(-(len(body) - len(ENCAPSULATION)) % 8)     # the pose, aligned to 8
    body += _POSE.pack(*position, *orientation)
    return bytes(body)


def is_canonical_pose_stamped(data: bytes) -> bool:
    """Whether ``data``, the CDR of a ``PoseStamped`` that ``pose_stamped_fields`` reads, is
    what ``pose_stamped_cdr`` makes of its fields: the encapsulation's options zero, the pose's
    alignment gap zeroed, nothing after the pose (the frame's bytes, the stamp and the numbers
    come back as they are)."""
    if len(data) < 16 or data[:4] != ENCAPSULATION:
        return False
    end = 16 + _U32.unpack_from(data, 12)[0]
    at = end + (-(end - len(ENCAPSULATION)) % 8)
    return len(data) == at + 8 * POSE_FLOATS and not any(data[end:at])


def _read_string(data: bytes, at: int) -> tuple[str, int]:
    """A CDR string at ``at`` (aligned to 4 from the encapsulation's end): its text and the
    offset after it. Raises ``ValueError`` when it does not fit or is not UTF-8."""
    at += -(at - len(ENCAPSULATION)) % 4
    (length,) = _U32.unpack_from(data, at)
    end = at + 4 + length
    if length == 0 or end > len(data) or data[end - 1] != 0:
        raise ValueError('bad string')
    return data[at + 4:end - 1].decode('utf-8'), end


def tf_message_fields(data: bytes) -> list[tuple[int, int, str, str, tuple[float, ...],
                                                  tuple[float, ...]]]:
    """The transforms of the CDR of a ``tf2_msgs/msg/TFMessage`` (``/tf``, ``/tf_static``) as
    ``(sec, nanosec, parent frame_id, child_frame_id, (x, y, z), (qx, qy, qz, qw))``: read with
    ``struct``, so neither ``tf2_msgs`` nor a message object is needed (the inverse of
    ``TFLayout.encode``). Raises ``ValueError`` if ``data`` is not little-endian plain CDR of
    that layout."""
    if len(data) < 8 or data[0] != 0 or data[1] != 1:
        raise ValueError('not little-endian plain CDR')
    try:
        (n,) = _U32.unpack_from(data, 4)
        at = 8
        out = []
        for _ in range(n):
            at += -(at - len(ENCAPSULATION)) % 4
            sec, nanosec = _TIME.unpack_from(data, at)
            parent, at = _read_string(data, at + 8)
            child, at = _read_string(data, at)
            at += -(at - len(ENCAPSULATION)) % 8
            pose = _POSE.unpack_from(data, at)
            at += 8 * POSE_FLOATS
            out.append((sec, nanosec, parent, child, pose[:3], pose[3:]))
    except (struct.error, UnicodeDecodeError) as exc:
        raise ValueError(f'not a TFMessage: {exc}') from None
    return out
