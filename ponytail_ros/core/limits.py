"""Joint limits: swing (a cone about the rest direction) and twist (about the segment's axis).

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
``C_first ⊗ … ⊗ C_j ⊗ q_j`` (a running product along its chain): every joint ends exactly
on its limits in one pass.

The equations run compiled, joint by joint (``limit_kernels``); this module is their Python
layer for the tests and the simulator's ``joint_angles``. ``collision``'s compiled resolve
calls the same kernels.
"""
import numpy as np

from . import limit_kernels as LK

__all__ = ['joint_angles', 'limit_rows', 'project_limits']


def _f(a):
    """A writable C-contiguous float64 array, the type the kernels are compiled for."""
    a = np.ascontiguousarray(a, dtype=float)
    return a if a.flags.writeable else a.copy()


def joint_angles(model, q, anchor_q):
    """Swing θ and twist φ of every joint, ``(n,)`` each, rad (see the module docstring)."""
    swing, twist = np.empty(model.n), np.empty(model.n)
    LK.joint_angles(_f(q), _f(anchor_q), _f(model.q_rest), model.is_first,
                    model.chain_of.astype(np.int64), swing, twist)
    return swing, twist


def limit_rows(model, q, w, anchor, margin):
    """Rows of the limits that are violated or may be within one step.

    ``margin(gap, sep)`` ``-> bool mask``: which rows to keep given the angular gap to the
    limit (rad, negative when violated) and the separation rate (rad/s, negative when
    closing). Returns a dict of row arrays (``collision`` rows: the swing rows of every
    limited joint, then its twist rows) or ``None``.
    """
    idx = _limited(model)
    k = idx.size
    axis, gap, sep = np.empty((2 * k, 3)), np.empty(2 * k), np.empty(2 * k)
    LK.limit_terms(_f(q), _f(w), _f(anchor.orientation), _f(anchor.angular_velocity),
                   _f(model.q_rest), model.is_first, model.chain_of.astype(np.int64), idx,
                   _f(model.swing_limit), _f(model.twist_limit), axis, gap, sep)
    limit = np.concatenate([model.swing_limit[idx], model.twist_limit[idx]])
    joint = np.concatenate([idx, idx])
    keep = margin(gap, sep) & np.isfinite(limit)
    if not np.any(keep):
        return None
    joint, axis = joint[keep], axis[keep]
    return dict(seg=joint, par=model.parent[joint], lin=np.zeros_like(axis), ang=-axis,
                ang_par=axis, depth=-gap[keep], sep=sep[keep])


def _limited(model):
    """Indices of the joints with a swing or a twist limit."""
    return np.flatnonzero(np.isfinite(model.swing_limit)
                          | np.isfinite(model.twist_limit)).astype(np.int64)


def project_limits(model, q, anchor_q, tolerance=0.0):
    """Orientations ``(n, 4)`` with every joint within its limits (see the module docstring),
    or ``None`` when no joint exceeds a limit by more than ``tolerance`` (rad)."""
    out = np.empty((model.n, 4))
    i64 = np.int64
    if not LK.project_limits(_f(q), _f(anchor_q), _f(model.q_rest), model.is_first,
                             model.chain_of.astype(i64), model.chain_start.astype(i64),
                             model.chain_end.astype(i64), _limited(model),
                             _f(model.swing_limit), _f(model.twist_limit), float(tolerance),
                             out):
        return None
    return out
