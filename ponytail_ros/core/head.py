"""Kinematic bodies: the head (or a static anchor) whose motion is prescribed, never simulated.

The chain hangs from a point fixed in a kinematic body. The animation prescribes that body's
pose and its derivatives; the chain never pushes back on it (one-way coupling, Hecker's
"kinematic control"). All quantities are in the world frame (REP 103: SI units, Z up), and
arrays carry a leading axis over the ``K`` kinematic bodies of a scene.

What the chain needs of a head is the motion of its attachment point (Table 1, Eq. 1–3):

    p   = R + r                      r = R_head @ a_local
    ṗ   = Ṙ + ω × r
    p̈   = R̈ + α × r + ω × (ω × r)

plus the head's orientation and angular velocity, which the joint damping and bending stiffness
of the first joint act against.
"""
from dataclasses import dataclass

import numpy as np

from .head_kernels import frame_ends as _frame_ends
from .head_kernels import point_kinematics, track_table

__all__ = [
    'KinematicState', 'AnchorKinematics', 'HeadMotion', 'StillMotion', 'SwayYawMotion',
    'WithStaticBodies', 'stack_states', 'point_table', 'frame_ends',
    'AnchorTrack',
]


#: The fields of ``KinematicState`` and of ``AnchorKinematics``, in order.
STATE_FIELDS = ('position', 'orientation', 'linear_velocity', 'angular_velocity',
                'linear_acceleration', 'angular_acceleration')
ANCHOR_FIELDS = ('position', 'velocity', 'acceleration', 'orientation', 'angular_velocity')


@dataclass
class KinematicState:
    """Pose, velocity and acceleration of ``K`` kinematic bodies at one instant.

    Attributes (world frame, SI units):
        position: ``(K, 3)`` origin of the body frame, m.
        orientation: ``(K, 4)`` unit quaternion ``(x, y, z, w)``, body to world.
        linear_velocity: ``(K, 3)`` velocity of the origin, m/s.
        angular_velocity: ``(K, 3)`` ω, rad/s.
        linear_acceleration: ``(K, 3)`` acceleration of the origin, m/s².
        angular_acceleration: ``(K, 3)`` α, rad/s².
    """

    position: np.ndarray
    orientation: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity: np.ndarray
    linear_acceleration: np.ndarray
    angular_acceleration: np.ndarray

    @classmethod
    def still(cls, position=(0.0, 0.0, 0.0), orientation=(0.0, 0.0, 0.0, 1.0)):
        """A body at rest; ``position`` ``(3,)`` or ``(K, 3)``."""
        p = np.atleast_2d(np.array(position, dtype=float))         # a copy, never a view
        q = np.broadcast_to(np.asarray(orientation, dtype=float), (p.shape[0], 4)).copy()
        z = np.zeros_like(p)
        return cls(p, q, z, z.copy(), z.copy(), z.copy())

    @property
    def n_bodies(self):
        return self.position.shape[0]

    def with_static_bodies(self, k=1):
        """These bodies followed by ``k`` bodies at rest at the world origin, unrotated (a
        static anchor such as a ceiling, whose points are given in world coordinates)."""
        if k == 0:
            return self
        still = KinematicState.still(np.zeros((k, 3)))
        return KinematicState(*(np.concatenate([getattr(self, f), getattr(still, f)])
                                for f in STATE_FIELDS))

    def is_finite(self):
        return all(np.all(np.isfinite(a)) for a in (
            self.position, self.orientation, self.linear_velocity, self.angular_velocity,
            self.linear_acceleration, self.angular_acceleration))

    def point_kinematics(self, body, r_local):
        """Eq. 1–3 for points fixed in bodies: ``body`` ``(C,)`` indices, ``r_local`` ``(C, 3)``.

        Returns ``AnchorKinematics`` of the ``C`` points (``head_kernels.point_kinematics``).
        """
        body = np.ascontiguousarray(body, dtype=np.int64).reshape(-1)
        C = body.shape[0]
        out = AnchorKinematics(np.empty((C, 3)), np.empty((C, 3)), np.empty((C, 3)),
                               np.empty((C, 4)), np.empty((C, 3)))
        point_kinematics(*(np.ascontiguousarray(getattr(self, f), dtype=float)
                           for f in STATE_FIELDS),
                         body, np.ascontiguousarray(r_local, dtype=float), out.position,
                         out.velocity, out.acceleration, out.orientation, out.angular_velocity)
        return out


