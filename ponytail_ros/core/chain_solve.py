"""The joint system A = J M⁻¹ Jᵀ of all chains: block-tridiagonal LDLᵀ, compiled.

A has one 3×3 block row per joint (joint i holds segment i's proximal point on its parent):
diagonal blocks ``D[i]`` and coupling blocks ``L[i] = A[i, i-1]`` (zero where ``is_first[i]``:
chains do not couple, so a crowd of chains is one factorisation). Like MuJoCo's
``mj_factorM`` / ``mj_solveM`` pair, the factorisation is done once per configuration and
solved for as many right-hand sides as the step needs:

    A = (1 + 𝓛) P (1 + 𝓛)ᵀ,   P_i = D_i - L_i P_{i-1}⁻¹ L_iᵀ,   𝓛_i = L_i P_{i-1}⁻¹,

with block-diagonal pivots P (3×3, symmetric positive definite) and the sub-diagonal 𝓛. The
factors kept are ``Pinv[i]`` = P_i⁻¹ (inverted once, by cofactors) and ``Lo[i]`` = 𝓛_i, so a
solve is multiplications only: no square root and no division in either pass. Divisions and
square roots cost ten multiplications each and lie on the recursion's critical path; a
block Cholesky would need six per joint. O(n) in time and memory, no LAPACK call.

Joint i's block row, from the segments' mass properties (Hecker's A of Eq. 14, per joint):

    A_ii = (1/m_i + 1/m_{i-1}) 1 - G_i - G_{i-1},   A_i,i-1 = -(1/m_{i-1} 1 + G_{i-1}),
    G_i = [h_i]× I_i⁻¹ [h_i]×,   h_i = (l_i/2) e_i (centre to distal joint, e_i the +X axis),

(the terms of segment i-1 only below a parent segment). ``joint_row`` is that equation and
its pivot, in scalars: ``factor`` runs it over a range of whole chains, and the steps that
fuse the factorisation with their own sweep (``step_rk4``'s accelerations, ``lanes``' SIMD
blocks) call it per joint, so every caller forms and factorises A with the same operations.

``factor`` returns False (nothing is raised inside compiled code) when a pivot is not positive
definite (Sylvester's criterion on P_i): A is then not positive definite, which a valid chain
never produces (a blow-up does).
"""
from collections import namedtuple

import numba as nb
import numpy as np

from .kernel_cache import ensure_fresh
from .vec import qaxis_x_s, qmatrix_s

ensure_fresh()          # before any kernel's cache is loaded (see ``kernel_cache``)

__all__ = ['JointModel', 'factor', 'solve', 'solve_from', 'solve_many', 'invert_pivot', 'pivot',
           'joint_row', 'store_factors', 'mass_properties', 'segment_G',
           'G_axisymmetric', 'G_general', 'inv_inertia_axisymmetric', 'store_block', 'block',
           'mul9', 'ZERO6', 'ZERO9']

#: What ``factor`` reads of a model (``step.StepModel`` has these fields too): ``length``
#: ``(n,)`` m, ``inv_mass`` ``(n,)`` 1/kg, ``inv_inertia`` ``(n, 3)`` inverse principal
#: moments (axial first) 1/(kg·m²), ``is_first`` ``(n,)`` bool, ``axisymmetric`` bool (every
#: segment's two perpendicular moments equal).
JointModel = namedtuple('JointModel', ['length', 'inv_mass', 'inv_inertia', 'is_first',
                                       'axisymmetric'])

_inline = nb.njit(cache=True, inline='always')

ZERO9 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
ZERO6 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@_inline
def invert_pivot(p):
    """``(ok, P⁻¹)`` for the symmetric 3×3 P given by its upper triangle
    ``p = (P00, P01, P02, P11, P12, P22)`` (P⁻¹ likewise, by cofactors); ok False unless P is
    positive definite (Sylvester's criterion), and P⁻¹ is then zeros. Scalars in and out: a
    joint's pivot stays in registers along the factorisation's recursion."""
    s00, s01, s02, s11, s12, s22 = p
    c00 = s11 * s22 - s12 * s12
    c01 = s02 * s12 - s01 * s22
    c02 = s01 * s12 - s02 * s11
    det = s00 * c00 + s01 * c01 + s02 * c02
    if not (s00 > 0.0 and s00 * s11 - s01 * s01 > 0.0 and det > 0.0):
        return False, ZERO6
    r = 1.0 / det
    return True, (c00 * r, c01 * r, c02 * r, (s00 * s22 - s02 * s02) * r,
                  (s01 * s02 - s00 * s12) * r, (s00 * s11 - s01 * s01) * r)


