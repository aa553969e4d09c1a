"""A scripted head motion for demos and tests: idle sway, nod, shake, turn, run with bob, stop.

ROS-free (numpy and the core only): ``HeadScript`` is a ``HeadMotion`` whose ``state_at(t)``
returns the pose and its derivatives, so it drives ``Simulator.advance_to`` directly as well as
the ``ponytail_head_demo`` node (which publishes only the pose).

Timeline (seconds, looping every ``HeadScript.PERIOD`` = 24 s); the head starts at ``origin``,
facing +X (REP 103 body axes: X forward, Y left, Z up):

    0 – 4     idle sway: 2 cm side to side with a little roll, 0.5 Hz
    4 – 6.5   nod: pitch ±0.35 rad at 1.5 Hz
    6.5 – 9   shake: yaw ±0.6 rad at 2 Hz
    9 – 10    turn left by 90°
    10.5 – 13.4  run 6 m along +Y at up to 3 m/s with a 3 cm bob at 2.8 Hz and a forward lean,
              ending in a sharp stop at 12.9 s (3 m/s to 0 in 0.15 s, about 3 g), then stand
    14.5 – 16 turn by 180°
    16.5 – 19.4  run back, sharp stop at 18.9 s
    20.5 – 21.5  turn by 90° (facing +X again), then idle until the loop closes at 24 s

Every component is windowed by C² smooth ramps, so the pose is C² everywhere (also across the
loop: the run comes back to the start and the heading ends at 2π). Derivatives are central
differences of the pose (accurate to ~1e-6 relative), which is plenty for a demo.
"""
import math

import numpy as np

from ponytail_ros.core.head import HeadMotion, KinematicState
from ponytail_ros.core.rotations import quat_conjugate, quat_multiply, quat_to_rotvec

__all__ = ['HeadScript', 'PHASES', 'euler_zyx_quat']

#: (name, start s, end s) of each phase of the script.
PHASES = (
    ('idle_sway', 0.0, 4.0),
    ('nod', 4.0, 6.5),
    ('shake', 6.5, 9.0),
    ('turn', 9.0, 10.0),
    ('run', 10.5, 13.4),
    ('turn_back', 14.5, 16.0),
    ('run_back', 16.5, 19.4),
    ('turn_front', 20.5, 21.5),
    ('idle', 21.5, 24.0),
)


def _smoother(u):
    """Smootherstep 6u⁵ − 15u⁴ + 10u³ clamped to [0, 1] (C² ramp)."""
    u = min(max(u, 0.0), 1.0)
    return u * u * u * (u * (6.0 * u - 15.0) + 10.0)


def _smoother_integral(u):
    """∫₀ᵘ smootherstep; equals 1/2 at u = 1 (and grows linearly beyond)."""
    if u <= 0.0:
        return 0.0
    if u >= 1.0:
        return 0.5 + (u - 1.0)
    u2 = u * u
    return u2 * u2 * (u * (u - 3.0) + 2.5)


def _window(t, a, b, ramp=0.3):
    """1 inside [a, b], 0 outside, smooth ramps of ``ramp`` s inside the interval."""
    return _smoother((t - a) / ramp) * _smoother((b - t) / ramp)


def _run_distance(t, t0, distance, speed, t_acc, t_dec):
    """Distance along a run starting at ``t0``: smooth acceleration over ``t_acc``, cruise at
    ``speed``, sharp smooth stop over ``t_dec``; returns (distance, speed fraction)."""
    t_cruise = distance / speed - 0.5 * (t_acc + t_dec)
    s = t - t0
    if s <= 0.0:
        return 0.0, 0.0
    if s < t_acc:
        return speed * t_acc * _smoother_integral(s / t_acc), _smoother(s / t_acc)
    d = 0.5 * speed * t_acc
    s -= t_acc
    if s < t_cruise:
        return d + speed * s, 1.0
    d += speed * t_cruise
    s -= t_cruise
    if s < t_dec:
        u = s / t_dec
        return d + speed * t_dec * (u - _smoother_integral(u)), 1.0 - _smoother(u)
    return distance, 0.0


def euler_zyx_quat(yaw, pitch, roll):
    """Quaternion ``(x, y, z, w)`` of ``Rz(yaw) · Ry(pitch) · Rx(roll)``."""
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    return np.array([
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    ])


