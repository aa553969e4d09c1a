"""Compiled joint-limit kernels (numba, nopython, no fastmath): angles, rates and projection.

The equations are those of ``limits`` (its module docstring), written per joint. Quaternions
are scalar-last ``(x, y, z, w)`` and handled as 4-tuples, vectors as 3-tuples (no allocation);
all frames are the world frame. Joint ``i``'s parent is the anchor body of its chain when
``is_first[i]`` (``anchor_q[chain_of[i]]``, ``anchor_omega[chain_of[i]]``), else segment
``i - 1``; its rest frame is ``q_parent ⊗ q_rest[i]``.
"""
import math

import numpy as np
from llvmlite import ir as llvm_ir
from numba import njit
from numba.core import types
from numba.extending import intrinsic

from .kernel_cache import ensure_fresh

ensure_fresh()      # the shared helpers' module: every kernel module imports it (``kernel_cache``)

__all__ = ['joint_angles', 'limit_terms', 'project_limits']


# -- small vector and quaternion helpers (tuples) -------------------------------------------
@njit(cache=True)
def v3(a, i):
    return (a[i, 0], a[i, 1], a[i, 2])


@njit(cache=True)
def q4(a, i):
    return (a[i, 0], a[i, 1], a[i, 2], a[i, 3])


@njit(cache=True)
def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True)
def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@njit(cache=True)
def add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@njit(cache=True)
def sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@njit(cache=True)
def scale(s, a):
    return (s * a[0], s * a[1], s * a[2])


@njit(cache=True)
def norm(a):
    return math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])


@njit(cache=True)
def qmul(a, b):
    """Hamilton product ``a ⊗ b`` (``b`` first, then ``a``)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


@njit(cache=True)
def qconj(q):
    return (-q[0], -q[1], -q[2], q[3])


@njit(cache=True)
def qnormalize(q):
    s = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / s, q[1] / s, q[2] / s, q[3] / s)


@njit(cache=True)
def qrotate(q, v):
    """``R(q) v`` (body to world)."""
    u = (q[0], q[1], q[2])
    t = scale(2.0, cross(u, v))
    return add(add(v, scale(q[3], t)), cross(u, t))


@njit(cache=True)
def qaxis_x(q):
    """World direction of the body +X axis."""
    x, y, z, w = q
    return (1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y))


@njit(cache=True)
def qmatrix(q, R):
    """The rotation matrix of the unit quaternion ``q`` (x, y, z, w) into the 3×3 ``R``."""
    x, y, z, w = q
    R[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[0, 1] = 2.0 * (x * y - w * z)
    R[0, 2] = 2.0 * (x * z + w * y)
    R[1, 0] = 2.0 * (x * y + w * z)
    R[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[1, 2] = 2.0 * (y * z - w * x)
    R[2, 0] = 2.0 * (x * z - w * y)
    R[2, 1] = 2.0 * (y * z + w * x)
    R[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@njit(cache=True)
def qfrom_rotvec(phi):
    """Unit quaternion of the rotation vector ``phi`` (axis × angle, rad)."""
    angle = norm(phi)
    half = 0.5 * angle
    if angle < 1e-8:
        s = 0.5 - angle * angle / 48.0
    else:
        s = math.sin(half) / angle
    return (phi[0] * s, phi[1] * s, phi[2] * s, math.cos(half))


@intrinsic
def sqrt_ieee(typingctx, x):
    """IEEE square root as LLVM's ``llvm.sqrt.f64``: vectorisable, unlike numba's libm call
    (which returns the same, correctly rounded, value)."""
    sig = types.float64(types.float64)

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic('llvm.sqrt', [llvm_ir.DoubleType()])
        return builder.call(fn, args)
    return sig, codegen


# Cephes' ``atan`` (S. L. Moshier): its range reduction and its rational approximation
# z + z³ P(z²)/Q(z²) on |z| ≤ 0.66; within 2 ulp of libm's ``atan2``
# (``test_atan_nonneg_is_within_two_ulps_of_atan2``).
_ATAN_P = (-8.750608600031904122785e-1, -1.615753718733365076637e1,
           -7.500855792314704667340e1, -1.228866684490136173410e2,
           -6.485021904942025371773e1)
_ATAN_Q = (2.485846490142306297962e1, 1.650270098316988542046e2,
           4.328810604912902668951e2, 4.853903996359136964868e2,
           1.945506571482613964425e2)
_ATAN_MOREBITS = 6.123233995736765886130e-17     # π/2 - fl(π/2)
_TAN_3PI_8 = 2.41421356237309504880


@njit(cache=True, inline='always', error_model='numpy')
def atan_nonneg(s, c):
    """atan2(s, c) (rad, in [0, π/2]) for s ≥ 0, c ≥ 0, not both zero: Cephes' ``atan`` of
    the ratio, reduced as -c/s, (s - c)/(s + c) or s/c (so that no ratio can overflow), in
    one division and selects, no branch and no call: a loop of them vectorises (libm's
    ``atan2`` is a call, which LLVM cannot)."""
    big = s > _TAN_3PI_8 * c
    mid = s > 0.66 * c
    num = -c if big else (s - c if mid else s)
    den = s if big else (s + c if mid else c)
    x = num / den
    y = 0.5 * math.pi if big else (0.25 * math.pi if mid else 0.0)
    more = _ATAN_MOREBITS if big else (0.5 * _ATAN_MOREBITS if mid else 0.0)
    P0, P1, P2, P3, P4 = _ATAN_P
    Q0, Q1, Q2, Q3, Q4 = _ATAN_Q
    z = x * x
    p = (((P0 * z + P1) * z + P2) * z + P3) * z + P4
    q = ((((z + Q0) * z + Q1) * z + Q2) * z + Q3) * z + Q4
    return y + ((x * (z * p / q) + x) + more)


@njit(cache=True, inline='always', error_model='numpy')
def rotvec_factor(x, y, z, w):
    """f with (x f, y f, z f) the rotation vector (axis × angle, angle in [0, π]) of the
    unit quaternion (x, y, z, w): 2 atan2(|v|, |w|)/|v|, negated if w < 0 (q and -q are the
    same rotation). Selects only, so that the bending stiffness's loop over every joint
    vectorises (``lanes``); ``qto_rotvec`` is the same arithmetic."""
    aw = abs(w)
    s = sqrt_ieee(x * x + y * y + z * z)
    small = s < 1e-8
    ss = 1.0 if small else s
    # 2 / |w| near the identity, else 2 atan2(s, |w|) / s: one division of the chosen terms
    # (both sides are computed, as selects: one division fewer than dividing each).
    num = 2.0 if small else 2.0 * atan_nonneg(ss, aw)
    den = max(aw, 1e-300) if small else ss
    f = num / den
    return -f if w < 0.0 else f


@njit(cache=True, inline='always')
def qto_rotvec(q):
    """Rotation vector (axis × angle, angle in [0, π]) of the unit quaternion ``q`` (inlined
    where it is used: a call of its own would cost the general step's stiffness loop more than
    its arithmetic)."""
    x, y, z, w = q
    f = rotvec_factor(x, y, z, w)
    return (x * f, y * f, z * f)


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