@_inline
def pivot(d, l, pp):
    """One block row of the factorisation, in scalars: ``(ok, 𝓛_i, P_i⁻¹)`` from the row's
    diagonal block D_i (symmetric: its upper triangle ``(00, 01, 02, 11, 12, 22)``), its
    coupling block L_i = A[i, i-1] (row-major ``(00, 01, 02, 10, ..., 22)``) and the previous
    row's P_{i-1}⁻¹ (upper triangle); 𝓛_i = L_i P_{i-1}⁻¹ (row-major),
    P_i = D_i - 𝓛_i L_iᵀ."""
    l00, l01, l02, l10, l11, l12, l20, l21, l22 = l
    p00, p01, p02, p11, p12, p22 = pp
    # 𝓛 = L P⁻¹: row a of L times column b of P⁻¹
    o00 = l00 * p00 + l01 * p01 + l02 * p02
    o01 = l00 * p01 + l01 * p11 + l02 * p12
    o02 = l00 * p02 + l01 * p12 + l02 * p22
    o10 = l10 * p00 + l11 * p01 + l12 * p02
    o11 = l10 * p01 + l11 * p11 + l12 * p12
    o12 = l10 * p02 + l11 * p12 + l12 * p22
    o20 = l20 * p00 + l21 * p01 + l22 * p02
    o21 = l20 * p01 + l21 * p11 + l22 * p12
    o22 = l20 * p02 + l21 * p12 + l22 * p22
    # P = D - 𝓛 Lᵀ (symmetric: the upper triangle)
    ok, pinv = invert_pivot((d[0] + -(o00 * l00 + o01 * l01 + o02 * l02),
                             d[1] + -(o00 * l10 + o01 * l11 + o02 * l12),
                             d[2] + -(o00 * l20 + o01 * l21 + o02 * l22),
                             d[3] + -(o10 * l10 + o11 * l11 + o12 * l12),
                             d[4] + -(o10 * l20 + o11 * l21 + o12 * l22),
                             d[5] + -(o20 * l20 + o21 * l21 + o22 * l22)))
    return ok, (o00, o01, o02, o10, o11, o12, o20, o21, o22), pinv


@_inline
def store_factors(Pinv, Lo, i, pinv, lo):
    """Row i's factors into ``Pinv[i]`` (from its upper triangle) and ``Lo[i]``."""
    Pinv[i, 0, 0], Pinv[i, 0, 1], Pinv[i, 0, 2] = pinv[0], pinv[1], pinv[2]
    Pinv[i, 1, 0], Pinv[i, 1, 1], Pinv[i, 1, 2] = pinv[1], pinv[3], pinv[4]
    Pinv[i, 2, 0], Pinv[i, 2, 1], Pinv[i, 2, 2] = pinv[2], pinv[4], pinv[5]
    Lo[i, 0, 0], Lo[i, 0, 1], Lo[i, 0, 2] = lo[0], lo[1], lo[2]
    Lo[i, 1, 0], Lo[i, 1, 1], Lo[i, 1, 2] = lo[3], lo[4], lo[5]
    Lo[i, 2, 0], Lo[i, 2, 1], Lo[i, 2, 2] = lo[6], lo[7], lo[8]


# -- a segment's mass properties and G = [h]× I⁻¹ [h]× (scalars: no 3×3 scratch arrays) ---------
@_inline
def inv_inertia_axisymmetric(e0, e1, e2, ia, ip):
    """World I⁻¹ = I_p⁻¹ 1 + (I_a⁻¹ - I_p⁻¹) e eᵀ (row-major 9-tuple) of an axisymmetric
    segment of axis e, inverse moments ``ia`` (axial), ``ip`` (1/(kg·m²))."""
    k = ia - ip
    ke0, ke1, ke2 = k * e0, k * e1, k * e2
    return (ke0 * e0 + ip, ke0 * e1, ke0 * e2,
            ke1 * e0, ke1 * e1 + ip, ke1 * e2,
            ke2 * e0, ke2 * e1, ke2 * e2 + ip)


@_inline
def _rdr(Ra, Rb, d):
    """(R diag(d) Rᵀ)_ab from rows a and b of R."""
    s = 0.0
    s += Ra[0] * Rb[0] * d[0]
    s += Ra[1] * Rb[1] * d[1]
    s += Ra[2] * Rb[2] * d[2]
    return s


@_inline
def _inv_inertia_general(R, d):
    """World I⁻¹ = R diag(d) Rᵀ (row-major 9-tuple), d the inverse principal moments."""
    R0, R1, R2 = R
    return (_rdr(R0, R0, d), _rdr(R0, R1, d), _rdr(R0, R2, d),
            _rdr(R1, R0, d), _rdr(R1, R1, d), _rdr(R1, R2, d),
            _rdr(R2, R0, d), _rdr(R2, R1, d), _rdr(R2, R2, d))


