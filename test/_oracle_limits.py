"""Oracle (test only): the NumPy implementation of ``ponytail_ros.core.limits`` before it was
compiled, kept to check the compiled kernels against.

Joint limits: swing (a cone about the rest direction) and twist (about the segment's axis).

Joint i joins segment i to its parent: the parent segment, or for a chain's first joint the
kinematic anchor body. Its rest frame is ``q_parent ⊗ q_rest`` (``Model.q_rest``: identity
for inner joints, so the rest direction is the parent segment's axis; for a first joint the
rest pose in the anchor frame, i.e. ``rest_direction`` or the hanging direction at ``reset``).
The child's rotation relative to it, ``q_rel = (q_parent ⊗ q_rest)⁻¹ ⊗ q_child``, is split
into swing and twist (``q_rel = swing ⊗ twist``, twist about the child's +X):

    swing θ = ∠(d, e)            d, e the rest frame's and the child's +X axes (world)
    twist φ = 2 atan2(x, w)      (x, y, z, w) = q_rel, w ≥ 0, so φ ∈ (-π, π]

Each limit is a one-sided constraint, ``θ ≤ θ_max`` and ``|φ| ≤ φ_max``, written as a row
of the unilateral solver (``collision``): a separation rate ``J u`` that must stay ≥ 0 and an
angular impulse along ``Jᵀ`` on the child (and the opposite on a parent segment; an anchor
body never moves). Exact rates, with Δω = ω_child - ω_parent:

    θ̇ = a · Δω                  a = d × e / |d × e|   (the swing axis)
    φ̇ = g · Δω                  g = R_child (1, (xy - wz)/(x² + w²), (wy + xz)/(x² + w²))

so the rows are ``sep = -a·Δω`` (swing) and ``sep = -σ g·Δω`` (twist, σ = sign φ).

Positions are projected exactly, not linearised (a cone is curved: its linearisation converges
slowly once the direction slides along it): ``project_limits`` turns every violating joint's
child back onto its limits (about the swing axis a by θ_max - θ, which leaves the twist
unchanged, then about its own axis by σφ_max - φ) and carries the whole distal part of the
chain along rigidly, so that the other joints' relative rotations are unchanged. With C_i the
world-frame correction of joint i computed in the current pose, segment j becomes
``C_first ⊗ … ⊗ C_j ⊗ q_j`` (a prefix product along its chain, ``log₂ N`` vectorised
passes): every joint ends exactly on its limits in one pass.
"""
import numpy as np

from ponytail_ros.core.rotations import (
    cross,
    quat_axis_x,
    quat_conjugate,
    quat_from_rotvec,
    quat_multiply,
    quat_normalize,
    quat_rotate,
)

__all__ = ['joint_angles', 'limit_rows', 'project_limits']


def _relative(model, q, anchor_q, idx):
    """Rest frames and relative rotations of joints ``idx``."""
    q_parent = model.parent_side(anchor_q, q)[idx]
    q_frame = quat_multiply(q_parent, model.q_rest[idx])
    q_rel = quat_multiply(quat_conjugate(q_frame), q[idx])
    return q_frame, np.where(q_rel[:, 3:4] < 0.0, -q_rel, q_rel)


