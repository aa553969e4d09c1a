"""Segment poses to ROS messages: ``geometry_msgs/PoseArray`` and ``visualization_msgs`` markers.

A chain's poses of a tick are a ``SegmentPoses``: the CDR bytes of its ``PoseArray``, encoded
once from the pose arrays (``wire.py``), which the node publishes and the recorder writes as
they are; the ``PoseArray`` object (and the ``/tf`` bytes) only when asked for. One
``ChainMessages`` per chain keeps its marker objects and refills them each tick (building rclpy
messages is the expensive part of publishing: allocation plus per-field type checks).

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
from typing import Dict, Optional, Sequence

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseArray
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker

import numpy as np

from ponytail_ros.core.rotations import (quat_axis_x, quat_from_two_vectors, quat_multiply,
                                         quat_rotate)

from .wire import pose_array_layout, pose_block, tf_layout

__all__ = ['SegmentPoses', 'tf_cdr', 'ChainMessages', 'ColliderMarkers', 'delete_all_marker',
           'Q_Z_TO_X', 'COLLIDER_COLOR', 'TF_TOPIC', 'TF_QOS_DEPTH', 'segment_frame']

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


def delete_all_marker(frame_id, stamp):
    m = Marker()
    m.header.frame_id = frame_id
    m.header.stamp = stamp
    m.action = Marker.DELETEALL
    return m


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
        self._message: Optional[PoseArray] = None
        self._tf: Dict[str, bytes] = {}

    @property
    def n(self) -> int:
        return self._layout.n

    @property
    def stamp(self):
        """``(sec, nanosec)`` of the stamp (as ``builtin_interfaces/Time`` splits it)."""
        return self.stamp_ns // 1_000_000_000, self.stamp_ns % 1_000_000_000

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
    children = tuple(segment_frame(prefix, s.chain, i) for s in segments for i in range(s.n))
    block = first.poses if len(segments) == 1 else np.concatenate([s.poses for s in segments])
    sec, nanosec = first.stamp
    return tf_layout(first.frame_id, children).encode(sec, nanosec, block)


class ChainMessages:
    """Reusable marker messages of one chain (``name``, segment ``lengths`` ``(n,)``,
    ``radius`` m)."""

    def __init__(self, name, lengths, radius):
        self.name = name
        self.lengths = np.asarray(lengths, dtype=float)
        self.radius = float(radius)
        self.n = len(self.lengths)
        self._style = None
        self._markers = []

    def segment_poses(self, origins, quats, frame_id, stamp_ns) -> SegmentPoses:
        """The tick's ``SegmentPoses`` (origins ``(n, 3)``, quats ``(n, 4)``)."""
        return SegmentPoses(self.name, origins, quats, frame_id, stamp_ns)

    def _build_markers(self, style, color):
        r = self.radius
        spheres = Marker()
        spheres.ns = self.name
        spheres.id = 0
        spheres.type = Marker.SPHERE_LIST
        spheres.action = Marker.ADD
        spheres.pose.orientation.w = 1.0
        spheres.scale.x = spheres.scale.y = spheres.scale.z = 2.0 * r
        spheres.points = [Point() for _ in range(self.n + 1)]
        markers = [spheres]
        if style == 'capsules':
            for i in range(self.n):
                c = Marker()
                c.ns = self.name
                c.id = i + 1
                c.type = Marker.CYLINDER
                c.action = Marker.ADD
                c.scale.x = c.scale.y = 2.0 * r
                c.scale.z = float(self.lengths[i])
                markers.append(c)
        elif style == 'line':
            line = Marker()
            line.ns = self.name
            line.id = 1
            line.type = Marker.LINE_STRIP
            line.action = Marker.ADD
            line.pose.orientation.w = 1.0
            line.scale.x = r
            line.points = [Point() for _ in range(self.n + 1)]
            markers.append(line)
        self._markers = markers
        self._style = style
        self.set_color(color)

    def set_color(self, color):
        rgba = ColorRGBA(r=float(color[0]), g=float(color[1]), b=float(color[2]),
                         a=float(color[3]))
        for m in self._markers:
            m.color = rgba

    def markers(self, origins, quats, style, color, frame_id, stamp):
        """Markers of the chain (a list; empty for style 'off'), and whether the set of marker
        ids changed since the last call (then send a DELETEALL first)."""
        if style == 'off':
            changed = self._style not in (None, 'off')
            self._style = 'off'
            self._markers = []
            return [], changed
        changed = style != self._style
        if changed:
            self._build_markers(style, color)
        axes = quat_axis_x(quats) * self.lengths[:, None]
        joints = np.concatenate([origins, origins[-1:] + axes[-1:]]).tolist()
        for m in self._markers:
            m.header.frame_id = frame_id
            m.header.stamp = stamp
        for pt, j in zip(self._markers[0].points, joints):
            pt.x, pt.y, pt.z = j
        if style == 'capsules':
            centres = (origins + 0.5 * axes).tolist()
            q_cyl = quat_multiply(quats, np.broadcast_to(Q_Z_TO_X, quats.shape)).tolist()
            for m, p, q in zip(self._markers[1:], centres, q_cyl):
                _set_pose(m.pose, p, q)
        else:
            for pt, j in zip(self._markers[1].points, joints):
                pt.x, pt.y, pt.z = j
        return self._markers, changed


