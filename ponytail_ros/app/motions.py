"""Analytic head motions for the benchmarks and stability tests (exact derivatives).

Every motion here is a ``HeadMotion`` of ``K`` kinematic bodies whose position, orientation,
velocity and acceleration are closed-form, so that ``Simulator.advance_to`` sees the head
exactly at every integrator stage and any error measured is the chain solver's own.

- ``SinusoidHead``: per body, a sinusoidal translation along each world axis plus a sinusoidal
  yaw (rotation about world Z through the head origin), each with its own amplitude,
  frequency and phase. With one body, sway along X and yaw, it is ``core.head.SwayYawMotion``
  (the moving head of ``../shared/reference/``); ``shake_motion`` is the violent variant;
  ``crowd_motion`` gives ``C`` heads with phase offsets for the batched benchmark. Because
  every degree of freedom is a pure sinusoid, the same motion is the free motion of a
  harmonic oscillator, which is how the MuJoCo comparison drives its head (see
  ``mujoco_chain``).
- ``SpinHead``: a head spinning at a constant rate about world Z (optionally spun up from
  rest with a smooth ramp).
- ``ShakeNodHead``: sway along X, yaw and a nod (pitch), for contacts and joint limits.

Every motion of the package lives in ``ponytail_ros.app``: these exact ones (benchmarks and
tests) here, the scripted demo head in ``head_script.py``. Not in ``core``: a motion is an
input the core is driven by, not part of its dynamics (``core.head`` keeps the ``HeadMotion``
interface and its basic motions: still, sway and yaw).
"""
import numpy as np

from ponytail_ros.core.head import (
    HeadMotion,
    KinematicState,
    SinusoidMotion,
    sinusoid_coefficients,
)
from ponytail_ros.core.rotations import quat_multiply

__all__ = ['SinusoidHead', 'SpinHead', 'ShakeNodHead', 'reference_motion', 'shake_motion',
           'crowd_motion', 'SHAKE']

TWO_PI = 2.0 * np.pi

# The violent head shake: ±0.1 m along X at 4 Hz plus ±1 rad of yaw at 3 Hz.
# Peak head acceleration 0.1 (8π)² ≈ 63 m/s², peak yaw acceleration (6π)² ≈ 355 rad/s², so the
# attachment point (0.11 m from the yaw axis) sees up to ~100 m/s² (~10 g).
SHAKE = dict(amplitude=(0.1, 0.0, 0.0), frequency=(4.0, 0.0, 0.0), yaw_amplitude=1.0,
             yaw_frequency=3.0)


