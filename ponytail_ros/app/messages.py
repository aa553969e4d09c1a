"""Segment poses to ROS messages: ``geometry_msgs/PoseArray`` and ``visualization_msgs`` markers.

A chain's poses of a tick are a ``SegmentPoses``: the CDR bytes of its ``PoseArray``, encoded
once from the pose arrays (``wire.py``), which the node publishes and the recorder writes as
they are; the ``PoseArray`` object (and the ``/tf`` bytes) only when asked for. The markers
likewise (``SegmentMarkers``): ``ChainMessages`` (per chain) and ``ColliderMarkers`` give their
``MarkerSpec``s (the same tuple while nothing changes) and each tick's poses and points, one
``MarkerArrayLayout`` encodes them. Building rclpy messages (allocation plus per-field type
checks) and converting them for rmw cost far more than the numbers; the node's inputs come in
as bytes too (``ReceivedPose``).

Conventions: a segment's pose has its origin at the proximal joint (towards the head) and its
local +X along the segment, so the distal joint is ``origin + R · (length, 0, 0)``. Markers:

* ``capsules``: one ``CYLINDER`` per segment (id 1..n; a cylinder's axis is its local Z, so its
  orientation is the segment's composed with +90° about Y) plus one ``SPHERE_LIST`` (id 0) with
  a sphere of the segment's diameter at every joint and at the tip;
* ``line``: a ``LINE_STRIP`` through the joints (id 1, width = the radius) plus the same
  ``SPHERE_LIST`` (id 0).

The marker namespace is the chain's name. Colliders (``ColliderMarkers``) are drawn in the
namespace ``colliders`` (id = the collider's index): a ``SPHERE``; a capsule as a ``CYLINDER``
(id 2k + 1000) and a ``SPHERE_LIST`` of its two end caps (id 2k + 1001); a plane as a thin
2 m × 2 m ``CUBE`` around its point. When the set of markers changes (style, segment count)
a ``DELETEALL`` is sent first so that nothing stale lingers in RViz/Foxglove.
"""
import math
from collections.abc import Sequence
from functools import lru_cache
from typing import NamedTuple, Optional

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseArray, PoseStamped
from visualization_msgs.msg import Marker, MarkerArray

from ponytail_ros.core.marker_kernels import chain_numbers, collider_numbers
from ponytail_ros.core.rotations import quat_from_two_vectors

from .wire import (
    MarkerArrayLayout,
    MarkerSpec,
    TFLayout,
    is_canonical_pose_stamped,
    pose_array_fields,
    pose_array_layout,
    pose_block,
    pose_stamped_cdr,
    pose_stamped_fields,
)

__all__ = ['SegmentPoses', 'SegmentMarkers', 'ReceivedPose', 'ReceivedPoses', 'Stamp', 'tf_cdr',
           'ChainMessages', 'ChainsMarkerNumbers', 'ColliderMarkers', 'DELETE_ALL',
           'IDENTITY_POSE', 'Q_Z_TO_X', 'COLLIDER_COLOR', 'TF_TOPIC', 'TF_QOS_DEPTH',
           'segment_frame']

#: The segments as TF frames: the topic (the node publishes it live, recordings hold it).
TF_TOPIC = '/tf'
#: tf2_ros's ``DynamicBroadcasterQoS``: reliable, volatile, keep last 100.
TF_QOS_DEPTH = 100


def segment_frame(prefix: str, chain: str, index: int) -> str:
    """The TF frame of segment ``index`` (0 = root) of ``chain``: ``<prefix><chain>/<index>``
    (one naming for the node's live ``/tf`` and the recorder's, ``recording/tf.py``)."""
    return f'{prefix}{chain}/{index}'

#: Colour of collider markers: translucent grey.
COLLIDER_COLOR = (0.6, 0.6, 0.65, 0.35)
#: Edge of the square drawn for a plane collider, m.
PLANE_SIZE = 2.0

