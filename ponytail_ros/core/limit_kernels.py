"""Compiled joint-limit kernels (numba, nopython, no fastmath): angles, rates and projection.

The equations are those of ``limits`` (its module docstring), written per joint. Quaternions
are scalar-last ``(x, y, z, w)`` and handled as 4-tuples, vectors as 3-tuples (no allocation);
all frames are the world frame. Joint ``i``'s parent is the anchor body of its chain when
``is_first[i]`` (``anchor_q[chain_of[i]]``, ``anchor_omega[chain_of[i]]``), else segment
``i - 1``; its rest frame is ``q_parent ⊗ q_rest[i]``.
"""
import math

import numpy as np
from numba import njit

from .vec import (
    cross,
    dot,
    norm,
    q4,
    qaxis_x,
    qconj,
    qfrom_rotvec,
    qmul,
    qnormalize,
    qrotate,
    scale,
    sub,
    v3,
)

__all__ = ['joint_angles', 'limit_terms', 'project_limits']


# -- swing and twist of one joint ----------------------------------------------------------
@njit(cache=True)
def relative(q, anchor_q, q_rest, is_first, chain_of, i):
    """Rest frame ``q_parent ⊗ q_rest[i]`` of joint ``i`` and the child's rotation relative
    to it (sign chosen so that w ≥ 0)."""
    q_parent = q4(anchor_q, chain_of[i]) if is_first[i] else q4(q, i - 1)
    q_frame = qmul(q_parent, q4(q_rest, i))
    r = qmul(qconj(q_frame), q4(q, i))
    if r[3] < 0.0:
        r = (-r[0], -r[1], -r[2], -r[3])
    return q_frame, r


@njit(cache=True)
def swing(q_frame, q_child):
    """Swing angle θ = ∠(d, e) and the unit swing axis a = d × e / |d × e|."""
    d = qaxis_x(q_frame)
    e = qaxis_x(q_child)
    c = cross(d, e)
    s = norm(c)
    theta = math.atan2(s, dot(d, e))
    if s > 1e-9:
        a = (c[0] / max(s, 1e-300), c[1] / max(s, 1e-300), c[2] / max(s, 1e-300))
    else:
        # Undefined at θ = 0 (no row then) or π: any axis perpendicular to e.
        ref = (1.0, 0.0, 0.0) if abs(e[0]) < 0.9 else (0.0, 1.0, 0.0)
        a = cross(e, ref)
    na = norm(a)
    return theta, (a[0] / na, a[1] / na, a[2] / na)


@njit(cache=True)
def twist(q_rel, q_child):
    """Twist φ = 2 atan2(x, w) and its rate axis g (φ̇ = g · Δω), world frame."""
    x, y, z, w = q_rel
    phi = 2.0 * math.atan2(x, w)
    den = max(x * x + w * w, 1e-12)
    g = qrotate(q_child, (1.0, (x * y - w * z) / den, (w * y + x * z) / den))
    return phi, g


# -- kernels ----------------------------------------------------------------------------------
@njit(cache=True)
def joint_angles(q, anchor_q, q_rest, is_first, chain_of, out_swing, out_twist):
    """Swing θ and twist φ of every joint (rad), into ``out_swing``, ``out_twist`` ``(n,)``."""
    for i in range(q.shape[0]):
        q_frame, q_rel = relative(q, anchor_q, q_rest, is_first, chain_of, i)
        out_swing[i] = swing(q_frame, q4(q, i))[0]
        out_twist[i] = twist(q_rel, q4(q, i))[0]


@njit(cache=True)
def limit_terms(q, w, anchor_q, anchor_omega, q_rest, is_first, chain_of, idx, swing_limit,
                twist_limit, axis, gap, sep):
    """Every limit of the joints ``idx`` (``k`` of them) as a candidate row: first the ``k``
    swing rows, then the ``k`` twist rows. Writes the row's axis (``(2k, 3)``: a, or σ g for
    a twist, σ = sign φ), its angular gap to the limit (rad, negative when violated; inf when
    off) and its separation rate ``-axis · Δω`` (rad/s, negative when closing)."""
    k = idx.shape[0]
    for r in range(k):
        i = idx[r]
        q_frame, q_rel = relative(q, anchor_q, q_rest, is_first, chain_of, i)
        qc = q4(q, i)
        theta, a = swing(q_frame, qc)
        phi, g = twist(q_rel, qc)
        sign = -1.0 if phi < 0.0 else 1.0
        w_parent = v3(anchor_omega, chain_of[i]) if is_first[i] else v3(w, i - 1)
        d_omega = sub(v3(w, i), w_parent)
        for c in range(3):
            axis[r, c] = a[c]
            axis[k + r, c] = sign * g[c]
        gap[r] = swing_limit[i] - theta
        gap[k + r] = twist_limit[i] - sign * phi
        sep[r] = -dot(a, d_omega)
        sep[k + r] = -(sign * g[0] * d_omega[0] + sign * g[1] * d_omega[1]
                       + sign * g[2] * d_omega[2])


@njit(cache=True, _nrt=True)
def project_limits(q, anchor_q, q_rest, is_first, chain_of, chain_start, chain_end, idx,
                   swing_limit, twist_limit, tolerance, out):
    """Orientations with every joint within its limits into ``out`` ``(n, 4)``; returns False
    (``out`` untouched) when no joint exceeds a limit by more than ``tolerance`` (rad).

    Each violating joint's child is turned back onto its limits (about its own +X by
    σφ_max - φ, then about the swing axis by θ_max - θ): a world-frame correction C_i; segment
    j becomes ``C_first ⊗ … ⊗ C_j ⊗ q_j`` (prefix product along its chain), so the other
    joints' relative rotations are unchanged.
    """
    n = q.shape[0]
    corr = np.zeros((n, 4))
    corr[:, 3] = 1.0
    any_fix = False
    for r in range(idx.shape[0]):
        i = idx[r]
        q_frame, q_rel = relative(q, anchor_q, q_rest, is_first, chain_of, i)
        qc = q4(q, i)
        theta, a = swing(q_frame, qc)
        over_s = theta - swing_limit[i]
        phi = 2.0 * math.atan2(q_rel[0], q_rel[3])
        over_t = abs(phi) - twist_limit[i]
        fix_s, fix_t = over_s > tolerance, over_t > tolerance
        if not (fix_s or fix_t):
            continue
        any_fix = True
        # Twist first, in the child's body frame (about its own +X), then the swing (world).
        tw = 0.0
        if fix_t:
            tw = -over_t if phi > 0.0 else (over_t if phi < 0.0 else 0.0)
        q_new = qmul(qc, qfrom_rotvec((tw, 0.0, 0.0)))
        sw = -over_s if fix_s else 0.0
        q_new = qmul(qfrom_rotvec(scale(sw, a)), q_new)
        c = qmul(q_new, qconj(qc))
        for j in range(4):
            corr[i, j] = c[j]
    if not any_fix:
        return False
    for ch in range(chain_start.shape[0]):
        acc = (0.0, 0.0, 0.0, 1.0)
        for i in range(chain_start[ch], chain_end[ch]):
            acc = qmul(acc, q4(corr, i))          # P_i = C_first ⊗ … ⊗ C_i
            qi = qnormalize(qmul(acc, q4(q, i)))
            for j in range(4):
                out[i, j] = qi[j]
    return True
