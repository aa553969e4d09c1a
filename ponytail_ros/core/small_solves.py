"""The small exact solves of the contact stage (numba, nopython, ``cache=True``; no NumPy
linear algebra, SciPy or LAPACK): a dense solve by Gaussian elimination with partial
pivoting, the linear complementarity problem by principal pivoting on the unit-diagonal
scaled matrix, and Lawson–Hanson's active-set NNLS as its fall-back.
"""
import numpy as np
from numba import njit

REG = 1e-9                   # relative regularisation of the (unit-diagonal) Delassus matrix
PIVOT_TOL = 1e-12            # sign tolerance of the principal pivoting (scaled units)


# -- small dense problems ------------------------------------------------------------------------
@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def lu_solve_into(A, b, M, x):  # noqa: C901 (elimination loops)
    """x with A x = b (dense, Gaussian elimination with partial pivoting); A, b are kept,
    ``M`` (like A) receives the factors."""
    n = b.shape[0]
    for r in range(n):
        x[r] = b[r]
        for c in range(n):
            M[r, c] = A[r, c]
    for c in range(n):
        p = c
        for r in range(c + 1, n):
            if abs(M[r, c]) > abs(M[p, c]):
                p = r
        if p != c:
            for j in range(n):
                M[c, j], M[p, j] = M[p, j], M[c, j]
            x[c], x[p] = x[p], x[c]
        for r in range(c + 1, n):
            f = M[r, c] / M[c, c]
            M[r, c] = f
            for j in range(c + 1, n):
                M[r, j] -= f * M[c, j]
            x[r] -= f * x[c]
    for c in range(n - 1, -1, -1):
        s = x[c]
        for j in range(c + 1, n):
            s -= M[c, j] * x[j]
        x[c] = s / M[c, c]


@njit(cache=True)
def lu_solve(A, b):
    """x with A x = b (``lu_solve_into``, new arrays)."""
    x = np.empty(b.shape[0])
    lu_solve_into(A, b, np.empty_like(A), x)
    return x


# Scratch of the dense problems of one chain's k rows (``dense_scratch``), by index: four
# k×k matrices, seven k-vectors, two k-indices and two k-masks (stacked: four arrays). Used by
# ``lcp_into`` (matrices 1-3, vectors 0-3, index 0, masks), ``friction_step_into`` (matrices
# 1-2) and ``chain_impulses`` (matrix 0, vectors 4-6, index 1).
DS_SQ, DS_VEC, DS_IDX, DS_MASK = range(4)