#: Rotation by +90° about Y: takes a cylinder's axis (local Z) to local X.
Q_Z_TO_X = np.array([0.0, math.sqrt(0.5), 0.0, math.sqrt(0.5)])


# The markers' numbers in few NumPy calls (a tick's marker arrays are small, so the cost is
# per call), each element by the same floating-point operations in the same order as
# ``core.rotations`` (tests compare the bytes): a subtraction ``x - y`` as ``x + (-y)`` and a
# product's sign folded into a constant factor are exact.

#: ``quat_axis_x``: columns ``(y, x, x)``, ``(y, y, z)``, ``(z, w, w)``, ``(z, z, y)``.
_AXIS_X_TAKE = np.array([1, 0, 0, 1, 1, 2, 2, 3, 3, 2, 2, 1])
_AXIS_X_SIGN = np.array([1.0, 1.0, -1.0])


def _axis_x(q: np.ndarray) -> np.ndarray:
    """``quat_axis_x(q)`` of ``(n, 4)`` quaternions, bit for bit: ``1 - 2 (y² + z²)``,
    ``2 (x y + w z)``, ``2 (x z - w y)``."""
    g = q.take(_AXIS_X_TAKE, axis=1).reshape(len(q), 4, 3)
    e = 2.0 * (g[:, 0] * g[:, 1] + g[:, 2] * g[:, 3] * _AXIS_X_SIGN)
    e[:, 0] = 1.0 - e[:, 0]
    return e