@_inline
def mass_properties(axisymmetric, x, y, z, w, i0, i1, i2):
    """Axis e (the body +X axis in the world) and world I⁻¹ (row-major 9-tuple) of a segment
    at orientation (x, y, z, w), inverse principal moments (i0, i1, i2) (axial first)."""
    if axisymmetric:
        e0, e1, e2 = qaxis_x_s(x, y, z, w)
        return e0, e1, e2, inv_inertia_axisymmetric(e0, e1, e2, i0, i1)
    R = qmatrix_s(x, y, z, w)
    return R[0][0], R[1][0], R[2][0], _inv_inertia_general(R, (i0, i1, i2))


@_inline
def G_axisymmetric(h0, h1, h2, ip):
    """G = [h]× I⁻¹ [h]× = (h hᵀ - |h|² 1) / I_p of an axisymmetric segment (h ∥ its axis):
    the upper triangle (00, 01, 02, 11, 12, 22)."""
    hh = h0 * h0 + h1 * h1 + h2 * h2
    return ((h0 * h0 - hh) * ip, h0 * h1 * ip, h0 * h2 * ip, (h1 * h1 - hh) * ip,
            h1 * h2 * ip, (h2 * h2 - hh) * ip)


@_inline
def G_general(h0, h1, h2, X):
    """G = [h]× I⁻¹ [h]× for the world I⁻¹ ``X`` (row-major), with
    [h]× = ((0, -h2, h1), (h2, 0, -h0), (-h1, h0, 0)): the upper triangle."""
    a00 = -h2 * X[3] + h1 * X[6]
    a01 = -h2 * X[4] + h1 * X[7]
    a02 = -h2 * X[5] + h1 * X[8]
    a10 = h2 * X[0] - h0 * X[6]
    a11 = h2 * X[1] - h0 * X[7]
    a12 = h2 * X[2] - h0 * X[8]
    a20 = -h1 * X[0] + h0 * X[3]
    a21 = -h1 * X[1] + h0 * X[4]
    return (a01 * h2 - a02 * h1, -a00 * h2 + a02 * h0, a00 * h1 - a01 * h0,
            -a10 * h2 + a12 * h0, a10 * h1 - a11 * h0, a20 * h1 - a21 * h0)


@_inline
def segment_G(axisymmetric, h0, h1, h2, ip, X):
    """G of a segment (``G_axisymmetric`` with its perpendicular inverse moment ``ip``, else
    ``G_general`` with its world I⁻¹ ``X``)."""
    if axisymmetric:
        return G_axisymmetric(h0, h1, h2, ip)
    return G_general(h0, h1, h2, X)


@_inline
def block(X, i):
    """The 3×3 block ``X[i]`` as a row-major 9-tuple."""
    return (X[i, 0, 0], X[i, 0, 1], X[i, 0, 2], X[i, 1, 0], X[i, 1, 1], X[i, 1, 2],
            X[i, 2, 0], X[i, 2, 1], X[i, 2, 2])


@_inline
def store_block(X, i, b):
    """The row-major 9-tuple ``b`` into the 3×3 block ``X[i]``."""
    X[i, 0, 0], X[i, 0, 1], X[i, 0, 2] = b[0], b[1], b[2]
    X[i, 1, 0], X[i, 1, 1], X[i, 1, 2] = b[3], b[4], b[5]
    X[i, 2, 0], X[i, 2, 1], X[i, 2, 2] = b[6], b[7], b[8]


@_inline
def mul9(X, v0, v1, v2):
    """The row-major 3×3 ``X`` times v."""
    return (X[0] * v0 + X[1] * v1 + X[2] * v2,
            X[3] * v0 + X[4] * v1 + X[5] * v2,
            X[6] * v0 + X[7] * v1 + X[8] * v2)


# -- the factorisation ----------------------------------------------------------------------------
@_inline
def joint_row(first, pinv_prev, im, imp, g, gp):
    """Joint i's block row of A (the module docstring's equation), factorised (``pivot``):
    ``(ok, 𝓛_i, P_i⁻¹)``. ``g``, ``gp``: G of the child segment and of the parent (upper
    triangles), ``im``, ``imp`` their inverse masses; ``first``: no parent segment (``imp``,
    ``gp`` unused), ``pinv_prev``: the previous row's P⁻¹ (upper triangle)."""
    g00, g01, g02, g11, g12, g22 = g
    if first:
        ok, pinv = invert_pivot((im - g00, -g01, -g02, im - g11, -g12, im - g22))
        return ok, ZERO9, pinv
    p00, p01, p02, p11, p12, p22 = gp
    s = im + imp
    d = (s - g00 - p00, -g01 - p01, -g02 - p02, s - g11 - p11, -g12 - p12, s - g22 - p22)
    l = (-imp - p00, -p01, -p02, -p01, -imp - p11, -p12, -p02, -p12, -imp - p22)
    return pivot(d, l, pinv_prev)