def _swing(q_frame, q_child):
    d = quat_axis_x(q_frame)
    e = quat_axis_x(q_child)
    c = cross(d, e)
    s = np.sqrt(np.sum(c * c, axis=1))
    theta = np.arctan2(s, np.sum(d * e, axis=1))
    # The axis is undefined at θ = 0 (no row then) or π: any axis perpendicular to e will do.
    fallback = cross(e, np.where(np.abs(e[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
    a = np.where((s > 1e-9)[:, None], c / np.maximum(s, 1e-300)[:, None], fallback)
    return theta, a / np.linalg.norm(a, axis=1, keepdims=True)


def _twist(q_rel, q_child):
    x, y, z, w = q_rel[:, 0], q_rel[:, 1], q_rel[:, 2], q_rel[:, 3]
    phi = 2.0 * np.arctan2(x, w)
    den = np.maximum(x * x + w * w, 1e-12)
    g_body = np.stack([np.ones_like(x), (x * y - w * z) / den, (w * y + x * z) / den], axis=1)
    return phi, quat_rotate(q_child, g_body)


def joint_angles(model, q, anchor_q):
    """Swing θ and twist φ of every joint, ``(n,)`` each, rad (see the module docstring)."""
    idx = np.arange(model.n)
    q_frame, q_rel = _relative(model, q, anchor_q, idx)
    return _swing(q_frame, q[idx])[0], _twist(q_rel, q[idx])[0]


def limit_rows(model, q, w, anchor, margin):
    """Rows of the limits that are violated or may be within one step.

    ``margin(gap, sep)`` ``-> bool mask``: which rows to keep given the angular gap to the
    limit (rad, negative when violated) and the separation rate (rad/s, negative when
    closing). Returns a dict of row arrays (``collision`` rows) or ``None``.
    """
    idx = _limited(model)
    q_frame, q_rel = _relative(model, q, anchor.orientation, idx)
    qc = q[idx]
    swing, a = _swing(q_frame, qc)
    phi, g = _twist(q_rel, qc)
    sign = np.where(phi < 0.0, -1.0, 1.0)
    angle = np.concatenate([swing, sign * phi])
    axis = np.concatenate([a, sign[:, None] * g])
    limit = np.concatenate([model.swing_limit[idx], model.twist_limit[idx]])
    joint = np.concatenate([idx, idx])
    d_omega = w[idx] - model.parent_side(anchor.angular_velocity, w)[idx]
    sep = -np.einsum('ij,ij->i', axis, np.concatenate([d_omega, d_omega]))
    gap = limit - angle                       # inf - angle where a limit is off
    keep = margin(gap, sep) & np.isfinite(limit)
    if not np.any(keep):
        return None
    joint, axis = joint[keep], axis[keep]
    return dict(seg=joint, par=model.parent[joint], lin=np.zeros_like(axis), ang=-axis,
                ang_par=axis, depth=-gap[keep], sep=sep[keep])


def _limited(model):
    """Indices of the joints with a swing or a twist limit (cached on the model)."""
    idx = getattr(model, '_limited_joints', None)
    if idx is None:
        idx = np.flatnonzero(np.isfinite(model.swing_limit) | np.isfinite(model.twist_limit))
        model._limited_joints = idx
    return idx


def project_limits(model, q, anchor_q, tolerance=0.0):
    """Orientations ``(n, 4)`` with every joint within its limits (see the module docstring),
    or ``None`` when no joint exceeds a limit by more than ``tolerance`` (rad)."""
    idx = _limited(model)
    q_frame, q_rel = _relative(model, q, anchor_q, idx)
    qc = q[idx]
    theta, a = _swing(q_frame, qc)
    over_s = theta - model.swing_limit[idx]
    x, w = q_rel[:, 0], q_rel[:, 3]
    phi = 2.0 * np.arctan2(x, w)
    over_t = np.abs(phi) - model.twist_limit[idx]
    fix_s, fix_t = over_s > tolerance, over_t > tolerance
    if not (np.any(fix_s) or np.any(fix_t)):
        return None
    # Twist first, in the child's body frame (about its own +X), then the swing in the world.
    twist = np.where(fix_t, -np.sign(phi) * over_t, 0.0)
    q_new = quat_multiply(qc, quat_from_rotvec(twist[:, None] * np.array([[1.0, 0.0, 0.0]])))
    swing = np.where(fix_s, -over_s, 0.0)
    q_new = quat_multiply(quat_from_rotvec(swing[:, None] * a), q_new)
    corr = np.tile(np.array([0.0, 0.0, 0.0, 1.0]), (model.n, 1))
    corr[idx] = quat_multiply(q_new, quat_conjugate(qc))
    # Prefix product along each chain (Hillis–Steele scan): P_j = C_first ⊗ … ⊗ C_j.
    start = model.chain_start[model.chain_of]
    pos = np.arange(model.n)
    shift = 1
    while shift < int(np.max(model.chain_end - model.chain_start)):
        has = pos - shift >= start
        corr[has] = quat_multiply(corr[pos[has] - shift], corr[has])
        shift *= 2
    return quat_normalize(quat_multiply(corr, q))