def _times_constant(b) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``quat_multiply(a, b)`` for a constant ``b`` as ``((aw K0 + ax K1) + ay K2) + az K3``:
    the four ``K`` (``(4,)``, the signed components of ``b`` in each term of the product)."""
    bx, by, bz, bw = (float(v) for v in b)
    return (np.array([bx, by, bz, bw]), np.array([bw, -bz, by, -bx]),
            np.array([bz, bw, -bx, -by]), np.array([-by, bx, bw, -bz]))


_Q_Z_TO_X_TERMS = _times_constant(Q_Z_TO_X)


def _times_z_to_x(q: np.ndarray) -> np.ndarray:
    """``quat_multiply(q, Q_Z_TO_X)`` of ``(n, 4)`` quaternions, bit for bit."""
    k0, k1, k2, k3 = _Q_Z_TO_X_TERMS
    return ((q[:, 3:4] * k0 + q[:, 0:1] * k1) + q[:, 1:2] * k2) + q[:, 2:3] * k3


def _rotate(q, v):
    """``quat_rotate`` of one quaternion and vector (floats), bit for bit."""
    u0, u1, u2, w = q
    v0, v1, v2 = v
    t0, t1, t2 = 2.0 * (u1 * v2 - u2 * v1), 2.0 * (u2 * v0 - u0 * v2), 2.0 * (u0 * v1 - u1 * v0)
    return (v0 + w * t0 + (u1 * t2 - u2 * t1), v1 + w * t1 + (u2 * t0 - u0 * t2),
            v2 + w * t2 + (u0 * t1 - u1 * t0))


def _from_two_vectors(a, b):
    """``quat_from_two_vectors`` of two vectors (floats), bit for bit (norms summed in order,
    as NumPy reduces three or four numbers); antiparallel ones, or a zero vector, by it."""
    try:
        na = math.sqrt((a[0] * a[0] + a[1] * a[1]) + a[2] * a[2])
        a0, a1, a2 = a[0] / na, a[1] / na, a[2] / na
        nb = math.sqrt((b[0] * b[0] + b[1] * b[1]) + b[2] * b[2])
        b0, b1, b2 = b[0] / nb, b[1] / nb, b[2] / nb
        w = 1.0 + ((a0 * b0 + a1 * b1) + a2 * b2)
        if w < 1e-12:
            raise ZeroDivisionError  # (antiparallel: its own branch)
        x, y, z = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        n = math.sqrt(((x * x + y * y) + z * z) + w * w)
        return (x / n, y / n, z / n, w / n)
    except ZeroDivisionError:
        return tuple(quat_from_two_vectors(np.array(a, dtype=float),
                                           np.array(b, dtype=float)).tolist())


_Z_FLOATS = (0.0, 0.0, 1.0)


def _set_pose(pose, p, q):
    pos, ori = pose.position, pose.orientation
    pos.x, pos.y, pos.z = p
    ori.x, ori.y, ori.z, ori.w = q


class SegmentPoses:
    """One chain's segment poses of one tick, held as the CDR of its ``geometry_msgs/PoseArray``
    (encoded once, ``wire.py``): what is published and recorded. Immutable: the arrays are
    read-only views of the bytes.

    Args:
        chain: the chain's name (its TF frames are ``<prefix><chain>/<i>``).
        origins, quats: ``(n, 3)`` and ``(n, 4)`` (x, y, z, w), root first.
        frame_id: the ``header.frame_id``.
        stamp_ns: the ``header.stamp``, integer ns.
    """

    __slots__ = ('chain', 'frame_id', 'stamp_ns', 'cdr', '_layout', '_message', '_tf')

    def __init__(self, chain: str, origins, quats, frame_id: str, stamp_ns: int):
        self.chain = chain
        self.frame_id = frame_id
        self.stamp_ns = int(stamp_ns)
        self._layout = pose_array_layout(frame_id, len(origins))
        sec, nanosec = self.stamp
        #: The ``PoseArray``'s CDR (encapsulation header included, padding zeroed).
        self.cdr: bytes = self._layout.encode(sec, nanosec, pose_block(origins, quats))
        self._message: PoseArray | None = None
        self._tf: dict[str, bytes] = {}

    @property
    def n(self) -> int:
        return self._layout.n

    @property
    def stamp(self):
        """``(sec, nanosec)`` of the stamp (as ``builtin_interfaces/Time`` splits it)."""
        return self.stamp_ns // 1_000_000_000, self.stamp_ns % 1_000_000_000

    @property
    def pose_bytes(self) -> bytes:
        """The poses' bytes in the CDR: ``n`` times 7 little-endian float64."""
        return self.cdr[self._layout.data_offset:]

    @property
    def poses(self) -> np.ndarray:
        """``(n, 7)``: position x, y, z, orientation x, y, z, w per segment (read-only)."""
        return self._layout.poses(self.cdr)

    @property
    def origins(self) -> np.ndarray:
        return self.poses[:, :3]

    @property
    def orientations(self) -> np.ndarray:
        return self.poses[:, 3:]

    def message(self) -> PoseArray:
        """The ``PoseArray`` (built on the first call; the same object after)."""
        if self._message is None:
            msg = PoseArray()
            msg.header.frame_id = self.frame_id
            sec, nanosec = self.stamp
            msg.header.stamp = Time(sec=sec, nanosec=nanosec)
            poses = []
            for row in self.poses.tolist():
                pose = Pose()
                _set_pose(pose, row[:3], row[3:])
                poses.append(pose)
            msg.poses = poses
            self._message = msg
        return self._message

    def tf_cdr(self, prefix: str = '') -> bytes:
        """CDR of the ``tf2_msgs/TFMessage`` of the segments: segment ``i`` as the frame
        ``segment_frame(prefix, chain, i)``, child of ``frame_id``, at the stamp."""
        data = self._tf.get(prefix)
        if data is None:
            data = self._tf[prefix] = tf_cdr((self,), prefix)
        return data


