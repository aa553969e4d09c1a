"""A TF buffer without ROS: the transforms of ``/tf`` and ``/tf_static``, composed along the
frame tree as tf2 does, and the poses of a frame in a fixed frame at the stamps of the moving
transforms that carry it (the head from TF, live and offline, with one implementation).

Frames form a tree: each transform ``parent -> child`` (``TransformStamped``: the pose of
``child`` in ``parent``, translation m, rotation a unit quaternion x, y, z, w) is the edge of
``child`` to its one parent. ``/tf_static`` edges hold one timeless value (the latest);
``/tf`` edges hold samples keyed by integer ns stamps, kept for ``cache_ns`` behind the newest
(tf2's 10 s). A look-up at ``t_ns`` interpolates each moving edge between the samples around
``t_ns`` as tf2's ``TimeCache`` does (translation lerped, rotation slerped along the shorter
arc, the ratio taken from integer ns differences), composes the edges from the common ancestor
down to each frame, and gives ``fixed_frame -> frame``.

Unlike tf2, which refuses it, a look-up past an edge's newest sample (or before its oldest)
holds that sample and says so: :class:`Lookup` names every edge it held and by how long, and
:class:`TFPoseSource` counts them (extrapolation; stale past ``stale_ns``). A frame never seen,
two frames with no common ancestor, or a loop raise :class:`TFError` naming the frames.

Nothing here imports ROS: the node (``ros/node.py``) and the replay (``recording/offline.py``)
feed it the fields of ``tf2_msgs/TFMessage`` (``wire.tf_message_fields``).
"""
from __future__ import annotations

import math
from bisect import bisect_left
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

__all__ = ['TFError', 'TFBuffer', 'Edge', 'Lookup', 'TFPoseSource', 'TFSample',
           'CACHE_NS', 'compose', 'invert', 'interpolate']

#: How long dynamic samples are kept behind an edge's newest (tf2's default cache time).
CACHE_NS = 10_000_000_000

Vec = tuple[float, float, float]
Quat = tuple[float, float, float, float]
Pose = tuple[Vec, Quat]


class TFError(LookupError):
    """A look-up that cannot be done: the message names the frames (never seen, not
    connected, a loop)."""


# -- pose algebra (plain floats: a few edges per look-up) -----------------------------------
def _rotate(q: Quat, v: Sequence[float]) -> Vec:
    x, y, z, w = q
    # v + 2 w (u x v) + 2 u x (u x v), u the vector part
    tx = 2.0 * (y * v[2] - z * v[1])
    ty = 2.0 * (z * v[0] - x * v[2])
    tz = 2.0 * (x * v[1] - y * v[0])
    return (v[0] + w * tx + (y * tz - z * ty),
            v[1] + w * ty + (z * tx - x * tz),
            v[2] + w * tz + (x * ty - y * tx))


def _qmul(a: Quat, b: Quat) -> Quat:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


def compose(a: Pose, b: Pose) -> Pose:
    """``a * b``: ``b`` (a pose in ``a``'s child frame) in ``a``'s parent frame."""
    r = _rotate(a[1], b[0])
    return (a[0][0] + r[0], a[0][1] + r[1], a[0][2] + r[2]), _qmul(a[1], b[1])


def invert(a: Pose) -> Pose:
    """The inverse transform of ``a`` (``invert(a) * a`` is the identity)."""
    x, y, z, w = a[1]
    qc = (-x, -y, -z, w)
    r = _rotate(qc, a[0])
    return (-r[0], -r[1], -r[2]), qc


def _normalized(q: Sequence[float]) -> Quat:
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not n > 0.0 or not math.isfinite(n):
        raise ValueError(f'rotation {tuple(q)} is not a quaternion')
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def interpolate(a: Pose, b: Pose, ratio: float) -> Pose:
    """tf2's interpolation of two samples: translation lerped, rotation slerped along the
    shorter arc (``tf2::slerp``), ``ratio`` in [0, 1] from ``a`` to ``b``."""
    pa, qa = a
    pb, qb = b
    p = (pa[0] + (pb[0] - pa[0]) * ratio, pa[1] + (pb[1] - pa[1]) * ratio,
         pa[2] + (pb[2] - pa[2]) * ratio)
    dot = qa[0] * qb[0] + qa[1] * qb[1] + qa[2] * qb[2] + qa[3] * qb[3]
    if dot < 0.0:
        qb, dot = (-qb[0], -qb[1], -qb[2], -qb[3]), -dot
    theta = math.acos(min(dot, 1.0))
    if theta < 1e-9:
        s0, s1 = 1.0 - ratio, ratio
    else:
        d = 1.0 / math.sin(theta)
        s0, s1 = math.sin((1.0 - ratio) * theta) * d, math.sin(ratio * theta) * d
    return p, _normalized((qa[0] * s0 + qb[0] * s1, qa[1] * s0 + qb[1] * s1,
                           qa[2] * s0 + qb[2] * s1, qa[3] * s0 + qb[3] * s1))


