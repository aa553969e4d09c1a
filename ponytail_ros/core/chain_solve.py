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

__all__ = ['factor', 'solve', 'solve_many']


@nb.njit(cache=True, inline='always')
def _invert_spd3(s00, s01, s02, s11, s12, s22, out):
    """``out`` = S⁻¹ for the symmetric 3×3 S of these entries; False unless S is positive
    definite."""
    c00 = s11 * s22 - s12 * s12
    c01 = s02 * s12 - s01 * s22
    c02 = s01 * s12 - s02 * s11
    det = s00 * c00 + s01 * c01 + s02 * c02
    if not (s00 > 0.0 and s00 * s11 - s01 * s01 > 0.0 and det > 0.0):
        return False
    r = 1.0 / det
    out[0, 0] = c00 * r
    out[0, 1] = out[1, 0] = c01 * r
    out[0, 2] = out[2, 0] = c02 * r
    out[1, 1] = (s00 * s22 - s02 * s02) * r
    out[1, 2] = out[2, 1] = (s01 * s02 - s00 * s12) * r
    out[2, 2] = (s00 * s11 - s01 * s01) * r
    return True


@nb.njit(cache=True, inline='always')
def _minus_lo_lt(Lo, L, i, a, b):
    return -(Lo[i, a, 0] * L[i, b, 0] + Lo[i, a, 1] * L[i, b, 1] + Lo[i, a, 2] * L[i, b, 2])


@nb.njit(cache=True)
def factor(D, L, is_first, Pinv, Lo):
    """Factorise A (blocks ``D``, ``L`` ``(n, 3, 3)``) into ``Pinv`` and ``Lo`` (in place).

    Returns True on success, False if A is not positive definite.
    """
    n = D.shape[0]
    for i in range(n):
        s00, s01, s02 = D[i, 0, 0], D[i, 0, 1], D[i, 0, 2]
        s11, s12, s22 = D[i, 1, 1], D[i, 1, 2], D[i, 2, 2]
        if is_first[i]:
            for a in range(3):
                for b in range(3):
                    Lo[i, a, b] = 0.0
        else:
            for a in range(3):
                for b in range(3):
                    Lo[i, a, b] = (L[i, a, 0] * Pinv[i - 1, 0, b] + L[i, a, 1] * Pinv[i - 1, 1, b]
                                   + L[i, a, 2] * Pinv[i - 1, 2, b])
            # P_i = D_i - 𝓛_i L_iᵀ (symmetric: the upper triangle)
            s00 += _minus_lo_lt(Lo, L, i, 0, 0)
            s01 += _minus_lo_lt(Lo, L, i, 0, 1)
            s02 += _minus_lo_lt(Lo, L, i, 0, 2)
            s11 += _minus_lo_lt(Lo, L, i, 1, 1)
            s12 += _minus_lo_lt(Lo, L, i, 1, 2)
            s22 += _minus_lo_lt(Lo, L, i, 2, 2)
        if not _invert_spd3(s00, s01, s02, s11, s12, s22, Pinv[i]):
            return False
    return True


@nb.njit(cache=True)
def solve(Pinv, Lo, is_first, b):
    """Solve A x = b with the factors of ``factor``; ``b`` ``(n, 3)`` is overwritten by x."""
    n = b.shape[0]
    # Forward: (1 + 𝓛) z = b.
    for i in range(1, n):
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


@nb.njit(cache=True)
def solve_many(Pinv, Lo, is_first, B):
    """Solve A X = B for ``B`` ``(k, n, 3)`` (k right-hand sides), in place."""
    for r in range(B.shape[0]):
        solve(Pinv, Lo, is_first, B[r])