@nb.njit(cache=True, _nrt=False)
def factor(J, q, s, e, hv, Iinv, Pinv, Lo):
    """A = J M⁻¹ Jᵀ of the whole chains of segments ``s:e`` at orientations ``q`` ``(n, 4)``,
    factorised row by row (``joint_row``) into ``Pinv`` = P⁻¹ and ``Lo`` = 𝓛 ``(n, 3, 3)``,
    with the half-vectors ``hv`` ``(n, 3)`` (h = (l/2) e, m) and world inverse inertias
    ``Iinv`` ``(n, 3, 3)`` it is formed from written on the way (rows ``s:e`` of each; chains
    do not couple, so a range's factors do not depend on the other chains). ``J``: the model
    (``JointModel``, or any structure with its fields, such as ``step.StepModel``).

    Returns True on success, False if A is not positive definite.
    """
    g = pinv = ZERO6
    for i in range(s, e):
        e0, e1, e2, X = mass_properties(J.axisymmetric, q[i, 0], q[i, 1], q[i, 2], q[i, 3],
                                        J.inv_inertia[i, 0], J.inv_inertia[i, 1],
                                        J.inv_inertia[i, 2])
        store_block(Iinv, i, X)
        hl = 0.5 * J.length[i]
        h0, h1, h2 = hl * e0, hl * e1, hl * e2
        hv[i, 0], hv[i, 1], hv[i, 2] = h0, h1, h2
        gp = g
        g = segment_G(J.axisymmetric, h0, h1, h2, J.inv_inertia[i, 1], X)
        first = J.is_first[i]
        imp = 0.0 if first else J.inv_mass[i - 1]
        ok, lo, pinv = joint_row(first, pinv, J.inv_mass[i], imp, g, gp)
        if not ok:
            return False
        store_factors(Pinv, Lo, i, pinv, lo)
    return True


@nb.njit(cache=True, _nrt=False)
def solve(Pinv, Lo, is_first, b):
    """Solve A x = b with the factors of ``factor``; ``b`` ``(n, 3)`` is overwritten by x."""
    solve_from(Pinv, Lo, is_first, b, np.int64(1))      # (a literal would specialise it)


@nb.njit(cache=True, _nrt=False)
def solve_from(Pinv, Lo, is_first, b, i0):
    """``solve`` for a right-hand side that is zero before row ``i0`` (a contact row's
    response): the forward pass starts there (before, it would subtract zeros), the backward
    pass is whole."""
    n = b.shape[0]
    # Forward: (1 + 𝓛) z = b.
    for i in range(max(i0, 1), n):
        if not is_first[i]:
            z0, z1, z2 = b[i - 1, 0], b[i - 1, 1], b[i - 1, 2]
            b[i, 0] -= Lo[i, 0, 0] * z0 + Lo[i, 0, 1] * z1 + Lo[i, 0, 2] * z2
            b[i, 1] -= Lo[i, 1, 0] * z0 + Lo[i, 1, 1] * z1 + Lo[i, 1, 2] * z2
            b[i, 2] -= Lo[i, 2, 0] * z0 + Lo[i, 2, 1] * z1 + Lo[i, 2, 2] * z2
    # Pivots and backward: (1 + 𝓛)ᵀ x = P⁻¹ z.
    for i in range(n - 1, -1, -1):
        z0, z1, z2 = b[i, 0], b[i, 1], b[i, 2]
        y0 = Pinv[i, 0, 0] * z0 + Pinv[i, 0, 1] * z1 + Pinv[i, 0, 2] * z2
        y1 = Pinv[i, 1, 0] * z0 + Pinv[i, 1, 1] * z1 + Pinv[i, 1, 2] * z2
        y2 = Pinv[i, 2, 0] * z0 + Pinv[i, 2, 1] * z1 + Pinv[i, 2, 2] * z2
        if i + 1 < n and not is_first[i + 1]:
            x0, x1, x2 = b[i + 1, 0], b[i + 1, 1], b[i + 1, 2]
            y0 -= Lo[i + 1, 0, 0] * x0 + Lo[i + 1, 1, 0] * x1 + Lo[i + 1, 2, 0] * x2
            y1 -= Lo[i + 1, 0, 1] * x0 + Lo[i + 1, 1, 1] * x1 + Lo[i + 1, 2, 1] * x2
            y2 -= Lo[i + 1, 0, 2] * x0 + Lo[i + 1, 1, 2] * x1 + Lo[i + 1, 2, 2] * x2
        b[i, 0], b[i, 1], b[i, 2] = y0, y1, y2


@nb.njit(cache=True, _nrt=False)
def solve_many(Pinv, Lo, is_first, B):
    """Solve A X = B for ``B`` ``(k, n, 3)`` (k right-hand sides), in place."""
    for r in range(B.shape[0]):
        solve(Pinv, Lo, is_first, B[r])