@dataclass
class AnchorKinematics:
    """What the solver needs of each chain's anchor: ``C`` rows, one per chain (world frame).

    ``position``/``velocity``/``acceleration`` are those of the attachment point (m, m/s, m/s²);
    ``orientation`` and ``angular_velocity`` are the anchor body's (the first joint's parent).
    """

    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    orientation: np.ndarray
    angular_velocity: np.ndarray

    def row(self, k):
        """Row ``k`` of a table of these (arrays ``(S, C, 3|4)``): the ``C`` points at one
        instant (views)."""
        return AnchorKinematics(self.position[k], self.velocity[k], self.acceleration[k],
                                self.orientation[k], self.angular_velocity[k])


def stack_anchors(anchors):
    """One ``AnchorKinematics`` of arrays ``(S, C, 3|4)`` from a sequence of ``S`` of them."""
    return AnchorKinematics(*(np.stack([getattr(a, f) for a in anchors])
                              for f in ANCHOR_FIELDS))


class HeadMotion:
    """A prescribed motion: ``state_at(t)`` returns the ``KinematicState`` at time ``t`` (s).

    ``states_at(times)`` returns the states at all ``times`` ``(T,)`` at once, as one
    ``KinematicState`` whose arrays have a leading time axis ``(T, K, 3|4)``: the simulator
    evaluates an exact motion at every stage time of a call before the compiled step runs.
    The default stacks ``state_at``; a motion in closed form overrides it with array
    expressions that give the same values bit for bit (the same IEEE operations per element:
    NumPy's ``sin`` and ``cos`` of an array equal those of its elements one by one).
    """

    def state_at(self, t):  # pragma: no cover - interface
        raise NotImplementedError

    def states_at(self, times):
        return stack_states([self.state_at(t) for t in np.asarray(times, dtype=float)])


def stack_states(states):
    """One ``KinematicState`` of arrays ``(T, K, 3|4)`` from a sequence of ``T`` of them."""
    return KinematicState(*(np.stack([getattr(s, f) for s in states]) for f in STATE_FIELDS))


def frame_ends(state0, state1, body, r_local):
    """``point_kinematics`` of the points ``body``/``r_local`` (as there) for two
    ``KinematicState``s, the ends of a frame: an ``AnchorKinematics`` of ``(2, C, 3|4)``
    arrays, row 0 from ``state0`` (``head_kernels.frame_ends``; bit for bit the two
    ``point_kinematics`` calls)."""
    C = body.shape[0]
    out = AnchorKinematics(np.empty((2, C, 3)), np.empty((2, C, 3)), np.empty((2, C, 3)),
                           np.empty((2, C, 4)), np.empty((2, C, 3)))
    _frame_ends(*(np.ascontiguousarray(getattr(state0, f), dtype=float) for f in STATE_FIELDS),
                *(np.ascontiguousarray(getattr(state1, f), dtype=float) for f in STATE_FIELDS),
                np.ascontiguousarray(body, dtype=np.int64),
                np.ascontiguousarray(r_local, dtype=float), out.position, out.velocity,
                out.acceleration, out.orientation, out.angular_velocity)
    return out


