"""Vectorised rotation helpers.

Quaternions are stored scalar-last, ``(x, y, z, w)``, like ``geometry_msgs/Quaternion`` and
``scipy.spatial.transform.Rotation``. A quaternion ``q`` maps body-frame vectors to the world
frame: ``v_world = R(q) @ v_body``. Every function takes arrays of shape ``(..., 4)`` / ``(..., 3)``
so that all segments (and all chains) are handled in one call.
"""
import numpy as np

__all__ = [
    'quat_multiply', 'quat_conjugate', 'quat_to_matrix', 'quat_rotate', 'quat_normalize',
    'quat_from_rotvec', 'quat_to_rotvec', 'quat_from_two_vectors', 'quat_integrate', 'skew',
    'quat_slerp', 'quat_axis_x', 'cross', 'IDENTITY_QUAT',
]

IDENTITY_QUAT = np.array([0.0, 0.0, 0.0, 1.0])


def quat_multiply(a, b):
    """Hamilton product ``a ⊗ b`` (apply ``b`` first, then ``a``)."""
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    c = np.empty(a.shape if a.shape == b.shape else np.broadcast_shapes(a.shape, b.shape))
    c[..., 0] = aw * bx + ax * bw + ay * bz - az * by
    c[..., 1] = aw * by - ax * bz + ay * bw + az * bx
    c[..., 2] = aw * bz + ax * by - ay * bx + az * bw
    c[..., 3] = aw * bw - ax * bx - ay * by - az * bz
    return c


def quat_conjugate(q):
    """Inverse of a unit quaternion."""
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def quat_normalize(q):
    """Return ``q / |q|`` (unit quaternions drift under integration; renormalise each step)."""
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_to_matrix(q):
    """Rotation matrices ``R`` of shape ``(..., 3, 3)`` for unit quaternions ``q``."""
    x, y, z, w = np.moveaxis(q, -1, 0)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1.0 - 2.0 * (yy + zz)
    R[..., 0, 1] = 2.0 * (xy - wz)
    R[..., 0, 2] = 2.0 * (xz + wy)
    R[..., 1, 0] = 2.0 * (xy + wz)
    R[..., 1, 1] = 1.0 - 2.0 * (xx + zz)
    R[..., 1, 2] = 2.0 * (yz - wx)
    R[..., 2, 0] = 2.0 * (xz - wy)
    R[..., 2, 1] = 2.0 * (yz + wx)
    R[..., 2, 2] = 1.0 - 2.0 * (xx + yy)
    return R


def cross(a, b):
    """``a × b`` over the last axis; ~2.5× faster than ``np.cross`` on small arrays."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    c = np.empty(a.shape if a.shape == b.shape else np.broadcast_shapes(a.shape, b.shape))
    c[..., 0] = a1 * b2 - a2 * b1
    c[..., 1] = a2 * b0 - a0 * b2
    c[..., 2] = a0 * b1 - a1 * b0
    return c


def quat_rotate(q, v):
    """Rotate body-frame vectors ``v`` into the world frame by unit quaternions ``q``."""
    u = q[..., :3]
    w = q[..., 3:4]
    t = 2.0 * cross(u, v)
    return v + w * t + cross(u, t)


def quat_axis_x(q):
    """World direction of the body +X axis, ``R(q)[:, 0]``, shape ``(..., 3)``."""
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    e = np.empty(q.shape[:-1] + (3,))
    e[..., 0] = 1.0 - 2.0 * (y * y + z * z)
    e[..., 1] = 2.0 * (x * y + w * z)
    e[..., 2] = 2.0 * (x * z - w * y)
    return e


def quat_from_rotvec(phi):
    """Unit quaternion of the rotation vector ``phi`` (axis × angle, rad)."""
    phi = np.asarray(phi, dtype=float)
    angle = np.linalg.norm(phi, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a -> 1/2 - a²/48 near zero avoids 0/0.
    small = angle < 1e-8
    scale = np.where(small, 0.5 - angle * angle / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([phi * scale, np.cos(half)], axis=-1)


def quat_to_rotvec(q):
    """Rotation vector (axis × angle, angle in [0, π]) of unit quaternions ``q``."""
    q = np.where(q[..., 3:4] < 0.0, -q, q)  # shortest rotation
    u = q[..., :3]
    s = np.linalg.norm(u, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., 3:4])
    small = s < 1e-8
    scale = np.where(small, 2.0 / np.maximum(q[..., 3:4], 1e-300), angle / np.where(small, 1.0, s))
    return u * scale


def quat_from_two_vectors(a, b):
    """Shortest-arc unit quaternion rotating direction ``a`` onto direction ``b``."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    c = cross(a, b)
    d = np.sum(a * b, axis=-1, keepdims=True)
    q = np.concatenate([c, 1.0 + d], axis=-1)
    # Antiparallel: rotate by π about any axis perpendicular to a.
    anti = (1.0 + d[..., 0]) < 1e-12
    if np.any(anti):
        axis = cross(a, np.array([1.0, 0.0, 0.0]))
        bad = np.linalg.norm(axis, axis=-1) < 1e-6
        axis = np.where(bad[..., None], cross(a, np.array([0.0, 1.0, 0.0])), axis)
        axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
        q = np.where(anti[..., None], np.concatenate([axis, np.zeros_like(d)], axis=-1), q)
    return quat_normalize(q)


def quat_integrate(q, omega, dt):
    """Advance ``q`` by the world-frame angular velocity ``omega`` held for ``dt`` (exact map)."""
    return quat_multiply(quat_from_rotvec(omega * dt), q)


def quat_slerp(q0, q1, s):
    """Spherical linear interpolation, ``s`` in [0, 1] (broadcasts over leading axes)."""
    d = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(d < 0.0, -q1, q1)
    rel = quat_multiply(q1, quat_conjugate(q0))
    return quat_multiply(quat_from_rotvec(np.asarray(s)[..., None] * quat_to_rotvec(rel)), q0)


def skew(v):
    """Cross-product matrices ``[v]×`` of shape ``(..., 3, 3)``: ``skew(a) @ b == a × b``."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1] = -v[..., 2]
    S[..., 0, 2] = v[..., 1]
    S[..., 1, 0] = v[..., 2]
    S[..., 1, 2] = -v[..., 0]
    S[..., 2, 0] = -v[..., 1]
    S[..., 2, 1] = v[..., 0]
    return S
