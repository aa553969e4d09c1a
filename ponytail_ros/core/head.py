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

from .head_kernels import (
    SINUSOID_COLUMNS,
    frame_ends as _frame_ends,
    point_kinematics,
    sinusoid_table,
    track_table,
)

__all__ = [
    'KinematicState', 'AnchorKinematics', 'HeadMotion', 'SinusoidMotion', 'StillMotion',
    'SwayYawMotion', 'WithStaticBodies', 'stack_states', 'point_table', 'frame_ends',
    'stage_times', 'sinusoid_coefficients', 'AnchorTrack', 'SINUSOID_COLUMNS',
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
    evaluates an exact motion at every stage time of a call before the compiled step runs
    (``stage_points``). The default stacks ``state_at``; a motion in closed form overrides it
    with array expressions that give the same values bit for bit (the same IEEE operations per
    element: NumPy's ``sin`` and ``cos`` of an array equal those of its elements one by one).

    ``fixed``: the motion never changes after construction (``stage_points`` is a function of
    its arguments alone), so a simulator may evaluate it ahead for its next calls.
    """

    fixed = False

    def state_at(self, t):  # pragma: no cover - interface
        raise NotImplementedError

    def states_at(self, times):
        return stack_states([self.state_at(t) for t in np.asarray(times, dtype=float)])

    def stage_points(self, t_base, k0, n_steps, dt, body, r_local):
        """Eq. 1–3 for the points ``body`` / ``r_local`` (as ``point_table``) at the stage
        times of steps ``k0 … k0 + n_steps - 1`` of ``dt`` s from ``t_base`` s
        (``stage_times``): an ``AnchorKinematics`` of C-contiguous ``(2 n_steps + 1, C, 3|4)``
        arrays, each row bit for bit ``state_at(t).point_kinematics(body, r_local)``. What
        ``Simulator.advance_to`` evaluates once per call; the default is ``point_table`` of
        ``states_at``, a motion may compute it in one compiled call (``SinusoidMotion``)."""
        return point_table(self.states_at(stage_times(t_base, k0, n_steps, dt)), body, r_local)


def stage_times(t_base, k0, n_steps, dt):
    """The stage times ``(2 n_steps + 1,)`` (s) of steps ``k0 … k0 + n_steps - 1`` of ``dt``
    from ``t_base``: row ``2k`` at step ``k0 + k``'s start, ``t_base + (k0 + k) dt``,
    ``2k + 1`` at its midpoint (half a step later), ``2 n_steps`` at the last step's end."""
    t = t_base + (k0 + np.arange(n_steps + 1)) * dt
    times = np.empty(2 * n_steps + 1)
    times[0::2] = t
    times[1::2] = t[:-1] + 0.5 * dt
    return times


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
    rows, points = _table_points(T, K, body, r_local)
    # The T instants as T·K bodies of one state: row t's bodies are t·K ... t·K + K - 1; the
    # outputs' (T·C, ·) views fill the (T, C, ·) tables.
    out = AnchorKinematics(np.empty((T, C, 3)), np.empty((T, C, 3)), np.empty((T, C, 3)),
                           np.empty((T, C, 4)), np.empty((T, C, 3)))
    point_kinematics(*(np.ascontiguousarray(getattr(states, f), dtype=float).reshape(T * K, -1)
                       for f in STATE_FIELDS),
                     rows, points, *(a.reshape(T * C, -1) for a in (
                         out.position, out.velocity, out.acceleration, out.orientation,
                         out.angular_velocity)))
    return out


_POINTS_CACHE: dict = {}


def _table_points(T, K, body, r_local):
    """``point_table``'s bodies ``(T·C,)`` (row t's: ``t·K + body``, ``body`` ``(C,)``) and
    points ``(T·C, 3)`` for ``T`` instants of ``K`` bodies, kept for the last few
    ``(T, K, body, r_local)`` (a simulator asks for the same few every call)."""
    r_local = np.asarray(r_local, dtype=float).reshape(-1, 3)
    key = (T, K, body.tobytes(), r_local.tobytes())
    hit = _POINTS_CACHE.get(key)
    if hit is None:
        C = body.shape[0]
        hit = ((np.arange(T)[:, None] * K + body).reshape(-1),
               np.ascontiguousarray(np.broadcast_to(r_local, (T, C, 3)).reshape(T * C, 3)))
        if len(_POINTS_CACHE) >= 16:
            _POINTS_CACHE.pop(next(iter(_POINTS_CACHE)))
        _POINTS_CACHE[key] = hit
    return hit


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

    fixed = True

    def __init__(self, position=(0.0, 0.0, 0.0), orientation=(0.0, 0.0, 0.0, 1.0)):
        self._state = KinematicState.still(position, orientation)
        self._points: tuple = (None, None)     # (key, AnchorKinematics) of the last points

    def state_at(self, t):
        return self._state

    def states_at(self, times):
        T = np.asarray(times).reshape(-1).shape[0]
        return KinematicState(*(np.broadcast_to(getattr(self._state, f),
                                                (T,) + getattr(self._state, f).shape).copy()
                                for f in STATE_FIELDS))

    def stage_points(self, t_base, k0, n_steps, dt, body, r_local):
        """The points' one pose repeated at every stage time (``HeadMotion.stage_points``)."""
        body = np.asarray(body, dtype=np.int64).reshape(-1)
        r_local = np.asarray(r_local, dtype=float).reshape(-1, 3)
        key = (body.tobytes(), r_local.tobytes())
        if self._points[0] != key:
            self._points = (key, self._state.point_kinematics(body, r_local))
        S = 2 * int(n_steps) + 1
        return AnchorKinematics(*(np.repeat(getattr(self._points[1], f)[None], S, axis=0)
                                  for f in ANCHOR_FIELDS))


def sinusoid_coefficients(p0, amplitude, amplitude_rate, amplitude_accel, omega, phase, yaw,
                          yaw_rate, yaw_accel, yaw_omega, yaw_phase):
    """The coefficients ``(K, SINUSOID_COLUMNS)`` of ``K`` sinusoidal bodies
    (``head_kernels.sinusoid_table``): per axis ``(K, 3)`` or ``(3,)`` p0 (m), A (m),
    A ω (m/s), -A ω² (m/s²), ω (rad/s), φ (rad); then ``(K,)`` or scalars Y (rad), Y ω_y
    (rad/s), -Y ω_y² (rad/s²), ω_y (rad/s), φ_y (rad). The products are taken as given: each
    as the motion's own NumPy form computes it, so that both give the same values bit for
    bit."""
    axes = [np.asarray(a, dtype=float).reshape(-1, 3) for a in (
        p0, amplitude, amplitude_rate, amplitude_accel, omega, phase)]
    turns = [np.asarray(a, dtype=float).reshape(-1, 1) for a in (
        yaw, yaw_rate, yaw_accel, yaw_omega, yaw_phase)]
    K = max(a.shape[0] for a in axes + turns)
    return np.ascontiguousarray(np.concatenate(
        [np.broadcast_to(a, (K, a.shape[1])) for a in axes + turns], axis=1))


class SinusoidMotion(HeadMotion):
    """A motion of ``K`` bodies whose every coordinate is a sinusoid of time (the form of
    ``head_kernels.sinusoid_table``): sway per axis and yaw about world Z. A subclass sets
    ``coefficients`` (``sinusoid_coefficients``, from its own parameters, fixed after
    construction) and gives ``state_at`` and ``states_at`` in NumPy with the same values; the
    points at a call's stage times (``stage_points``) are then computed in one compiled call."""

    coefficients: np.ndarray
    fixed = True

    def stage_points(self, t_base, k0, n_steps, dt, body, r_local):
        """``HeadMotion.stage_points`` in one compiled call (``sinusoid_table``)."""
        body = np.ascontiguousarray(body, dtype=np.int64).reshape(-1)
        S, C = 2 * int(n_steps) + 1, body.shape[0]
        out = AnchorKinematics(np.empty((S, C, 3)), np.empty((S, C, 3)), np.empty((S, C, 3)),
                               np.empty((S, C, 4)), np.empty((S, C, 3)))
        sinusoid_table(self.coefficients, float(t_base), int(k0), int(n_steps), float(dt), body,
                       np.ascontiguousarray(r_local, dtype=float).reshape(-1, 3),
                       (out.position, out.velocity, out.acceleration, out.orientation,
                        out.angular_velocity))
        return out


class SwayYawMotion(SinusoidMotion):
    """Side-to-side sway with a yaw oscillation, with exact derivatives.

    ``position = p0 + (A sin 2πft, 0, 0)``; orientation = rotation about world Z by
    ``yaw = Y sin 2πf_y t``. This is the moving head of ``../shared/reference/``.
    """

    def __init__(self, p0=(0.0, 0.0, 1.6), amplitude=0.05, frequency=1.5, yaw_amplitude=0.6,
                 yaw_frequency=0.8):
        self.p0 = np.asarray(p0, dtype=float)
        self.A, self.f, self.Y, self.fy = amplitude, frequency, yaw_amplitude, yaw_frequency
        w = 2.0 * np.pi * self.f
        wy = 2.0 * np.pi * self.fy
        # (the products as ``states_at`` forms them; the other axes' terms are +0)
        self.coefficients = sinusoid_coefficients(
            self.p0, (self.A, 0.0, 0.0), (self.A * w, 0.0, 0.0), (-self.A * w * w, 0.0, 0.0),
            (w, 0.0, 0.0), (0.0, 0.0, 0.0), self.Y, self.Y * wy, -self.Y * wy * wy, wy, 0.0)

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