def point_table(states, body, r_local):
    """Eq. 1–3 for points fixed in bodies at every time of ``states`` (a ``KinematicState``
    of ``(T, K, 3|4)`` arrays, as ``HeadMotion.states_at`` gives): an ``AnchorKinematics`` of
    ``(T, C, 3|4)`` arrays, each row as ``KinematicState.point_kinematics`` computes it."""
    T, K = states.position.shape[:2]
    body = np.asarray(body, dtype=np.int64).reshape(-1)
    C = body.shape[0]
    # The T instants as T·K bodies of one state: row t's bodies are t·K ... t·K + K - 1; the
    # outputs' (T·C, ·) views fill the (T, C, ·) tables.
    out = AnchorKinematics(np.empty((T, C, 3)), np.empty((T, C, 3)), np.empty((T, C, 3)),
                           np.empty((T, C, 4)), np.empty((T, C, 3)))
    point_kinematics(*(np.ascontiguousarray(getattr(states, f), dtype=float).reshape(T * K, -1)
                       for f in STATE_FIELDS),
                     (np.arange(T)[:, None] * K + body).reshape(-1),
                     np.broadcast_to(np.asarray(r_local, dtype=float).reshape(C, 3),
                                     (T, C, 3)).reshape(T * C, 3),
                     out.position.reshape(T * C, 3), out.velocity.reshape(T * C, 3),
                     out.acceleration.reshape(T * C, 3), out.orientation.reshape(T * C, 4),
                     out.angular_velocity.reshape(T * C, 3))
    return out


class WithStaticBodies(HeadMotion):
    """``motion``'s bodies followed by ``k`` static ones (``KinematicState.with_static_bodies``):
    a scene with a head and a ceiling anchor."""

    def __init__(self, motion, k=1):
        self.motion, self.k = motion, int(k)

    def state_at(self, t):
        return self.motion.state_at(t).with_static_bodies(self.k)

    def states_at(self, times):
        moving = self.motion.states_at(times)
        T = moving.position.shape[0]
        still = KinematicState.still(np.zeros((self.k, 3)))
        return KinematicState(*(np.concatenate(
            [getattr(moving, f), np.broadcast_to(getattr(still, f),
                                                 (T,) + getattr(still, f).shape)],
            axis=1) for f in STATE_FIELDS))


class StillMotion(HeadMotion):
    """Kinematic bodies that never move (a ceiling anchor, a still head)."""

    def __init__(self, position=(0.0, 0.0, 0.0), orientation=(0.0, 0.0, 0.0, 1.0)):
        self._state = KinematicState.still(position, orientation)

    def state_at(self, t):
        return self._state

    def states_at(self, times):
        T = np.asarray(times).reshape(-1).shape[0]
        return KinematicState(*(np.broadcast_to(getattr(self._state, f),
                                                (T,) + getattr(self._state, f).shape).copy()
                                for f in STATE_FIELDS))


class SwayYawMotion(HeadMotion):
    """Side-to-side sway with a yaw oscillation, with exact derivatives.

    ``position = p0 + (A sin 2πft, 0, 0)``; orientation = rotation about world Z by
    ``yaw = Y sin 2πf_y t``. This is the moving head of ``../shared/reference/``.
    """

    def __init__(self, p0=(0.0, 0.0, 1.6), amplitude=0.05, frequency=1.5, yaw_amplitude=0.6,
                 yaw_frequency=0.8):
        self.p0 = np.asarray(p0, dtype=float)
        self.A, self.f, self.Y, self.fy = amplitude, frequency, yaw_amplitude, yaw_frequency

    def state_at(self, t):
        w = 2.0 * np.pi * self.f
        wy = 2.0 * np.pi * self.fy
        x = self.A * np.sin(w * t)
        yaw = self.Y * np.sin(wy * t)
        yaw_d = self.Y * wy * np.cos(wy * t)
        yaw_dd = -self.Y * wy * wy * np.sin(wy * t)
        p = self.p0 + np.array([x, 0.0, 0.0])
        return KinematicState(
            position=p[None],
            orientation=np.array([[0.0, 0.0, np.sin(0.5 * yaw), np.cos(0.5 * yaw)]]),
            linear_velocity=np.array([[self.A * w * np.cos(w * t), 0.0, 0.0]]),
            angular_velocity=np.array([[0.0, 0.0, yaw_d]]),
            linear_acceleration=np.array([[-self.A * w * w * np.sin(w * t), 0.0, 0.0]]),
            angular_acceleration=np.array([[0.0, 0.0, yaw_dd]]),
        )

    def states_at(self, times):
        t = np.asarray(times, dtype=float).reshape(-1)
        w = 2.0 * np.pi * self.f
        wy = 2.0 * np.pi * self.fy
        yaw = self.Y * np.sin(wy * t)
        z = np.zeros((t.shape[0], 1, 3))
        p = np.broadcast_to(self.p0, z.shape) + z
        p[:, 0, 0] = self.p0[0] + self.A * np.sin(w * t)
        q = np.zeros((t.shape[0], 1, 4))
        q[:, 0, 2] = np.sin(0.5 * yaw)
        q[:, 0, 3] = np.cos(0.5 * yaw)
        v, om, a, al = z.copy(), z.copy(), z.copy(), z.copy()
        v[:, 0, 0] = self.A * w * np.cos(w * t)
        om[:, 0, 2] = self.Y * wy * np.cos(wy * t)
        a[:, 0, 0] = -self.A * w * w * np.sin(w * t)
        al[:, 0, 2] = -self.Y * wy * wy * np.sin(wy * t)
        return KinematicState(p, q, v, om, a, al)