def tf_cdr(segments: Sequence[SegmentPoses], prefix: str = '') -> bytes:
    """CDR of one ``tf2_msgs/TFMessage`` holding the segments of every chain in ``segments``
    (one tick's, so one frame and one stamp), chain after chain, root first."""
    first = segments[0]
    layout = _tf_layout(first.frame_id, prefix, tuple((s.chain, s.n) for s in segments))
    # (the PoseArray's CDR holds the stamp and the poses as the TFMessage's do)
    poses = (first.pose_bytes if len(segments) == 1
             else b''.join([s.pose_bytes for s in segments]))
    return layout.encode_raw(first.cdr[4:12], poses)


@lru_cache(maxsize=256)
def _tf_layout(frame_id: str, prefix: str, chains: tuple[tuple[str, int], ...]) -> TFLayout:
    """The ``TFLayout`` of the segments of ``chains`` (``(name, n_segments)``) under
    ``frame_id`` (the frame names built once, not every tick)."""
    return TFLayout(frame_id, [segment_frame(prefix, c, i) for c, n in chains for i in range(n)])


class Stamp(NamedTuple):
    """A header stamp (as ``builtin_interfaces/Time``: ``sec``, ``nanosec``)."""

    sec: int
    nanosec: int


class ReceivedPose:
    """A ``geometry_msgs/PoseStamped`` as received in CDR bytes (the node's raw input
    subscriptions), its fields decoded with ``struct`` (``wire.pose_stamped_fields``); the
    message object only when asked for (a recorder).

    Build with :meth:`decode`, None when the bytes need rclpy's deserialisation instead.
    """

    __slots__ = ('cdr', 'stamp', 'frame_id', 'position', 'orientation', '_message')

    def __init__(self, cdr: bytes, stamp: Stamp, frame_id: str, position, orientation):
        self.cdr = cdr
        self.stamp = stamp
        self.frame_id = frame_id
        self.position = position
        self.orientation = orientation
        self._message: PoseStamped | None = None

    @classmethod
    def decode(cls, cdr: bytes) -> Optional['ReceivedPose']:
        fields = pose_stamped_fields(cdr)
        if fields is None:
            return None
        sec, nanosec, frame_id, position, orientation = fields
        return cls(cdr, Stamp(sec, nanosec), frame_id, position, orientation)

    def canonical_cdr(self) -> bytes:
        """The pose's canonical CDR (``wire.pose_stamped_cdr``): what the recorder writes. The
        bytes received may carry uninitialised padding or slack (``recording.cdr``); when they
        are canonical already (``wire.is_canonical_pose_stamped``), they are it."""
        if is_canonical_pose_stamped(self.cdr):
            return self.cdr
        return pose_stamped_cdr(self.stamp.sec, self.stamp.nanosec, self.frame_id,
                                self.position, self.orientation)

    def message(self) -> PoseStamped:
        """The ``PoseStamped`` (built on the first call; the same object after)."""
        if self._message is None:
            msg = PoseStamped()
            msg.header.stamp = Time(sec=self.stamp.sec, nanosec=self.stamp.nanosec)
            msg.header.frame_id = self.frame_id
            _set_pose(msg.pose, self.position, self.orientation)
            self._message = msg
        return self._message


