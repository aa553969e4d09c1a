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

``factor`` returns False (nothing is raised inside compiled code) when a pivot is not positive
definite (Sylvester's criterion on P_i): A is then not positive definite, which a valid chain
never produces (a blow-up does).
"""
import numba as nb

from .kernel_cache import ensure_fresh

ensure_fresh()          # before any kernel's cache is loaded (see ``kernel_cache``)

__all__ = ['factor', 'solve', 'solve_from', 'solve_many', 'invert_pivot', 'pivot']

_ZERO9 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
_ZERO6 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@nb.njit(cache=True, inline='always')
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
        return False, _ZERO6
    r = 1.0 / det
    return True, (c00 * r, c01 * r, c02 * r, (s00 * s22 - s02 * s02) * r,
                  (s01 * s02 - s00 * s12) * r, (s00 * s11 - s01 * s01) * r)


@nb.njit(cache=True, inline='always')
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


@nb.njit(cache=True, inline='always')
def store_factors(Pinv, Lo, i, pinv, lo):
    """Row i's factors into ``Pinv[i]`` (from its upper triangle) and ``Lo[i]``."""
    Pinv[i, 0, 0], Pinv[i, 0, 1], Pinv[i, 0, 2] = pinv[0], pinv[1], pinv[2]
    Pinv[i, 1, 0], Pinv[i, 1, 1], Pinv[i, 1, 2] = pinv[1], pinv[3], pinv[4]
    Pinv[i, 2, 0], Pinv[i, 2, 1], Pinv[i, 2, 2] = pinv[2], pinv[4], pinv[5]
    Lo[i, 0, 0], Lo[i, 0, 1], Lo[i, 0, 2] = lo[0], lo[1], lo[2]
    Lo[i, 1, 0], Lo[i, 1, 1], Lo[i, 1, 2] = lo[3], lo[4], lo[5]
    Lo[i, 2, 0], Lo[i, 2, 1], Lo[i, 2, 2] = lo[6], lo[7], lo[8]


@nb.njit(cache=True, _nrt=False)
def factor(D, L, is_first, Pinv, Lo):
    """Factorise A (blocks ``D``, ``L`` ``(n, 3, 3)``; D's upper triangle is read) into
    ``Pinv`` and ``Lo`` (in place).

    Returns True on success, False if A is not positive definite.
    """
    n = D.shape[0]
    pinv = _ZERO6
    for i in range(n):
        d = (D[i, 0, 0], D[i, 0, 1], D[i, 0, 2], D[i, 1, 1], D[i, 1, 2], D[i, 2, 2])
        if is_first[i]:
            lo = _ZERO9
            ok, pinv = invert_pivot(d)
        else:
            l = (L[i, 0, 0], L[i, 0, 1], L[i, 0, 2], L[i, 1, 0], L[i, 1, 1], L[i, 1, 2],
                 L[i, 2, 0], L[i, 2, 1], L[i, 2, 2])
            ok, lo, pinv = pivot(d, l, pinv)
        if not ok:
            return False
        store_factors(Pinv, Lo, i, pinv, lo)
    return True


@nb.njit(cache=True, _nrt=False)
def solve(Pinv, Lo, is_first, b):
    """Solve A x = b with the factors of ``factor``; ``b`` ``(n, 3)`` is overwritten by x."""
    solve_from(Pinv, Lo, is_first, b, 1)


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