class SinusoidHead(SinusoidMotion):
    """``K`` heads, each ``p(t) = p0 + A ∘ sin(2π f t + φ)`` and yaw ``Y sin(2π f_y t + φ_y)``
    (a ``SinusoidMotion``: a call's stage times are evaluated in one compiled call).

    Args (broadcast to ``K`` bodies; per-axis arrays have a trailing axis of 3):
        p0: ``(K, 3)`` or ``(3,)`` centre position, m.
        amplitude, frequency, phase: per axis, m, Hz, rad.
        yaw_amplitude, yaw_frequency, yaw_phase: rad, Hz, rad.
        n_bodies: ``K`` (default: from ``p0``).
    """

    def __init__(self, p0=(0.0, 0.0, 1.6), amplitude=(0.05, 0.0, 0.0), frequency=(1.5, 0.0, 0.0),
                 phase=(0.0, 0.0, 0.0), yaw_amplitude=0.6, yaw_frequency=0.8, yaw_phase=0.0,
                 n_bodies=None):
        p0 = np.atleast_2d(np.asarray(p0, dtype=float))
        k = p0.shape[0] if n_bodies is None else int(n_bodies)
        self.n_bodies = k
        self.p0 = np.broadcast_to(p0, (k, 3)).copy()
        self.A = np.broadcast_to(np.asarray(amplitude, dtype=float), (k, 3)).copy()
        self.w = TWO_PI * np.broadcast_to(np.asarray(frequency, dtype=float), (k, 3))
        self.phi = np.broadcast_to(np.asarray(phase, dtype=float), (k, 3)).copy()
        self.Y = np.broadcast_to(np.asarray(yaw_amplitude, dtype=float), (k,)).copy()
        self.wy = TWO_PI * np.broadcast_to(np.asarray(yaw_frequency, dtype=float), (k,))
        self.phy = np.broadcast_to(np.asarray(yaw_phase, dtype=float), (k,)).copy()
        # (the products as ``states_at`` forms them)
        self.coefficients = sinusoid_coefficients(
            self.p0, self.A, self.A * self.w, -self.A * self.w ** 2, self.w, self.phi, self.Y,
            self.Y * self.wy, -self.Y * self.wy ** 2, self.wy, self.phy)

    def yaw(self, t):
        """Yaw angle, rate and acceleration ``(K,)`` each."""
        s = np.sin(self.wy * t + self.phy)
        c = np.cos(self.wy * t + self.phy)
        return self.Y * s, self.Y * self.wy * c, -self.Y * self.wy ** 2 * s

    def state_at(self, t):
        arg = self.w * t + self.phi
        s, c = np.sin(arg), np.cos(arg)
        yaw, yaw_d, yaw_dd = self.yaw(t)
        k = self.n_bodies
        z = np.zeros((k, 3))
        q = np.zeros((k, 4))
        q[:, 2] = np.sin(0.5 * yaw)
        q[:, 3] = np.cos(0.5 * yaw)
        w = z.copy()
        w[:, 2] = yaw_d
        al = z.copy()
        al[:, 2] = yaw_dd
        return KinematicState(position=self.p0 + self.A * s, orientation=q,
                              linear_velocity=self.A * self.w * c, angular_velocity=w,
                              linear_acceleration=-self.A * self.w ** 2 * s,
                              angular_acceleration=al)

    def states_at(self, times):
        t = np.asarray(times, dtype=float).reshape(-1, 1, 1)
        arg = self.w * t + self.phi                                    # (T, K, 3)
        s, c = np.sin(arg), np.cos(arg)
        yaw, yaw_d, yaw_dd = self.yaw(t[:, :, 0])                     # (T, K) each
        shape = arg.shape
        q = np.zeros(shape[:2] + (4,))
        q[..., 2] = np.sin(0.5 * yaw)
        q[..., 3] = np.cos(0.5 * yaw)
        w = np.zeros(shape)
        w[..., 2] = yaw_d
        al = np.zeros(shape)
        al[..., 2] = yaw_dd
        return KinematicState(position=self.p0 + self.A * s, orientation=q,
                              linear_velocity=self.A * self.w * c, angular_velocity=w,
                              linear_acceleration=-self.A * self.w ** 2 * s,
                              angular_acceleration=al)

    def peak_acceleration(self, r=0.0):
        """Upper bound of the acceleration of a point at distance ``r`` from the yaw axis."""
        lin = np.linalg.norm(self.A * self.w ** 2, axis=1)
        return float(np.max(lin + r * (self.Y * self.wy ** 2 + (self.Y * self.wy) ** 2)))


class SpinHead(HeadMotion):
    """A head spinning about world Z at ``rate`` rad/s, reached by a smooth ramp of ``ramp`` s.

    yaw(t) = rate (t - ramp/2) after the ramp; during it the rate rises as the C¹ smoothstep
    ``rate (3s² - 2s³)``, ``s = t/ramp`` (``ramp = 0``: spinning from t = 0, a step in ω).
    """

    def __init__(self, rate, p0=(0.0, 0.0, 1.6), ramp=0.0):
        self.rate = float(rate)
        self.p0 = np.asarray(p0, dtype=float)
        self.ramp = float(ramp)

    def _yaw(self, t):
        r, T = self.rate, self.ramp
        if T <= 0.0 or t >= T:
            return r * (t - 0.5 * T), r, 0.0
        if t <= 0.0:
            return 0.0, 0.0, 0.0
        s = t / T
        # ∫ r (3s² - 2s³) dt = r T (s³ - s⁴/2)
        return (r * T * (s ** 3 - 0.5 * s ** 4), r * (3 * s * s - 2 * s ** 3),
                r * (6 * s - 6 * s * s) / T)

    def state_at(self, t):
        yaw, yd, ydd = self._yaw(float(t))
        z = np.zeros((1, 3))
        q = np.array([[0.0, 0.0, np.sin(0.5 * yaw), np.cos(0.5 * yaw)]])
        return KinematicState(position=self.p0[None].copy(), orientation=q,
                              linear_velocity=z.copy(),
                              angular_velocity=np.array([[0.0, 0.0, yd]]),
                              linear_acceleration=z.copy(),
                              angular_acceleration=np.array([[0.0, 0.0, ydd]]))