class ReceivedPoses:
    """A ``geometry_msgs/PoseArray`` of input poses (``frames_topic``: every extra frame's pose
    in one message, in the order of ``frames``), as received in CDR bytes or as a message.

    ``poses`` ``(n, 7)``: x, y, z, qx, qy, qz, qw per pose. Build with :meth:`decode` (None when
    the bytes need rclpy's deserialisation) or :meth:`of_message`.
    """

    __slots__ = ('stamp', 'frame_id', 'poses', '_message')

    def __init__(self, stamp: Stamp, frame_id: str, poses: np.ndarray):
        self.stamp = stamp
        self.frame_id = frame_id
        self.poses = poses
        self._message: PoseArray | None = None

    @classmethod
    def decode(cls, cdr: bytes) -> Optional['ReceivedPoses']:
        fields = pose_array_fields(cdr)
        if fields is None:
            return None
        sec, nanosec, frame_id, poses = fields
        return cls(Stamp(sec, nanosec), frame_id, poses)

    @classmethod
    def of_message(cls, msg: PoseArray) -> 'ReceivedPoses':
        poses = np.array([(p.position.x, p.position.y, p.position.z, p.orientation.x,
                           p.orientation.y, p.orientation.z, p.orientation.w)
                          for p in msg.poses], dtype=float).reshape(-1, 7)
        out = cls(Stamp(msg.header.stamp.sec, msg.header.stamp.nanosec), msg.header.frame_id,
                  poses)
        out._message = msg
        return out

    def __len__(self) -> int:
        return len(self.poses)

    def canonical_cdr(self) -> bytes:
        """The canonical CDR of the message (``wire.PoseArrayLayout``): what the recorder
        writes."""
        layout = pose_array_layout(self.frame_id, len(self.poses))
        return layout.encode(self.stamp.sec, self.stamp.nanosec, self.poses)

    def message(self) -> PoseArray:
        """The ``PoseArray`` (built on the first call; the same object after)."""
        if self._message is None:
            msg = PoseArray()
            msg.header.stamp = Time(sec=self.stamp.sec, nanosec=self.stamp.nanosec)
            msg.header.frame_id = self.frame_id
            poses = []
            for row in self.poses.tolist():
                pose = Pose()
                _set_pose(pose, row[:3], row[3:])
                poses.append(pose)
            msg.poses = poses
            self._message = msg
        return self._message


class SegmentMarkers:
    """One tick's ``visualization_msgs/MarkerArray`` held as its CDR (encoded once from the
    markers' specs and numbers, ``wire.MarkerArrayLayout``): what is published and recorded.

    Args:
        layout: the ``MarkerArrayLayout`` (frame and marker specs).
        stamp_ns: every marker's ``header.stamp``, integer ns.
        poses: ``(n, 7)``, a pose per marker; points: ``(p, 3)``, the markers' points in order.
    """

    __slots__ = ('layout', 'stamp_ns', 'poses', 'points', 'cdr', '_message')

    def __init__(self, layout: MarkerArrayLayout, stamp_ns: int, poses: np.ndarray,
                 points: np.ndarray):
        self.layout = layout
        self.stamp_ns = int(stamp_ns)
        self.poses = poses
        self.points = points
        sec, nanosec = self.stamp_ns // 1_000_000_000, self.stamp_ns % 1_000_000_000
        #: The ``MarkerArray``'s CDR (encapsulation header included, padding zeroed).
        self.cdr: bytes = layout.encode(sec, nanosec, poses, points)
        self._message: MarkerArray | None = None

    @property
    def wire(self) -> bytes:
        """The CDR as rmw serialises the message (what the node publishes): ``cdr`` without
        the zeros that pad it to a multiple of 4 bytes (a ``Marker`` ends with a bool)."""
        return self.cdr[:self.layout.unpadded_size]

    def message(self) -> MarkerArray:
        """The ``MarkerArray`` (built on the first call; the same object after)."""
        if self._message is None:
            stamp = Time(sec=self.stamp_ns // 1_000_000_000,
                         nanosec=self.stamp_ns % 1_000_000_000)
            markers, k = [], 0
            points = self.points.tolist()
            for spec, row in zip(self.layout.specs, self.poses.tolist(), strict=True):
                m = Marker()
                m.header.frame_id = self.layout.frame_id
                m.header.stamp = stamp
                m.ns, m.id, m.type, m.action = spec.ns, spec.id, spec.type, spec.action
                _set_pose(m.pose, row[:3], row[3:])
                m.scale.x, m.scale.y, m.scale.z = spec.scale
                c = m.color
                c.r, c.g, c.b, c.a = spec.color
                if spec.n_points:
                    pts = []
                    for xyz in points[k:k + spec.n_points]:
                        pt = Point()
                        pt.x, pt.y, pt.z = xyz
                        pts.append(pt)
                    m.points = pts
                    k += spec.n_points
                markers.append(m)
            self._message = MarkerArray(markers=markers)
        return self._message