class AnchorTrack:
    """Anchor kinematics between two frames, for stepping at times the animation never gave.

    The attachment point follows the quintic Hermite through its position, velocity and
    acceleration at both frames, so the solver sees a C²-continuous anchor whatever the frame
    rate (this is what makes the result independent of it). The anchor body's orientation is
    slerped and its angular velocity interpolated linearly: they enter only damping and
    stiffness of the first joint.

    Outside ``[t0, t1]`` (the fixed-step accumulator strays up to one internal step before
    ``t0``) the point follows the 2nd-order Taylor expansion from the nearer end,
    p + v τ + ½ a τ²: C²-continuous with the quintic there and bounded however short the
    interval is (a quintic extrapolated to s = -dt/h blows up as frames get close together).
    """

    def __init__(self, t0, a0, t1, a1):
        self.t0 = float(t0)
        self.h = max(float(t1) - float(t0), 1e-12)
        self._ends = tuple(np.ascontiguousarray([getattr(a0, f), getattr(a1, f)], dtype=float)
                           for f in ANCHOR_FIELDS)
        self._C = self._ends[0].shape[1]

    @classmethod
    def from_ends(cls, t0, t1, ends):
        """The track between ``t0`` and ``t1`` from its ends as ``frame_ends`` gives them: an
        ``AnchorKinematics`` of ``(2, C, 3|4)`` C-contiguous arrays (row 0 at ``t0``), kept
        without a copy."""
        track = cls.__new__(cls)
        track.t0 = float(t0)
        track.h = max(float(t1) - float(t0), 1e-12)
        track._ends = tuple(getattr(ends, f) for f in ANCHOR_FIELDS)
        track._C = track._ends[0].shape[1]
        return track

    def table(self, times):
        """The anchors at all ``times`` ``(S,)`` at once, as the rows of an
        ``AnchorKinematics`` of arrays ``(S, C, 3|4)`` (the compiled step's anchor table;
        evaluated by ``head_kernels.track_table``)."""
        t = np.ascontiguousarray(times, dtype=float).reshape(-1)
        S, C = t.shape[0], self._C
        out = AnchorKinematics(np.empty((S, C, 3)), np.empty((S, C, 3)), np.empty((S, C, 3)),
                               np.empty((S, C, 4)), np.empty((S, C, 3)))
        track_table(t, self.t0, self.h, *self._ends, out.position, out.velocity, out.acceleration,
                    out.orientation, out.angular_velocity)
        return out

    def at(self, t):
        """The anchors at one time ``t`` (s): ``AnchorKinematics`` of ``(C, 3|4)`` arrays, row 0
        of ``table`` (one evaluation of the track for both)."""
        row = self.table(np.array([float(t)]))
        return AnchorKinematics(row.position[0], row.velocity[0], row.acceleration[0],
                                row.orientation[0], row.angular_velocity[0])