class ColliderMarkers:
    """Markers of the scene's colliders (namespace ``colliders``), posed by the kinematic
    bodies they are fixed in."""

    def __init__(self):
        self._key = None
        self._markers = []

    def _build(self, colliders):
        color = ColorRGBA(r=COLLIDER_COLOR[0], g=COLLIDER_COLOR[1], b=COLLIDER_COLOR[2],
                          a=COLLIDER_COLOR[3])
        markers = []
        for k, c in enumerate(colliders):
            m = Marker()
            m.ns = 'colliders'
            m.action = Marker.ADD
            m.color = color
            if c.kind == 'sphere':
                m.id, m.type = k, Marker.SPHERE
                m.scale.x = m.scale.y = m.scale.z = 2.0 * c.radius
                markers.append(m)
            elif c.kind == 'capsule':
                m.id, m.type = 2 * k + 1000, Marker.CYLINDER
                m.scale.x = m.scale.y = 2.0 * c.radius
                m.scale.z = max(2.0 * c.half_length, 1e-6)
                caps = Marker()
                caps.ns, caps.id, caps.type = 'colliders', 2 * k + 1001, Marker.SPHERE_LIST
                caps.action, caps.color = Marker.ADD, color
                caps.pose.orientation.w = 1.0
                caps.scale.x = caps.scale.y = caps.scale.z = 2.0 * c.radius
                caps.points = [Point(), Point()]
                markers += [m, caps]
            else:
                m.id, m.type = k, Marker.CUBE
                m.scale.x = m.scale.y = PLANE_SIZE
                m.scale.z = 1e-3
                markers.append(m)
        self._markers = markers

    def markers(self, colliders, bodies, style, frame_id, stamp):
        """Markers of ``colliders`` (``ColliderSpec``s) with the kinematic bodies ``bodies``
        (``KinematicState``; a collider with ``body None`` is static), and whether the set of
        marker ids changed since the last call."""
        key = None if style == 'off' or not colliders else tuple(colliders)
        changed = key != self._key and self._key is not None
        if key != self._key:
            self._key = key
            self._markers = []
            if key is not None:
                self._build(colliders)
        if key is None:
            return [], changed
        markers = iter(self._markers)
        z = np.array([0.0, 0.0, 1.0])
        for c in colliders:
            centre, axis = np.asarray(c.center, float), np.asarray(c.axis, float)
            axis = axis / np.linalg.norm(axis) if c.kind != 'sphere' else z
            if c.body is not None:
                qb = bodies.orientation[c.body]
                centre = bodies.position[c.body] + quat_rotate(qb, centre)
                axis = quat_rotate(qb, axis)
            q = quat_from_two_vectors(z, axis)        # marker Z along the axis / normal
            m = next(markers)
            m.header.frame_id = frame_id
            m.header.stamp = stamp
            _set_pose(m.pose, centre.tolist(), q.tolist())
            if c.kind == 'capsule':
                caps = next(markers)
                caps.header.frame_id = frame_id
                caps.header.stamp = stamp
                for pt, end in zip(caps.points, (centre - c.half_length * axis,
                                                 centre + c.half_length * axis)):
                    pt.x, pt.y, pt.z = end.tolist()
        return self._markers, changed
