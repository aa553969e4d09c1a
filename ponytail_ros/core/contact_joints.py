"""The jointed chain in the contact stage: the factorised joint system J M⁻¹ Jᵀ
(block-tridiagonal, O(n), ``chain_solve``) at the current orientations, and the projections
that close every joint (positions rebuilt from the anchor, velocities M-orthogonally
projected). numba, nopython, ``cache=True``; world frame, SI units.
"""
import numpy as np
from numba import njit

from .chain_solve import JointModel, factor, solve as chain_solve
from .contact_model import (
    AXISYMMETRIC,
    CHAIN_END,
    CHAIN_OF,
    CHAIN_START,
    HAS_CHILD,
    INV_INERTIA,
    INV_MASS,
    IS_FIRST,
    LENGTH,
    M_INV_I,
    M_LO,
    M_PIVOTS,
    SEG,
    V_H,
    WS_TOUCHED,
    mat,
    vec,
    zero_pair,
)
from .vec import add, cross, q4, qaxis_x, scale, sub, v3


@njit(cache=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def mat_vec(M, i, u):
    """M[i] u for a stack of 3×3 matrices ``M``."""
    return (M[i, 0, 0] * u[0] + M[i, 0, 1] * u[1] + M[i, 0, 2] * u[2],
            M[i, 1, 0] * u[0] + M[i, 1, 1] * u[1] + M[i, 1, 2] * u[2],
            M[i, 2, 0] * u[0] + M[i, 2, 1] * u[1] + M[i, 2, 2] * u[2])


# -- the chain's configuration: half-vectors, inverse inertias, the factorised J M⁻¹ Jᵀ ------
@njit(cache=True, inline='always')
def joint_model(model):
    """The fields of the contact stage's model tuple that ``chain_solve.factor`` reads."""
    return JointModel(model[LENGTH], model[INV_MASS], model[INV_INERTIA], model[IS_FIRST],
                      model[AXISYMMETRIC])


@njit(cache=True)
def joint_factors(q, model, h, inv_I, C, Lo):
    """At orientations ``q``: half-vectors ``h`` (centre to distal joint, m), world inverse
    inertias ``inv_I`` ``(n, 3, 3)`` and the factors (``C``, ``Lo``) of A = J M⁻¹ Jᵀ, every
    chain (``chain_solve.factor``). False if A is not positive definite."""
    return factor(joint_model(model), q, np.int64(0), np.int64(q.shape[0]), h, inv_I, C, Lo)


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def apply_joint_impulses(lam, h, inv_I, inv_mass, has_child, s, e, dv, dw):
    """Add the velocity change of joint impulses ``lam`` (on the children, minus on the
    parents) over segments ``s:e`` (whole chains) to ``dv``, ``dw`` (``lam``, ``dv``, ``dw``
    indexed from s): Δv_i = (λ_i - λ_{i+1}) / m_i,  Δω_i = I_i⁻¹ ((λ_i + λ_{i+1}) × h_i).
    The model's arrays, not its tuple: called per row (``row_response``)."""
    for i in range(s, e):
        ln = v3(lam, i - s + 1) if has_child[i] else (0.0, 0.0, 0.0)
        li = v3(lam, i - s)
        dwi = mat_vec(inv_I, i, cross(add(li, ln), v3(h, i)))
        for a in range(3):
            dv[i - s, a] += (li[a] - ln[a]) * inv_mass[i]
            dw[i - s, a] += dwi[a]


@njit(cache=True, _nrt=False)             # (called from Python too: ``chain_ops``)
def joint_projection(v, w, anchor_velocity, h, inv_I, C, Lo, model, c_dot, dv, dw):
    """The velocities closest to ``(v, w)`` in the mass metric that close every joint (in
    place): joint impulses from A λ = Ċ (Ċ = parent's point velocity minus the child's).
    ``c_dot``, ``dv``, ``dw`` ``(n, 3)``: scratch."""
    is_first, chain_of = model[IS_FIRST], model[CHAIN_OF]
    n = v.shape[0]
    for i in range(n):
        child = sub(v3(v, i), cross(v3(w, i), v3(h, i)))
        if is_first[i]:
            par = v3(anchor_velocity, chain_of[i])
        else:
            par = add(v3(v, i - 1), cross(v3(w, i - 1), v3(h, i - 1)))
        d = sub(par, child)
        for a in range(3):
            c_dot[i, a] = d[a]
    chain_solve(C, Lo, is_first, c_dot)
    zero_pair(dv, dw)
    apply_joint_impulses(c_dot, h, inv_I, model[INV_MASS], model[HAS_CHILD], 0, n, dv, dw)
    for i in range(n):
        for a in range(3):
            v[i, a] += dv[i, a]
            w[i, a] += dw[i, a]


@njit(cache=True, _nrt=False)             # (called from Python too: ``chain_ops``)
def project_positions(anchor_position, h, model, x):
    """Centres that close every joint exactly: x_i = p_anchor + Σ_{j<i} 2 h_j + h_i."""
    chain_start, chain_end = model[CHAIN_START], model[CHAIN_END]
    for c in range(chain_start.shape[0]):
        p = v3(anchor_position, c)
        for i in range(chain_start[c], chain_end[c]):
            hi = v3(h, i)
            xi = add(p, hi)
            for a in range(3):
                x[i, a] = xi[a]
            p = add(p, scale(2.0, hi))


@njit(cache=True, _nrt=False)             # (called from Python too: ``chain_ops``)
def project_velocities(anchor_velocity, w, h, model, v):
    """Centre velocities of the rigid chain: v_i = v_anchor + Σ_{j<i} 2 ω_j × h_j + ω_i × h_i."""
    chain_start, chain_end = model[CHAIN_START], model[CHAIN_END]
    for c in range(chain_start.shape[0]):
        p = v3(anchor_velocity, c)
        for i in range(chain_start[c], chain_end[c]):
            wh = cross(v3(w, i), v3(h, i))
            vi = add(p, wh)
            for a in range(3):
                v[i, a] = vi[a]
            p = add(p, scale(2.0, wh))


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def half_vectors(length, q, h):
    for i in range(q.shape[0]):
        hi = scale(0.5 * length[i], qaxis_x(q4(q, i)))
        for a in range(3):
            h[i, a] = hi[a]


@njit(cache=True, inline='always')
def joint_factors_ws(q, model, ws):
    """``joint_factors`` into the workspace's factorisation (``V_H``, ``M_INV_I`` …
    ``M_LO``)."""
    n = q.shape[0]
    return factor(joint_model(model), q, np.int64(0), np.int64(n), vec(ws, V_H, n),
                  mat(ws, M_INV_I, n), mat(ws, M_PIVOTS, n), mat(ws, M_LO, n))


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def touched_joint_factors(q, model, I, h, inv_I, C, Lo, touched):
    """The factorisation of the chains that rows ``I`` act on only, and every segment's
    half-vector: what a stage that solves only those rows reads (its rows couple only within
    their chains; the half-vectors are read by the velocity rebuild). A chain's factors are
    those ``joint_factors_ws`` gives it. False if a factorised chain's A is not positive
    definite. ``touched`` ``(2, C)`` integers: scratch."""
    chain_of, chain_start, chain_end = model[CHAIN_OF], model[CHAIN_START], model[CHAIN_END]
    half_vectors(model[LENGTH], q, h)
    mark, chains = touched[0], touched[1]
    for r in range(I.shape[0]):
        mark[chain_of[I[r, SEG]]] = 0
    nt = 0
    for r in range(I.shape[0]):
        c = chain_of[I[r, SEG]]
        if mark[c] == 0:
            mark[c] = 1
            chains[nt] = c
            nt += 1
    J = joint_model(model)
    for t in range(nt):
        c = chains[t]
        if not factor(J, q, chain_start[c], chain_end[c], h, inv_I, C, Lo):
            return False
    return True


@njit(cache=True, inline='always')
def touched_joint_factors_ws(q, model, I, ws):
    """``touched_joint_factors`` into the workspace's factorisation."""
    n = q.shape[0]
    return touched_joint_factors(q, model, I, vec(ws, V_H, n), mat(ws, M_INV_I, n),
                                 mat(ws, M_PIVOTS, n), mat(ws, M_LO, n), ws[WS_TOUCHED])