def reference_motion():
    """The moving head of ``../shared/reference/`` (sway 5 cm at 1.5 Hz, yaw 0.6 rad at 0.8 Hz)."""
    return SinusoidHead()


def shake_motion(p0=(0.0, 0.0, 1.6)):
    """The violent head shake (``SHAKE``)."""
    return SinusoidHead(p0=p0, **SHAKE)


def crowd_motion(n, spacing=1.0):
    """``n`` heads on a line ``spacing`` m apart, each the reference sway/yaw with its own phase.

    Phases are spread evenly over a period (sway and yaw offset differently), so no two chains
    move alike.
    """
    k = np.arange(n)
    p0 = np.stack([spacing * k, np.zeros(n), np.full(n, 1.6)], axis=1)
    phase = np.zeros((n, 3))
    phase[:, 0] = TWO_PI * k / max(n, 1)
    return SinusoidHead(p0=p0, phase=phase, yaw_phase=TWO_PI * ((0.37 * k) % 1.0))


class ShakeNodHead(HeadMotion):
    """A violent head shake with exact derivatives: ±A along X at f Hz and ±Y rad of yaw at
    f_y Hz about the head's vertical axis, plus a nod (pitch) of ±P rad at f_p Hz (one body;
    the contact, limit and scene tests' motion: the nod swings the chain into colliders and
    limits the sway-and-yaw motions above leave alone)."""

    def __init__(self, p0=(0.0, 0.0, 1.6), amplitude=0.1, frequency=3.0, yaw=1.0,
                 yaw_frequency=2.5, pitch=0.3, pitch_frequency=1.7):
        self.p0 = np.asarray(p0, dtype=float)
        self.A, self.w = amplitude, 2 * np.pi * frequency
        self.Y, self.wy = yaw, 2 * np.pi * yaw_frequency
        self.P, self.wp = pitch, 2 * np.pi * pitch_frequency

    def state_at(self, t):
        A, w, Y, wy, P, wp = self.A, self.w, self.Y, self.wy, self.P, self.wp
        yaw, yd, ydd = Y * np.sin(wy * t), Y * wy * np.cos(wy * t), -Y * wy * wy * np.sin(wy * t)
        pit, pd, pdd = P * np.sin(wp * t), P * wp * np.cos(wp * t), -P * wp * wp * np.sin(wp * t)
        # R = Rz(yaw) Ry(pitch): ω = yaw' z + pitch' Rz(yaw) y; α = its derivative.
        z = np.array([0.0, 0.0, 1.0])
        y_axis = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
        y_axis_dot = yd * np.array([-np.cos(yaw), -np.sin(yaw), 0.0])
        omega = yd * z + pd * y_axis
        alpha = ydd * z + pdd * y_axis + pd * y_axis_dot
        qz = np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
        qy = np.array([0.0, np.sin(pit / 2), 0.0, np.cos(pit / 2)])
        q = quat_multiply(qz, qy)
        return KinematicState(
            position=(self.p0 + [A * np.sin(w * t), 0.0, 0.0])[None],
            orientation=q[None],
            linear_velocity=np.array([[A * w * np.cos(w * t), 0.0, 0.0]]),
            angular_velocity=omega[None],
            linear_acceleration=np.array([[-A * w * w * np.sin(w * t), 0.0, 0.0]]),
            angular_acceleration=alpha[None])