# -- the tree ----------------------------------------------------------------------------------
@dataclass
class Edge:
    """The transform of ``child`` in ``parent``: one value (``static``) or samples by stamp."""

    parent: str
    child: str
    static: bool
    #: integer ns stamps, increasing; ``values[i]`` the pose at ``stamps[i]``
    stamps: list[int] = field(default_factory=list)
    values: list[Pose] = field(default_factory=list)

    @property
    def name(self) -> str:
        return f'{self.parent} -> {self.child}'

    @property
    def newest(self) -> int:
        return self.stamps[-1]

    def at(self, t_ns: int) -> tuple[Pose, int]:
        """The pose at ``t_ns`` and how far (ns, > 0) ``t_ns`` lies outside the samples (the
        nearest sample held then; 0 within them or for a static edge)."""
        if self.static:
            return self.values[-1], 0
        stamps = self.stamps
        if t_ns >= stamps[-1]:
            return self.values[-1], t_ns - stamps[-1]
        if t_ns <= stamps[0]:
            return self.values[0], stamps[0] - t_ns
        i = bisect_left(stamps, t_ns)
        t1 = stamps[i]
        if t1 == t_ns:
            return self.values[i], 0
        t0 = stamps[i - 1]
        # (integer ns differences, then the ratio: no precision lost to large epoch stamps)
        return interpolate(self.values[i - 1], self.values[i], (t_ns - t0) / (t1 - t0)), 0


@dataclass
class Lookup:
    """A composed transform: ``position``/``orientation`` of the frame in the fixed frame at
    ``t_ns``; ``held``: ``(edge name, ns)`` of every moving edge whose samples did not reach
    ``t_ns`` (its nearest sample held)."""

    t_ns: int
    position: Vec
    orientation: Quat
    held: tuple[tuple[str, int], ...] = ()


