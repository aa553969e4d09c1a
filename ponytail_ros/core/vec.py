"""Small vector and quaternion algebra of every compiled kernel (numba, nopython, no fastmath).

Quaternions are scalar-last ``(x, y, z, w)``, body to world; vectors are 3-tuples. Two forms of
the same equations, each written once:

* component form (names ending ``_s``, and the row forms ``qaxis_x_at``, ``qnormalize_at``):
  scalars in, a tuple of scalars out, inlined into the caller (``inline='always'``): the loops
  of the step and of the SIMD lanes keep every value in registers and LLVM can vectorise them
  (no call, no array or tuple argument whose reference counts a call would pay);
* tuple form (``cross(a, b)``, ``qmul(a, b)``, ...): the same arithmetic on tuples, compiled
  once as small functions, for the kernels where a call costs nothing measurable (contacts,
  limits, head estimation, the state queries).

Frames and units: whatever the caller's are (all kernels work in the world frame, SI).
"""
import math

import numpy as np
from llvmlite import ir as llvm_ir
from numba import njit
from numba.core import types
from numba.extending import intrinsic

from .kernel_cache import ensure_fresh

ensure_fresh()      # the shared helpers' module: every kernel module imports it (``kernel_cache``)

__all__ = ['cross_s', 'qmul_s', 'qrot_s', 'qaxis_x_s', 'qmatrix_s', 'qfrom_rotvec_s',
           'qaxis_x_at', 'qnormalize_at', 'v3', 'q4', 'dot', 'cross', 'add', 'sub', 'scale',
           'norm', 'qmul', 'qconj', 'qnormalize', 'qrotate', 'qaxis_x', 'qmatrix',
           'qfrom_rotvec', 'sqrt_ieee', 'atan_nonneg', 'rotvec_factor', 'qto_rotvec']

_inline = njit(cache=True, inline='always')


# -- component form ------------------------------------------------------------------------------
@_inline
def cross_s(a0, a1, a2, b0, b1, b2):
    """a × b."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@_inline
def qmul_s(ax, ay, az, aw, bx, by, bz, bw):
    """Hamilton product a ⊗ b (``b`` first, then ``a``)."""
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


@_inline
def qrot_s(qx, qy, qz, qw, v0, v1, v2):
    """R(q) v, body to world: v + w t + u × t with t = 2 u × v, u = (qx, qy, qz) (q need not
    be exactly unit: the formula of ``rotations.quat_rotate``)."""
    t0, t1, t2 = cross_s(qx, qy, qz, v0, v1, v2)
    t0, t1, t2 = 2.0 * t0, 2.0 * t1, 2.0 * t2
    c0, c1, c2 = cross_s(qx, qy, qz, t0, t1, t2)
    return v0 + qw * t0 + c0, v1 + qw * t1 + c1, v2 + qw * t2 + c2


@_inline
def qaxis_x_s(x, y, z, w):
    """World direction of the body +X axis, R(q)[:, 0]."""
    return 1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)


@_inline
def qmatrix_s(x, y, z, w):
    """Rows of R(q), body to world (3 3-tuples: no 3×3 array to allocate)."""
    return ((1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)),
            (2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)),
            (2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)))


@_inline
def qfrom_rotvec_s(p0, p1, p2):
    """Unit quaternion of the rotation vector p (axis × angle, rad)."""
    angle = np.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    half = 0.5 * angle
    if angle < 1e-8:
        s = 0.5 - angle * angle / 48.0
    else:
        s = np.sin(half) / angle
    return p0 * s, p1 * s, p2 * s, np.cos(half)


@_inline
def qaxis_x_at(q, i):
    """``qaxis_x_s`` of row i of the quaternions ``q`` ``(n, 4)``."""
    return qaxis_x_s(q[i, 0], q[i, 1], q[i, 2], q[i, 3])


@_inline
def qnormalize_at(q, i):
    """Row i of the quaternions ``q`` ``(n, 4)`` scaled to unit length, in place."""
    r = 1.0 / np.sqrt(q[i, 0] ** 2 + q[i, 1] ** 2 + q[i, 2] ** 2 + q[i, 3] ** 2)
    q[i, 0] *= r
    q[i, 1] *= r
    q[i, 2] *= r
    q[i, 3] *= r


# -- tuple form ----------------------------------------------------------------------------------
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
    return cross_s(a[0], a[1], a[2], b[0], b[1], b[2])


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
    return qmul_s(a[0], a[1], a[2], a[3], b[0], b[1], b[2], b[3])


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
    return qrot_s(q[0], q[1], q[2], q[3], v[0], v[1], v[2])


@njit(cache=True)
def qaxis_x(q):
    """World direction of the body +X axis."""
    return qaxis_x_s(q[0], q[1], q[2], q[3])


@njit(cache=True)
def qmatrix(q, R):
    """The rotation matrix of the unit quaternion ``q`` (x, y, z, w) into the 3×3 ``R``."""
    rows = qmatrix_s(q[0], q[1], q[2], q[3])
    for a in range(3):
        for b in range(3):
            R[a, b] = rows[a][b]


@njit(cache=True)
def qfrom_rotvec(phi):
    """Unit quaternion of the rotation vector ``phi`` (axis × angle, rad)."""
    return qfrom_rotvec_s(phi[0], phi[1], phi[2])


# -- square root and rotation vectors that vectorise ---------------------------------------------
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