#: The pose of a marker drawn by its points (and of the DELETEALL): the identity.
IDENTITY_POSE = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
#: ``Marker.DELETEALL`` (namespace '', id 0).
DELETE_ALL = MarkerSpec('', 0, Marker.ARROW, Marker.DELETEALL)
_NO_POINTS = np.zeros((0, 3))


def _rgba(color) -> tuple:
    return (float(color[0]), float(color[1]), float(color[2]), float(color[3]))


class ChainMessages:
    """The marker specs of one chain (``name``, segment ``lengths`` ``(n,)``, ``radius`` m)
    and the tick's ``SegmentPoses``."""

    def __init__(self, name, lengths, radius):
        self.name = name
        self.lengths = np.asarray(lengths, dtype=float)
        self._lengths_column = self.lengths[:, None]
        self.radius = float(radius)
        self.n = len(self.lengths)
        self._style = None
        self._color = None
        self._specs: tuple = ()

    def segment_poses(self, origins, quats, frame_id, stamp_ns) -> SegmentPoses:
        """The tick's ``SegmentPoses`` (origins ``(n, 3)``, quats ``(n, 4)``)."""
        return SegmentPoses(self.name, origins, quats, frame_id, stamp_ns)

    def _build_specs(self, style, color):
        r, rgba = self.radius, _rgba(color)
        specs = [MarkerSpec(self.name, 0, Marker.SPHERE_LIST, Marker.ADD, (2.0 * r,) * 3,
                            rgba, self.n + 1)]
        if style == 'capsules':
            specs += [MarkerSpec(self.name, i + 1, Marker.CYLINDER, Marker.ADD,
                                 (2.0 * r, 2.0 * r, float(self.lengths[i])), rgba)
                      for i in range(self.n)]
        elif style == 'line':
            specs.append(MarkerSpec(self.name, 1, Marker.LINE_STRIP, Marker.ADD, (r, 0.0, 0.0),
                                    rgba, self.n + 1))
        self._specs = tuple(specs)
        self._style = style
        self._color = color

    def set_color(self, color):
        """The chain's colour (``(r, g, b, a)``) from now on."""
        if self._style not in (None, 'off'):
            self._build_specs(self._style, color)
        self._color = color

    def marker_specs(self, style, color):
        """The chain's marker specs (a tuple, the same object while nothing changes; empty for
        style 'off') and whether the set of marker ids changed since the last call (then send
        a DELETEALL first)."""
        if style == 'off':
            changed = self._style not in (None, 'off')
            self._style = 'off'
            self._specs = ()
            return (), changed
        changed = style != self._style
        if changed or color != self._color:
            self._build_specs(style, color)
        return self._specs, changed

    def markers(self, origins, quats, style, color):
        """Markers of the chain: their specs (``marker_specs``), poses ``(k, 7)``, points
        ``(p, 3)``, and whether the set of marker ids changed since the last call."""
        specs, changed = self.marker_specs(style, color)
        if style == 'off':
            return (), np.zeros((0, 7)), _NO_POINTS, changed
        axes = _axis_x(quats) * self._lengths_column
        joints = np.concatenate([origins, origins[-1:] + axes[-1:]])
        if style == 'capsules':
            poses = np.empty((self.n + 1, 7))
            poses[0] = IDENTITY_POSE
            poses[1:, :3] = origins + 0.5 * axes
            poses[1:, 3:] = _times_z_to_x(quats)
            return self._specs, poses, joints, changed
        return (self._specs, np.stack([IDENTITY_POSE, IDENTITY_POSE]),
                np.concatenate([joints, joints]), changed)