class TFBuffer:
    """The edges of ``/tf`` and ``/tf_static`` by child frame (module docstring).

    ``version`` increases whenever the tree's shape changes (an edge added, a parent changed),
    so that users may keep a path between changes. Counts: ``old`` (samples older than the
    cache behind their edge's newest, dropped), ``repeated`` (a stamp already held, ignored as
    tf2 does).
    """

    def __init__(self, cache_ns: int = CACHE_NS):
        self.cache_ns = int(cache_ns)
        self.edges: dict[str, Edge] = {}
        self.version = 0
        self.old = 0
        self.repeated = 0

    def frames(self) -> set:
        """Every frame named by some edge."""
        return set(self.edges) | {e.parent for e in self.edges.values()}

    def add(self, parent: str, child: str, stamp_ns: int, translation: Sequence[float],
            rotation: Sequence[float], static: bool = False) -> bool:
        """One transform (the pose of ``child`` in ``parent`` at ``stamp_ns``). Returns whether
        it was stored. Raises ``ValueError`` for a non-finite or zero value, or an edge from a
        frame to itself."""
        if parent == child:
            raise ValueError(f'transform from frame {parent!r} to itself')
        if not child or not parent:
            raise ValueError(f'transform {parent!r} -> {child!r}: empty frame name')
        t = (float(translation[0]), float(translation[1]), float(translation[2]))
        if not all(math.isfinite(x) for x in t):
            raise ValueError(f'transform {parent} -> {child}: translation {t} is not finite')
        pose = (t, _normalized(rotation))
        edge = self.edges.get(child)
        if edge is None or edge.parent != parent or edge.static != static:
            # A new edge, or the child moved to another parent (tf2 keeps one parent per frame).
            edge = self.edges[child] = Edge(parent, child, static)
            self.version += 1
        if static:
            edge.stamps[:] = [int(stamp_ns)]
            edge.values[:] = [pose]
            return True
        stamps = edge.stamps
        stamp_ns = int(stamp_ns)
        if not stamps or stamp_ns > stamps[-1]:
            stamps.append(stamp_ns)
            edge.values.append(pose)
            cut = bisect_left(stamps, stamp_ns - self.cache_ns)
            if cut:
                del stamps[:cut]
                del edge.values[:cut]
            return True
        if stamp_ns < stamps[-1] - self.cache_ns:
            self.old += 1
            return False
        i = bisect_left(stamps, stamp_ns)
        if stamps[i] == stamp_ns:
            self.repeated += 1
            return False
        stamps.insert(i, stamp_ns)
        edge.values.insert(i, pose)
        return True

    def add_transforms(self, transforms: Iterable[tuple[int, int, str, str, Sequence[float],
                                                        Sequence[float]]],
                       static: bool = False) -> list[tuple[str, int]]:
        """The transforms of one ``TFMessage`` (``wire.tf_message_fields``: ``(sec, nanosec,
        parent, child, translation, rotation)``); returns ``(child, stamp_ns)`` of the moving
        samples stored. An invalid transform raises ``ValueError`` naming it; the ones before
        it are kept."""
        added = []
        for sec, nanosec, parent, child, t, q in transforms:
            stamp = sec * 1_000_000_000 + nanosec
            if self.add(parent.lstrip('/'), child.lstrip('/'), stamp, t, q, static) \
                    and not static:
                added.append((child.lstrip('/'), stamp))
        return added

    # -- paths and look-ups ---------------------------------------------------------------
    def _ancestors(self, frame: str) -> list[Edge]:
        """The edges from ``frame`` up to its root, nearest first."""
        out: list[Edge] = []
        seen = {frame}
        edge = self.edges.get(frame)
        while edge is not None:
            out.append(edge)
            if edge.parent in seen:
                loop = ' -> '.join([e.child for e in out] + [edge.parent])
                raise TFError(f'the TF tree has a loop: {loop} (each frame must have one '
                              f'parent, and no frame may be its own ancestor)')
            seen.add(edge.parent)
            edge = self.edges.get(edge.parent)
        return out

    def path(self, fixed_frame: str, frame: str) -> tuple[list[Edge], list[Edge]]:
        """The edges from ``fixed_frame`` up to the common ancestor and from ``frame`` up to
        it (each nearest first). Raises ``TFError`` naming the frames."""
        known = self.frames()
        for name in (fixed_frame, frame):
            if name not in known:
                shown = ', '.join(sorted(known)[:20]) or 'none yet'
                raise TFError(f'frame {name!r} has not appeared on /tf or /tf_static (frames '
                              f'seen: {shown})')
        up_fixed = self._ancestors(fixed_frame)
        up_frame = self._ancestors(frame)
        chain_fixed = [fixed_frame] + [e.parent for e in up_fixed]
        chain_frame = [frame] + [e.parent for e in up_frame]
        on_frame = set(chain_frame)
        common = next((f for f in chain_fixed if f in on_frame), None)
        if common is None:
            raise TFError(f'frames {fixed_frame!r} and {frame!r} are not connected in the TF '
                          f'tree: {" -> ".join(reversed(chain_fixed))} and '
                          f'{" -> ".join(reversed(chain_frame))} have no common ancestor')
        return (up_fixed[:chain_fixed.index(common)], up_frame[:chain_frame.index(common)])

    def lookup(self, fixed_frame: str, frame: str, t_ns: int) -> Lookup:
        """The pose of ``frame`` in ``fixed_frame`` at ``t_ns`` (module docstring). Raises
        ``TFError`` naming the frames."""
        up_fixed, up_frame = self.path(fixed_frame, frame)
        return _compose_path(up_fixed, up_frame, int(t_ns))


def _down(edges: list[Edge], t_ns: int, held: list[tuple[str, int]]) -> Pose:
    """The pose of the first edge's child in the last edge's parent (edges nearest first)."""
    pose: Pose = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    for edge in reversed(edges):
        value, outside = edge.at(t_ns)
        if outside:
            held.append((edge.name, outside))
        pose = compose(pose, value)
    return pose


def _compose_path(up_fixed: list[Edge], up_frame: list[Edge], t_ns: int) -> Lookup:
    held: list[tuple[str, int]] = []
    pose = compose(invert(_down(up_fixed, t_ns, held)), _down(up_frame, t_ns, held))
    return Lookup(t_ns, pose[0], pose[1], tuple(held))


# -- poses of a frame at the moving edges' stamps ------------------------------------------------
@dataclass
class TFSample:
    """A pose of the frame in the fixed frame, at ``stamp_ns`` (a moving edge's stamp)."""

    stamp_ns: int
    position: Vec
    orientation: Quat