class HeadScript(HeadMotion):
    """The scripted head (see the module docstring).

    Args:
        origin: start position of the head, m (default 1.6 m above the world origin).
        loop: repeat the script every ``PERIOD`` s (else hold the final pose).
        time_scale: play speed (2 = twice as fast).
    """

    PERIOD = 24.0
    RUN_DISTANCE = 6.0
    RUN_SPEED = 3.0
    RUN_ACCEL_TIME = 0.6
    STOP_TIME = 0.15

    def __init__(self, origin=(0.0, 0.0, 1.6), loop=True, time_scale=1.0):
        self.origin = np.asarray(origin, dtype=float).reshape(3)
        self.loop = bool(loop)
        self.time_scale = float(time_scale)

    def phase(self, t):
        """Name of the phase at time ``t`` ('' between phases)."""
        s = self._script_time(t)
        for name, a, b in PHASES:
            if a <= s < b:
                return name
        return ''

    def _script_time(self, t):
        s = float(t) * self.time_scale
        if self.loop:
            return s % self.PERIOD
        return min(max(s, 0.0), self.PERIOD)

    def pose(self, t):
        """Position ``(3,)`` and orientation ``(4,)`` (x, y, z, w) at ``t``."""
        s = self._script_time(t)
        two_pi = 2.0 * math.pi
        # Heading: +90° (9–10 s), +180° (14.5–16 s), +90° (20.5–21.5 s).
        heading = (0.5 * math.pi * _smoother((s - 9.0) / 1.0)
                   + math.pi * _smoother((s - 14.5) / 1.5)
                   + 0.5 * math.pi * _smoother((s - 20.5) / 1.0))
        w_idle = _window(s, 0.0, 4.0) + _window(s, 21.5, 24.0 + 0.3)
        if s < 0.3:   # the idle phase continues across the loop boundary
            w_idle = 1.0
        sway = 0.02 * math.sin(two_pi * 0.5 * s) * w_idle
        roll = 0.05 * math.sin(two_pi * 0.5 * s) * w_idle
        pitch = 0.35 * math.sin(two_pi * 1.5 * (s - 4.0)) * _window(s, 4.0, 6.5)
        yaw = heading + 0.6 * math.sin(two_pi * 2.0 * (s - 6.5)) * _window(s, 6.5, 9.0)

        args = (self.RUN_DISTANCE, self.RUN_SPEED, self.RUN_ACCEL_TIME, self.STOP_TIME)
        d_out, f_out = _run_distance(s, 10.5, *args)
        d_back, f_back = _run_distance(s, 16.5, *args)
        along = d_out - d_back                      # metres along +Y from the start
        speed_fraction = f_out + f_back
        bob = 0.03 * speed_fraction * 0.5 * (1.0 - math.cos(two_pi * 2.8 * s))
        pitch += 0.15 * speed_fraction             # lean forward while running

        p = self.origin + np.array([0.0, along, bob])
        # Lateral sway along the head's left axis.
        p[:2] += sway * np.array([-math.sin(heading), math.cos(heading)])
        return p, euler_zyx_quat(yaw, pitch, roll)

    def state_at(self, t, h=1e-3):
        """``KinematicState`` (K = 1) at ``t``; derivatives by central differences."""
        t = float(t)
        p0, q0 = self.pose(t)
        pm, qm = self.pose(t - h)
        pp, qp = self.pose(t + h)
        # Angular velocity in the world frame from the relative rotations to the neighbours.
        phi_p = quat_to_rotvec(quat_multiply(_align(qp, q0), quat_conjugate(q0)))
        phi_m = quat_to_rotvec(quat_multiply(_align(qm, q0), quat_conjugate(q0)))
        return KinematicState(
            position=p0[None],
            orientation=q0[None],
            linear_velocity=((pp - pm) / (2.0 * h))[None],
            angular_velocity=((phi_p - phi_m) / (2.0 * h))[None],
            linear_acceleration=((pp - 2.0 * p0 + pm) / (h * h))[None],
            angular_acceleration=((phi_p + phi_m) / (h * h))[None],
        )


def _align(q, ref):
    return -q if float(q @ ref) < 0.0 else q
