"""Time integrators: one fixed step ``h`` of the constrained equations of motion.

Each takes the state, the time ``t``, the step ``h``, ``accel(t, x, q, v, w) -> (a, α)`` (the
constraint forces already solved inside) and returns the new ``(x, q, v, w)``. Quaternions are
renormalised; putting the state back on the joint constraints is ``stabilization``'s job.

- ``symplectic_euler``: semi-implicit Euler, v and ω first, then positions with the new
  velocities (orientation by the exact exponential map). 1st order, one solve per step.
- ``rk4``: classical Runge–Kutta, 4th order, four solves per step (q̇ = ½ (ω, 0) ⊗ q).
"""
import numpy as np

from .rotations import quat_integrate, quat_multiply, quat_normalize

__all__ = ['symplectic_euler', 'rk4', 'INTEGRATOR_STEPS', 'SOLVES_PER_STEP']


def _q_dot(q, w):
    return 0.5 * quat_multiply(np.concatenate([w, np.zeros((w.shape[0], 1))], axis=1), q)


def symplectic_euler(accel, t, h, x, q, v, w):
    a, alpha = accel(t, x, q, v, w)
    v1 = v + h * a
    w1 = w + h * alpha
    return x + h * v1, quat_normalize(quat_integrate(q, w1, h)), v1, w1


def rk4(accel, t, h, x, q, v, w):
    a1, b1 = accel(t, x, q, v, w)
    q1d = _q_dot(q, w)
    hh = 0.5 * h
    x2, q2, v2, w2 = x + hh * v, q + hh * q1d, v + hh * a1, w + hh * b1
    a2, b2 = accel(t + hh, x2, q2, v2, w2)
    q2d = _q_dot(q2, w2)
    x3, q3, v3, w3 = x + hh * v2, q + hh * q2d, v + hh * a2, w + hh * b2
    a3, b3 = accel(t + hh, x3, q3, v3, w3)
    q3d = _q_dot(q3, w3)
    x4, q4, v4, w4 = x + h * v3, q + h * q3d, v + h * a3, w + h * b3
    a4, b4 = accel(t + h, x4, q4, v4, w4)
    q4d = _q_dot(q4, w4)
    s = h / 6.0
    return (x + s * (v + 2.0 * v2 + 2.0 * v3 + v4),
            quat_normalize(q + s * (q1d + 2.0 * q2d + 2.0 * q3d + q4d)),
            v + s * (a1 + 2.0 * a2 + 2.0 * a3 + a4),
            w + s * (b1 + 2.0 * b2 + 2.0 * b3 + b4))


INTEGRATOR_STEPS = {'symplectic_euler': symplectic_euler, 'rk4': rk4}
SOLVES_PER_STEP = {'symplectic_euler': 1, 'rk4': 4}
