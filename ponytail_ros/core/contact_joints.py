"""The jointed chain in the contact stage: the factorised joint system J M⁻¹ Jᵀ
(block-tridiagonal, O(n), ``chain_solve``) at the current orientations, and the projections
that close every joint (positions rebuilt from the anchor, velocities M-orthogonally
projected). numba, nopython, ``cache=True``; world frame, SI units.
"""
import numpy as np
from numba import njit

from .chain_solve import factor as _chain_factor
from .chain_solve import invert_pivot as _invert_pivot
from .chain_solve import pivot as _pivot
from .chain_solve import solve as _chain_solve
from .chain_solve import store_factors as _store_factors
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
    M_G,
    M_INV_I,
    M_LO,
    M_PIVOTS,
    SEG,
    V_H,
    WS_R3,
    WS_TOUCHED,
    mat,
    vec,
    zero_pair,
)
from .limit_kernels import add, cross, dot, q4, qaxis_x, qmatrix, scale, sub, v3


@njit(cache=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def mat_vec(M, i, u):
    """M[i] u for a stack of 3×3 matrices ``M``."""
    return (M[i, 0, 0] * u[0] + M[i, 0, 1] * u[1] + M[i, 0, 2] * u[2],
            M[i, 1, 0] * u[0] + M[i, 1, 1] * u[1] + M[i, 1, 2] * u[2],
            M[i, 2, 0] * u[0] + M[i, 2, 1] * u[1] + M[i, 2, 2] * u[2])


# -- the chain's configuration: half-vectors, inverse inertias, the factorised J M⁻¹ Jᵀ ------
@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def axisymmetric_terms(hi, half, inv_inertia, i, inv_I, G):
    """Segment i with principal moments (I_a, I_p, I_p): I⁻¹ = 1/I_p + (1/I_a - 1/I_p) e eᵀ
    and G = (h hᵀ - |h|² 1) / I_p, e = h / (l/2) its axis (world)."""
    e = (hi[0] / half, hi[1] / half, hi[2] / half)
    k = inv_inertia[i, 0] - inv_inertia[i, 1]
    hh = dot(hi, hi)
    for a in range(3):
        for b in range(3):
            inv_I[i, a, b] = k * e[a] * e[b]
            G[i, a, b] = hi[a] * hi[b]
        inv_I[i, a, a] += inv_inertia[i, 1]
        G[i, a, a] -= hh
    for a in range(3):
        for b in range(3):
            G[i, a, b] *= inv_inertia[i, 1]


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def general_terms(qi, hi, inv_inertia, i, inv_I, G, R, SI):
    """Segment i with any principal moments: I⁻¹ = R diag(1/I) Rᵀ (R of ``qi``) and
    G = ([h]× I⁻¹) [h]×, built with [h]× u = h × u column by column (``R``, ``SI``: 3×3
    scratch)."""
    qmatrix(qi, R)
    for a in range(3):
        for b in range(3):
            s = 0.0
            for c in range(3):
                s += R[a, c] * inv_inertia[i, c] * R[b, c]
            inv_I[i, a, b] = s
    for b in range(3):
        col = cross(hi, (inv_I[i, 0, b], inv_I[i, 1, b], inv_I[i, 2, b]))
        for a in range(3):
            SI[a, b] = col[a]
    for a in range(3):
        # (M [h]×)[a, b] = Σ_c M[a, c] [h]×[c, b].
        G[i, a, 0] = SI[a, 1] * hi[2] - SI[a, 2] * hi[1]
        G[i, a, 1] = SI[a, 2] * hi[0] - SI[a, 0] * hi[2]
        G[i, a, 2] = SI[a, 0] * hi[1] - SI[a, 1] * hi[0]


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def joint_blocks(G, inv_mass, is_first, D, L):
    """Blocks of A = J M⁻¹ Jᵀ: ``A_ii = (1/m_i + 1/m_{i-1}) 1 - G_i - G_{i-1}`` (the second
    terms only below a parent segment), ``A_i,i-1 = -(1/m_{i-1} 1 + G_{i-1})``."""
    for i in range(G.shape[0]):
        for a in range(3):
            for b in range(3):
                eye = 1.0 if a == b else 0.0
                D[i, a, b] = eye * inv_mass[i] - G[i, a, b]
                L[i, a, b] = 0.0
                if not is_first[i]:
                    D[i, a, b] += eye * inv_mass[i - 1] - G[i - 1, a, b]
                    L[i, a, b] = -(eye * inv_mass[i - 1] + G[i - 1, a, b])


@njit(cache=True)
def factor_chain(q, model, h, inv_I, C, Lo):
    """At orientations ``q``: half-vectors ``h`` (centre to distal joint, m), world inverse
    inertias ``inv_I`` ``(n, 3, 3)`` and the factors (``C``, ``Lo``, ``chain_solve``) of
    A = J M⁻¹ Jᵀ (``joint_blocks``), G = [h]× I⁻¹ [h]× (``solver``). False if A is not
    positive definite."""
    n = q.shape[0]
    return factor_chain_into(q, model, h, inv_I, C, Lo, np.empty((n, 3, 3)),
                             np.empty((n, 3, 3)), np.empty((n, 3, 3)), np.empty((2, 3, 3)))


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def factor_chain_into(q, model, h, inv_I, C, Lo, G, D, L, R3):
    """``factor_chain`` with its scratch given: the blocks ``G``, ``D``, ``L`` ``(n, 3, 3)``
    and two 3×3 matrices ``R3`` ``(2, 3, 3)``."""
    length, inv_inertia = model[LENGTH], model[INV_INERTIA]
    n = q.shape[0]
    for i in range(n):
        half = 0.5 * length[i]
        hi = scale(half, qaxis_x(q4(q, i)))
        for a in range(3):
            h[i, a] = hi[a]
        if model[AXISYMMETRIC]:
            axisymmetric_terms(hi, half, inv_inertia, i, inv_I, G)
        else:
            general_terms(q4(q, i), hi, inv_inertia, i, inv_I, G, R3[0], R3[1])
    joint_blocks(G, model[INV_MASS], model[IS_FIRST], D, L)
    return _chain_factor(D, L, model[IS_FIRST], C, Lo)


@njit(cache=True, inline='always')
def axisymmetric_G(hi, half, inv_inertia, i, inv_I):
    """``axisymmetric_terms`` with G returned (row-major 9-tuple, the same operations)
    instead of stored: I⁻¹ into ``inv_I[i]``."""
    e = (hi[0] / half, hi[1] / half, hi[2] / half)
    k = inv_inertia[i, 0] - inv_inertia[i, 1]
    ip = inv_inertia[i, 1]
    hh = dot(hi, hi)
    for a in range(3):
        for b in range(3):
            inv_I[i, a, b] = k * e[a] * e[b]
        inv_I[i, a, a] += ip
    return ((hi[0] * hi[0] - hh) * ip, (hi[0] * hi[1]) * ip, (hi[0] * hi[2]) * ip,
            (hi[1] * hi[0]) * ip, (hi[1] * hi[1] - hh) * ip, (hi[1] * hi[2]) * ip,
            (hi[2] * hi[0]) * ip, (hi[2] * hi[1]) * ip, (hi[2] * hi[2] - hh) * ip)


@njit(cache=True, inline='always')
def joint_row(gi, gp, im, ip, first):
    """Block row i of A (``joint_blocks``, the same operations) as scalars, from G_i ``gi``,
    G_{i-1} ``gp`` (row-major 9-tuples) and 1/m_i, 1/m_{i-1}: D_i's upper triangle
    ``(00, 01, 02, 11, 12, 22)`` and L_i row-major (zeros where ``first``)."""
    d00 = 1.0 * im - gi[0]
    d01 = 0.0 * im - gi[1]
    d02 = 0.0 * im - gi[2]
    d11 = 1.0 * im - gi[4]
    d12 = 0.0 * im - gi[5]
    d22 = 1.0 * im - gi[8]
    if first:
        return (d00, d01, d02, d11, d12, d22), (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    d00 += 1.0 * ip - gp[0]
    d01 += 0.0 * ip - gp[1]
    d02 += 0.0 * ip - gp[2]
    d11 += 1.0 * ip - gp[4]
    d12 += 0.0 * ip - gp[5]
    d22 += 1.0 * ip - gp[8]
    return ((d00, d01, d02, d11, d12, d22),
            (-(1.0 * ip + gp[0]), -(0.0 * ip + gp[1]), -(0.0 * ip + gp[2]),
             -(0.0 * ip + gp[3]), -(1.0 * ip + gp[4]), -(0.0 * ip + gp[5]),
             -(0.0 * ip + gp[6]), -(0.0 * ip + gp[7]), -(1.0 * ip + gp[8])))


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def factor_segments(q, model, s, e, h, inv_I, C, Lo, G, R3):
    """``factor_chain_into`` for the whole chains of segments ``s:e`` only, with G and A's
    blocks formed row by row in registers (``axisymmetric_G``, ``joint_row``) instead of the
    tables ``G``, ``D``, ``L``: the same operations in the same order, so the same factors,
    bit for bit (chains do not couple: a chain's factors do not depend on the others'). ``G``
    ``(n, 3, 3)`` (a general inertia's G), ``R3`` ``(2, 3, 3)``: scratch."""
    length, inv_inertia = model[LENGTH], model[INV_INERTIA]
    inv_mass, is_first = model[INV_MASS], model[IS_FIRST]
    axisymmetric = model[AXISYMMETRIC]
    pinv = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    gp = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for i in range(s, e):
        half = 0.5 * length[i]
        hi = scale(half, qaxis_x(q4(q, i)))
        for a in range(3):
            h[i, a] = hi[a]
        if axisymmetric:
            gi = axisymmetric_G(hi, half, inv_inertia, i, inv_I)
        else:
            general_terms(q4(q, i), hi, inv_inertia, i, inv_I, G, R3[0], R3[1])
            gi = (G[i, 0, 0], G[i, 0, 1], G[i, 0, 2], G[i, 1, 0], G[i, 1, 1], G[i, 1, 2],
                  G[i, 2, 0], G[i, 2, 1], G[i, 2, 2])
        first = is_first[i]
        d, l = joint_row(gi, gp, inv_mass[i], inv_mass[i - 1] if not first else 0.0, first)
        if first:
            ok, pinv = _invert_pivot(d)
        else:
            ok, l, pinv = _pivot(d, l, pinv)
        if not ok:
            return False
        _store_factors(C, Lo, i, pinv, l)
        gp = gi
    return True


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


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
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
    _chain_solve(C, Lo, is_first, c_dot)
    zero_pair(dv, dw)
    apply_joint_impulses(c_dot, h, inv_I, model[INV_MASS], model[HAS_CHILD], 0, n, dv, dw)
    for i in range(n):
        for a in range(3):
            v[i, a] += dv[i, a]
            w[i, a] += dw[i, a]


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
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


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
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
def factor_ws(q, model, ws):
    """``factor_chain`` into the workspace's factorisation (``V_H``, ``M_INV_I`` … ``M_LO``),
    every chain (``factor_segments`` over all segments)."""
    n = q.shape[0]
    return factor_segments(q, model, np.int64(0), n, vec(ws, V_H, n), mat(ws, M_INV_I, n),
                           mat(ws, M_PIVOTS, n), mat(ws, M_LO, n), mat(ws, M_G, n), ws[WS_R3])


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def factor_touched(q, model, I, h, inv_I, C, Lo, G, R3, touched):
    """The factorisation of the chains that rows ``I`` act on only, and every segment's
    half-vector: what a stage that solves only those rows reads (its rows couple only within
    their chains; the half-vectors are read by the velocity rebuild). A chain's factors are
    those ``factor_ws`` gives it. False if a factorised chain's A is not positive definite.
    ``touched`` ``(2, C)`` integers: scratch."""
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
    for t in range(nt):
        c = chains[t]
        if not factor_segments(q, model, chain_start[c], chain_end[c], h, inv_I, C, Lo, G, R3):
            return False
    return True


@njit(cache=True, inline='always')
def factor_rows_ws(q, model, I, ws):
    """``factor_touched`` into the workspace's factorisation."""
    n = q.shape[0]
    return factor_touched(q, model, I, vec(ws, V_H, n), mat(ws, M_INV_I, n),
                          mat(ws, M_PIVOTS, n), mat(ws, M_LO, n), mat(ws, M_G, n), ws[WS_R3],
                          ws[WS_TOUCHED])