class ChainsMarkerNumbers:
    """The marker poses and points of several chains laid end to end (rows ``starts[c] ..
    starts[c] + n_c - 1`` of one tick's ``(N, 3)`` origins and ``(N, 4)`` quaternions), in one
    pass over all segments: bit for bit each ``ChainMessages.markers``' numbers, concatenated
    in chain order (the same element-wise operations on longer arrays). A crowd's marker tick
    costs a few NumPy calls instead of a few per chain."""

    def __init__(self, counts: Sequence[int], lengths: np.ndarray):
        n_seg = np.asarray(counts, dtype=np.int64)     # segments of each chain
        c = np.arange(len(n_seg))
        starts = np.concatenate([[0], np.cumsum(n_seg)[:-1]]).astype(np.int64)
        chain_of = np.repeat(c, n_seg)
        self.n = int(n_seg.sum())
        self.n_chains = len(n_seg)
        self._lengths = np.ascontiguousarray(lengths, dtype=float)
        self._last = starts + n_seg - 1                 # each chain's tip segment
        # capsules: chain c's rows in poses: its sphere list (identity), then its segments
        self._identity_rows = starts + c
        self._capsule_rows = np.arange(self.n) + chain_of + 1
        # its n + 1 joints in points: the segments' origins, then the tip
        self._origin_rows = np.arange(self.n) + chain_of
        self._tip_rows = starts + n_seg + c
        # line: chain c's points are its joints twice (the sphere list's, the strip's)
        joint_rows = np.arange(self.n + self.n_chains)
        joint_chain = np.repeat(c, n_seg + 1)
        first = np.concatenate([[0], np.cumsum(n_seg + 1)[:-1]])
        self._line_rows = np.concatenate([joint_rows + first[joint_chain],
                                          joint_rows + first[joint_chain] + n_seg[joint_chain]
                                          + 1])

    def numbers(self, origins: np.ndarray, quats: np.ndarray, style: str):
        """``(poses, points)`` of style 'capsules' or 'line' (as ``ChainMessages.markers``),
        computed in one compiled call (``core.marker_kernels.chain_numbers``)."""
        if origins.shape != (self.n, 3) or quats.shape != (self.n, 4):
            raise ValueError(f'origins {origins.shape} and quats {quats.shape} must be '
                             f'({self.n}, 3) and ({self.n}, 4): one row per segment')
        capsules = style == 'capsules'
        joints = np.empty((self.n + self.n_chains, 3))
        poses = np.empty((self.n + self.n_chains, 7) if capsules else (0, 7))
        chain_numbers(np.ascontiguousarray(origins, dtype=float),
                      np.ascontiguousarray(quats, dtype=float), self._lengths, self._last,
                      self._origin_rows, self._tip_rows, self._capsule_rows, self._identity_rows,
                      capsules, *_Q_Z_TO_X_TERMS, poses, joints)
        if capsules:
            return poses, joints
        points = np.empty((2 * len(joints), 3))
        points[self._line_rows] = np.concatenate([joints, joints])
        return np.tile(IDENTITY_POSE, (2 * self.n_chains, 1)), points


_Z = np.array([0.0, 0.0, 1.0])


def _unit(v):
    return v / np.linalg.norm(v)