class TFPoseSource:
    """The poses of ``frame`` in ``fixed_frame`` from ``buffer``, one at each stamp of the moving
    edges on the path between them (the head pose stamp = the moving edges' sample stamps).

    Tell it every moving sample stored (:meth:`note`, with ``TFBuffer.add_transforms``'
    result); :meth:`poll` returns the poses now due, in stamp order: a stamp once every moving
    edge on the path has a sample at or after it (interpolated, as tf2 would), or, bounded,
    once the newest sample on the path is ``wait_ns`` past it (the lagging edges then held at
    their newest sample: counted in ``extrapolated``, and in ``stale`` when held for more than
    ``stale_ns``). A path that cannot be found is counted in ``missing`` and its reason kept in
    ``error``. Stamps at or before the last pose given, or before the first sample of some
    moving edge on the path, are not given (``late``).
    """

    def __init__(self, buffer: TFBuffer, fixed_frame: str, frame: str, *,
                 wait_ns: int = 250_000_000, stale_ns: int = 250_000_000):
        if fixed_frame == frame:
            raise ValueError(f'the frame and the fixed frame are both {frame!r}')
        self.buffer = buffer
        self.fixed_frame = fixed_frame
        self.frame = frame
        self.wait_ns = int(wait_ns)
        self.stale_ns = int(stale_ns)
        self._version = -1
        self._path: tuple[list[Edge], list[Edge]] | None = None
        self._on_path: set = set()
        self._pending: set = set()
        #: stamps seen (of any edge) while the path is unknown: used once it is found
        self._unplaced: dict[str, list[int]] = {}
        self.last_ns: int | None = None
        self.missing = 0
        #: polls in a row that could not find the path (0 once it is found)
        self.failing = 0
        self.error: str | None = None
        self.late = 0
        #: edge name -> poses given with that edge held past its newest (or before its oldest)
        self.extrapolated: Counter = Counter()
        #: edge name -> poses given with that edge held for more than ``stale_ns``
        self.stale: Counter = Counter()
        #: the last pose's held edges (``Lookup.held``)
        self.last_held: tuple[tuple[str, int], ...] = ()

    def note(self, samples: Iterable[tuple[str, int]]) -> None:
        """Moving samples stored: ``(child frame, stamp ns)``."""
        self._refresh()
        for child, stamp in samples:
            if self.last_ns is not None and stamp <= self.last_ns:
                if child in self._on_path:
                    self.late += 1
                continue
            if self._path is None:
                self._unplaced.setdefault(child, []).append(stamp)
            elif child in self._on_path:
                self._pending.add(stamp)

    def _refresh(self) -> None:
        """The path again when the tree changed (stamps noted meanwhile placed on it)."""
        if self.buffer.version == self._version:
            return
        self._version = self.buffer.version
        try:
            self._path = self.buffer.path(self.fixed_frame, self.frame)
            self.error = None
        except TFError as err:
            self._path, self._on_path, self.error = None, set(), str(err)
            return
        self._on_path = {e.child for edges in self._path for e in edges if not e.static}
        for child, stamps in self._unplaced.items():
            if child in self._on_path:
                self._pending.update(s for s in stamps
                                     if self.last_ns is None or s > self.last_ns)
        self._unplaced.clear()

    @property
    def moving_edges(self) -> list[Edge]:
        """The moving edges on the path (empty when it is unknown)."""
        if self._path is None:
            return []
        return [e for edges in self._path for e in edges if not e.static]

    def poll(self) -> list[TFSample]:
        """The poses now due (class docstring), oldest first."""
        self._refresh()
        if self._path is None:
            self.missing += 1
            self.failing += 1
            # (keep what arrived, bounded: a frame that never appears must not grow memory)
            for stamps in self._unplaced.values():
                if len(stamps) > 10_000:
                    del stamps[:-10_000]
            return []
        self.failing = 0
        due = self._due()
        if not due:
            return []
        up_fixed, up_frame = self._path
        out = []
        for stamp in due:
            look = _compose_path(up_fixed, up_frame, stamp)
            for name, ns in look.held:
                self.extrapolated[name] += 1
                if ns > self.stale_ns:
                    self.stale[name] += 1
            self.last_held = look.held
            out.append(TFSample(stamp, look.position, look.orientation))
        self.last_ns = due[-1]
        return out

    def _due(self) -> list[int]:
        """The pending stamps now due, in order (taken out of the pending ones)."""
        moving = self.moving_edges
        if not self._pending or not moving:
            return []
        ready_until = min(e.newest for e in moving)
        waited_until = max(e.newest for e in moving) - self.wait_ns
        due = sorted(s for s in self._pending if s <= ready_until or s <= waited_until)
        self._pending.difference_update(due)
        # (before some edge's first sample: that edge could only be held, never interpolated)
        start = max(e.stamps[0] for e in moving)
        if due and due[0] < start:
            self.late += sum(1 for s in due if s < start)
            due = [s for s in due if s >= start]
        return due