@njit(cache=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def dense_scratch(k):
    """Fresh scratch for dense problems of up to k rows (indices ``DS_*``)."""
    return (np.empty((4, k, k)), np.empty((7, k)), np.empty((2, k), dtype=np.int64),
            np.empty((2, k), dtype=np.bool_))


@njit(cache=True, inline='always')
def square(A, k):
    """The leading k×k block of the matrix ``A``."""
    return A[:k, :k]


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def solve_active_into(Ws, bs, active, lam, sq_a, sq_m, rhs, sol, idx):
    """λ_A = -W_AA⁻¹ b_A on the active set A, λ = 0 elsewhere (into ``lam``); ``sq_a``,
    ``sq_m`` (≥ k×k), ``rhs``, ``sol``, ``idx`` (≥ k): scratch."""
    k = bs.shape[0]
    na = 0
    for i in range(k):
        lam[i] = 0.0
        if active[i]:
            idx[na] = i
            na += 1
    if na == 0:
        return
    A = square(sq_a, na)
    for a in range(na):
        rhs[a] = -bs[idx[a]]
        for b in range(na):
            A[a, b] = Ws[idx[a], idx[b]]
    lu_solve_into(A, rhs[:na], square(sq_m, na), sol[:na])
    for a in range(na):
        lam[idx[a]] = sol[a]


@njit(cache=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def solve_active(Ws, bs, active, lam):
    """λ_A = -W_AA⁻¹ b_A on the active set A, λ = 0 elsewhere (into ``lam``)."""
    k = bs.shape[0]
    solve_active_into(Ws, bs, active, lam, np.empty((k, k)), np.empty((k, k)), np.empty(k),
                      np.empty(k), np.empty(k, dtype=np.int64))


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def row_dot(A, i, x):
    """Σ_j A[i, j] x[j] (no BLAS)."""
    s = 0.0
    for j in range(x.shape[0]):
        s += A[i, j] * x[j]
    return s


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def entering_variable(Ws, bs, lam, passive):
    """Lawson–Hanson: the bound variable with the largest dual -(Wλ + b)_i > 1e-12, or -1."""
    best, j = 1e-12, -1
    for i in range(bs.shape[0]):
        if not passive[i]:
            g = -bs[i] - row_dot(Ws, i, lam)
            if g > best:
                best, j = g, i
    return j


@njit(cache=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def step_to_feasible(Ws, bs, passive, lam, z):
    """Lawson–Hanson inner loop: solve on the passive set; while a passive variable would
    turn non-positive, move λ towards the solution as far as stays feasible and release the
    variables that reach zero."""
    k = bs.shape[0]
    for _ in range(3 * k + 3):
        solve_active(Ws, bs, passive, z)
        if not np.any(passive & (z <= 0.0)):
            for a in range(lam.shape[0]):
                lam[a] = z[a]
            return
        alpha = 1.0
        for i in range(k):
            if passive[i] and z[i] <= 0.0:
                alpha = min(alpha, lam[i] / (lam[i] - z[i]))
        for i in range(k):
            lam[i] += alpha * (z[i] - lam[i])
            if passive[i] and lam[i] <= 1e-15:
                passive[i] = False
                lam[i] = 0.0


@njit(cache=True)
def nnls_quadratic(Ws, bs):
    """min ½ λᵀ W λ + bᵀ λ over λ ≥ 0 (W symmetric positive definite): Lawson–Hanson active
    set, with the gradient -(Wλ + b) as the dual."""
    k = bs.shape[0]
    lam = np.zeros(k)
    z = np.zeros(k)
    passive = np.zeros(k, dtype=np.bool_)
    for _ in range(3 * k + 3):
        j = entering_variable(Ws, bs, lam, passive)
        if j < 0:
            break
        passive[j] = True
        step_to_feasible(Ws, bs, passive, lam, z)
    return lam


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def sign_violations(Ws, bs, active, lam, bad):
    """Principal pivoting: which rows violate their sign condition (an active row pulling,
    λ < 0, or an inactive one penetrating, (Wλ + b) < 0, beyond ``PIVOT_TOL``), into ``bad``;
    returns the lowest such row, or -1."""
    first = -1
    for i in range(bs.shape[0]):
        slack = row_dot(Ws, i, lam) + bs[i]
        bad[i] = lam[i] < -PIVOT_TOL if active[i] else slack < -PIVOT_TOL
        if bad[i] and first < 0:
            first = i
    return first


@njit(cache=True, _nrt=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def _lcp_fallback(Ws, bs, d, out):
    """``lcp``'s Lawson–Hanson fallback into ``out`` (it allocates: kept out of the
    borrowing ``lcp_into``)."""
    lam_fb = nnls_quadratic(Ws, bs)
    for i in range(out.shape[0]):
        out[i] = lam_fb[i] * d[i]


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def lcp_into(W, b, out, ds, Ws):  # noqa: C901 - the pivoting loop reads as the algorithm
    """``lcp`` into ``out`` (k,), with the scratch ``ds`` (``dense_scratch`` of ≥ k rows;
    ``W`` may be its square 0) and ``Ws`` (k×k) for the scaled matrix; borrowing its
    arguments (no reference counting: it runs for every touching chain and step)."""
    k = b.shape[0]
    any_closing = False
    for i in range(k):
        any_closing = any_closing or b[i] < 0.0
    if not any_closing:
        out[:] = 0.0
        return
    if k == 1:
        out[0] = max(-b[0] / W[0, 0], 0.0)
        return
    d, bs, lam = ds[DS_VEC][0][:k], ds[DS_VEC][1][:k], out
    active, bad = ds[DS_MASK][0][:k], ds[DS_MASK][1][:k]
    for i in range(k):
        d[i] = 1.0 / np.sqrt(W[i, i])
    for i in range(k):
        for j in range(k):
            Ws[i, j] = W[i, j] * d[i] * d[j]
        Ws[i, i] += REG
    for i in range(k):
        bs[i] = b[i] * d[i]
        active[i] = bs[i] < 0.0
        lam[i] = 0.0
        bad[i] = False
    # The active-set solve's scratch: two k² buffers, its right-hand side and solution.
    sq_a, sq_m, rhs, sol = ds[DS_SQ][1], ds[DS_SQ][2], ds[DS_VEC][2], ds[DS_VEC][3]
    for it in range(4 * k + 8):
        solve_active_into(Ws, bs, active, lam, sq_a, sq_m, rhs, sol, ds[DS_IDX][0])
        first = sign_violations(Ws, bs, active, lam, bad)
        if first < 0:
            for i in range(k):
                # max(λ, 0) as np.maximum has it (NaN kept), then unscaled.
                out[i] = (0.0 if lam[i] < 0.0 else lam[i]) * d[i]
            return
        if it < 4:
            for i in range(k):
                active[i] ^= bad[i]
        else:
            active[first] = not active[first]
    _lcp_fallback(Ws, bs, d, out)


@njit(cache=True)
def lcp(W, b):
    """λ ≥ 0 with Wλ + b ≥ 0 and λ·(Wλ + b) = 0, W symmetric positive semi-definite.

    Principal pivoting on the unit-diagonal scaled, ``REG``-regularised W: the rows with
    b < 0 start active; the active block is solved exactly and every row violating a sign
    condition moves to the other side (block pivoting; after 4 rounds one row at a time, the
    lowest index: Murty's rule, which terminates for positive definite W). Falls back to
    Lawson–Hanson (``nnls_quadratic``) if it ever stalls."""
    k = b.shape[0]
    out = np.empty(k)
    ds = dense_scratch(k)
    lcp_into(W, b, out, ds, square(ds[DS_SQ][3], k))
    return out
