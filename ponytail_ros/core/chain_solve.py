"""The joint system A = J M⁻¹ Jᵀ of all chains: block-tridiagonal Cholesky, compiled.

A has one 3×3 block row per joint (joint i holds segment i's proximal point on its parent):
diagonal blocks ``D[i]`` and coupling blocks ``L[i] = A[i, i-1]`` (zero where ``is_first[i]``:
chains do not couple, so a crowd of chains is one factorisation). Like MuJoCo's
``mj_factorM`` / ``mj_solveM`` pair, the factorisation is done once per configuration and
solved for as many right-hand sides as the step needs:

    A = 𝓛 𝓛ᵀ,   𝓛 lower block-bidiagonal: diagonal blocks C[i] (lower-triangular Cholesky
                factors), sub-diagonal blocks Lo[i] = L[i] C[i-1]⁻ᵀ,
                C[i] C[i]ᵀ = D[i] - Lo[i] Lo[i]ᵀ.

O(n) in time and memory, no LAPACK call; ``factor`` returns False (nothing is raised inside
compiled code) when a pivot is not positive: A is then not positive definite, which a valid
chain never produces (a blow-up does).
"""
import numba as nb
import numpy as np

__all__ = ['factor', 'solve', 'solve_many']


@nb.njit(cache=True, inline='always')
def _chol3(A, C):
    """Lower Cholesky factor ``C`` of the symmetric 3×3 ``A``; False if not positive definite."""
    a00 = A[0, 0]
    if not a00 > 0.0:
        return False
    c00 = np.sqrt(a00)
    c10 = A[1, 0] / c00
    c20 = A[2, 0] / c00
    a11 = A[1, 1] - c10 * c10
    if not a11 > 0.0:
        return False
    c11 = np.sqrt(a11)
    c21 = (A[2, 1] - c20 * c10) / c11
    a22 = A[2, 2] - c20 * c20 - c21 * c21
    if not a22 > 0.0:
        return False
    C[0, 0] = c00
    C[0, 1] = 0.0
    C[0, 2] = 0.0
    C[1, 0] = c10
    C[1, 1] = c11
    C[1, 2] = 0.0
    C[2, 0] = c20
    C[2, 1] = c21
    C[2, 2] = np.sqrt(a22)
    return True


@nb.njit(cache=True)
def factor(D, L, is_first, C, Lo):
    """Factorise A (blocks ``D``, ``L`` ``(n, 3, 3)``) into ``C``, ``Lo`` (written in place).

    Returns True on success, False if A is not positive definite.
    """
    n = D.shape[0]
    S = np.empty((3, 3))
    for i in range(n):
        for a in range(3):
            for b in range(3):
                S[a, b] = D[i, a, b]
        if is_first[i]:
            for a in range(3):
                for b in range(3):
                    Lo[i, a, b] = 0.0
        else:
            # Lo[i] = L[i] C[i-1]⁻ᵀ: solve Lo[i] C[i-1]ᵀ = L[i] row by row (forward).
            for a in range(3):
                for b in range(3):
                    s = L[i, a, b]
                    for k in range(b):
                        s -= Lo[i, a, k] * C[i - 1, b, k]
                    Lo[i, a, b] = s / C[i - 1, b, b]
            for a in range(3):
                for b in range(3):
                    s = 0.0
                    for k in range(3):
                        s += Lo[i, a, k] * Lo[i, b, k]
                    S[a, b] -= s
        if not _chol3(S, C[i]):
            return False
    return True


@nb.njit(cache=True)
def solve(C, Lo, is_first, b):
    """Solve A x = b with the factors of ``factor``; ``b`` ``(n, 3)`` is overwritten by x."""
    n = b.shape[0]
    # Forward: 𝓛 y = b.
    for i in range(n):
        r0, r1, r2 = b[i, 0], b[i, 1], b[i, 2]
        if not is_first[i]:
            for k in range(3):
                r0 -= Lo[i, 0, k] * b[i - 1, k]
                r1 -= Lo[i, 1, k] * b[i - 1, k]
                r2 -= Lo[i, 2, k] * b[i - 1, k]
        y0 = r0 / C[i, 0, 0]
        y1 = (r1 - C[i, 1, 0] * y0) / C[i, 1, 1]
        y2 = (r2 - C[i, 2, 0] * y0 - C[i, 2, 1] * y1) / C[i, 2, 2]
        b[i, 0], b[i, 1], b[i, 2] = y0, y1, y2
    # Backward: 𝓛ᵀ x = y.
    for i in range(n - 1, -1, -1):
        r0, r1, r2 = b[i, 0], b[i, 1], b[i, 2]
        if i + 1 < n and not is_first[i + 1]:
            for k in range(3):
                xk = b[i + 1, k]
                r0 -= Lo[i + 1, k, 0] * xk
                r1 -= Lo[i + 1, k, 1] * xk
                r2 -= Lo[i + 1, k, 2] * xk
        x2 = r2 / C[i, 2, 2]
        x1 = (r1 - C[i, 2, 1] * x2) / C[i, 1, 1]
        x0 = (r0 - C[i, 1, 0] * x1 - C[i, 2, 0] * x2) / C[i, 0, 0]
        b[i, 0], b[i, 1], b[i, 2] = x0, x1, x2


@nb.njit(cache=True)
def solve_many(C, Lo, is_first, B):
    """Solve A X = B for ``B`` ``(k, n, 3)`` (k right-hand sides), in place."""
    for r in range(B.shape[0]):
        solve(C, Lo, is_first, B[r])
