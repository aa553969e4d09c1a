"""Coulomb friction of the contact stage (numba, nopython, ``cache=True``): one Jacobi step
with an exact line search that cannot add kinetic energy (not an exact Coulomb cone:
sticking is reached over a few steps).
"""
import numpy as np
from numba import njit

from .small_solves import DS_SQ, REG, dense_scratch, lu_solve_into, square


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def friction_step_into(W, slip, bound, lam, ds):
    """``friction_step`` into ``lam`` (k,), with the scratch ``ds`` (``dense_scratch`` of
    ≥ k rows)."""
    k = slip.shape[0]
    tr = 0.0
    for i in range(k):
        tr += W[i, i]
    A = square(ds[DS_SQ][1], k)
    for a in range(W.shape[0]):
        for b in range(W.shape[1]):
            A[a, b] = W[a, b]
    for i in range(k):
        A[i, i] += REG * tr / k
    lu_solve_into(A, slip, square(ds[DS_SQ][2], k), lam)
    work = 0.0
    for i in range(k):
        lam[i] = min(max(lam[i], 0.0), bound[i])
        work += lam[i] * slip[i]
    quad = 0.0
    for i in range(k):
        s = 0.0
        for j in range(k):
            s += lam[j] * W[j, i]
        quad += s * lam[i]
    if work <= 0.0 or quad <= 0.0:
        lam[:] = 0.0
        return
    alpha = min(1.0, work / quad)
    for i in range(k):
        lam[i] *= alpha


@njit(cache=True)
def friction_step(W, slip, bound):
    """Friction impulses 0 ≤ λ ≤ bound against sliding speeds ``slip``: the impulse that would
    stop all of them, clipped to the Coulomb bound, then scaled by α ∈ [0, 1] with
    α ≤ λ·slip / λᵀWλ, so that ΔKE = -αλ·slip + ½α²λᵀWλ ≤ 0."""
    lam = np.empty(slip.shape[0])
    friction_step_into(W, slip, bound, lam, dense_scratch(slip.shape[0]))
    return lam