class ColliderMarkers:
    """Markers of the scene's colliders (namespace ``colliders``), posed by the kinematic
    bodies they are fixed in."""

    def __init__(self):
        self._key = None
        self._specs: tuple = ()
        self._local: list = []
        self._local_floats: list = []
        self._z = _Z.tolist()
        self._last_body = -1                # the largest body a collider is fixed in

    def _build(self, colliders):
        #: per collider its centre and unit axis in its body (the sphere's: +Z)
        self._local = [(np.asarray(c.center, float),
                        _unit(np.asarray(c.axis, float)) if c.kind != 'sphere' else _Z)
                       for c in colliders]
        self._local_floats = [(centre.tolist(), axis.tolist()) for centre, axis in self._local]
        # The same as arrays: rows of centres and axes, the body-fixed ones (``_moving``) and
        # their bodies, each collider's pose row (a capsule's is followed by an identity row
        # for its end spheres), the capsules and their half lengths.
        self._centres = np.array([c for c, _ in self._local_floats], dtype=float).reshape(-1, 3)
        self._axes = np.array([a for _, a in self._local_floats], dtype=float).reshape(-1, 3)
        self._moving = np.array([k for k, c in enumerate(colliders) if c.body is not None],
                                dtype=np.intp)
        self._bodies = np.array([colliders[k].body for k in self._moving], dtype=np.intp)
        self._last_body = int(self._bodies.max()) if self._bodies.size else -1
        rows = np.cumsum([0] + [2 if c.kind == 'capsule' else 1 for c in colliders])
        self._pose_rows, self._n_rows = rows[:-1], int(rows[-1])
        self._capsules = np.array([k for k, c in enumerate(colliders) if c.kind == 'capsule'],
                                  dtype=np.intp)
        self._identity_rows = self._pose_rows[self._capsules] + 1
        self._half_lengths = np.array([colliders[k].half_length for k in self._capsules],
                                      dtype=float)
        color = COLLIDER_COLOR
        specs = []
        for k, c in enumerate(colliders):
            if c.kind == 'sphere':
                specs.append(MarkerSpec('colliders', k, Marker.SPHERE, Marker.ADD,
                                        (2.0 * c.radius,) * 3, color))
            elif c.kind == 'capsule':
                specs += [MarkerSpec('colliders', 2 * k + 1000, Marker.CYLINDER, Marker.ADD,
                                     (2.0 * c.radius, 2.0 * c.radius,
                                      max(2.0 * c.half_length, 1e-6)), color),
                          MarkerSpec('colliders', 2 * k + 1001, Marker.SPHERE_LIST, Marker.ADD,
                                     (2.0 * c.radius,) * 3, color, 2)]
            else:
                specs.append(MarkerSpec('colliders', k, Marker.CUBE, Marker.ADD,
                                        (PLANE_SIZE, PLANE_SIZE, 1e-3), color))
        self._specs = tuple(specs)

    def markers(self, colliders, bodies, style):
        """Markers of ``colliders`` (``ColliderSpec``s) with the kinematic bodies ``bodies``
        (``KinematicState``; a collider with ``body None`` is static): specs, poses, points
        (as ``ChainMessages.markers``), and whether the set of marker ids changed since the
        last call."""
        key = None if style == 'off' or not colliders else tuple(colliders)
        changed = key != self._key and self._key is not None
        if key != self._key:
            self._key = key
            self._specs = ()
            if key is not None:
                self._build(colliders)
        if key is None:
            return (), np.zeros((0, 7)), _NO_POINTS, changed
        # Every collider in one compiled call (a crowd has one skull per character), each
        # number by the arithmetic of ``_rotate`` and ``_from_two_vectors``, so the same bits.
        if self._last_body >= len(bodies.position):
            raise ValueError(f'a collider is fixed in body {self._last_body}; the kinematic '
                             f'bodies given are 0 to {len(bodies.position) - 1}')
        centres, axes = self._centres.copy(), self._axes.copy()
        poses = np.empty((self._n_rows, 7))
        points = np.empty((2 * len(self._capsules), 3))
        degenerate = np.empty(len(centres), dtype=np.bool_)
        if collider_numbers(centres, axes, self._moving, self._bodies,
                            np.ascontiguousarray(bodies.position, dtype=float),
                            np.ascontiguousarray(bodies.orientation, dtype=float),
                            self._pose_rows, self._identity_rows, self._capsules,
                            self._half_lengths, poses, points, degenerate):
            for k in np.flatnonzero(degenerate).tolist():   # zero or opposite +Z: by its branch
                poses[self._pose_rows[k], 3:] = _from_two_vectors(_Z_FLOATS, axes[k].tolist())
        return (self._specs, poses, points, changed)
