"""Impulses of the contact stage (numba, nopython, ``cache=True``): the rows' exact LCP per
chain (rows couple only within a chain; ``contact_rows`` gives each row's response and W,
``small_solves`` the LCP), the velocity change they cause, then friction on the contacts
that push (``friction``). World frame, SI units.
"""
import numpy as np
from numba import njit

from .contact_model import (
    ANG,
    APAR,
    ARM,
    CHAIN_END,
    CHAIN_OF,
    CHAIN_START,
    CONTACT,
    HAS_CHILD,
    INV_I_MAX,
    INV_MASS,
    IS_FIRST,
    LIN,
    MOBILITY,
    MU,
    PAR,
    R_BOUND,
    R_LAM,
    R_SPEED,
    SC_CDOT,
    SC_DS,
    SC_INT,
    SC_LC,
    SC_MOBILE,
    SC_RESP,
    SC_W,
    SEG,
    T_FRIC,
    V_N2,
    V_N3,
    VOTH,
    WS_IDS,
    WS_ROWVEC,
    WS_SOLVE,
    WS_TABLES,
    solve_scratch,
    vec,
    zero_pair,
)
from .contact_rows import col3, delassus, group_rows_into, row_response
from .friction import friction_step_into
from .small_solves import DS_IDX, DS_SQ, DS_VEC, REG, dense_scratch, lcp_into, square
from .vec import add, cross, dot, norm, scale, sub, v3


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def chain_impulses(W, mobile, b, bound, members, lam, ds):
    """λ ``(kg,)`` of one chain's rows (index into ``members``): the mobile rows' LCP on the
    symmetrised W (or, when ``bound`` is not empty, the friction step), zero for the others.
    ``ds``: ``dense_scratch`` of ≥ kg rows."""
    kg = W.shape[0]
    sel = ds[DS_IDX][1]
    nm = 0
    for a in range(kg):
        if mobile[a]:
            sel[nm] = a
            nm += 1
    friction = bound.shape[0] > 0
    Wc = square(ds[DS_SQ][0], nm)
    bc, bnd, lc = ds[DS_VEC][4][:nm], ds[DS_VEC][5][:nm], ds[DS_VEC][6][:nm]
    for a in range(nm):
        bc[a] = b[members[sel[a]]]
        bnd[a] = bound[members[sel[a]]] if friction else 0.0
        for bb in range(nm):
            Wc[a, bb] = 0.5 * (W[sel[a], sel[bb]] + W[sel[bb], sel[a]])
    if friction:
        friction_step_into(Wc, bc, bnd, lc, ds)
    else:
        lcp_into(Wc, bc, lc, ds, square(ds[DS_SQ][3], nm))
    lam[:] = 0.0
    for a in range(nm):
        lam[sel[a]] = lc[a]


@njit(cache=True, _nrt=False)
def solve_rows_into(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam, sc):
    """``solve_rows`` with the impulses into ``lam`` ``(k,)``. Its scratch is ``sc``
    (``solve_scratch``) when large enough for this call's rows (borrowed, no reference
    counting), else sized by them (``solve_rows_alloc``: a few allocations, whatever the
    number of chains and rows)."""
    chain_of, chain_start, chain_end = model[CHAIN_OF], model[CHAIN_START], model[CHAIN_END]
    k = R.shape[0]
    if k == 0:
        return
    resp = sc[SC_RESP]
    c0 = chain_of[I[0, SEG]]
    if k == 1 and resp.shape[1] >= 1 and resp.shape[2] >= chain_end[c0] - chain_start[c0]:
        # One row (most calls of a ponytail on its skull): no grouping, no dense problems.
        lam[0] = _solve_one_row(R, I, b, bound, h, inv_I, C, Lo, model, sc, dv_out, dw_out)
        return
    n_chains = chain_start.shape[0]
    ib = sc[SC_INT]
    if ib.shape[0] < 4 * k + 1 + n_chains or sc[SC_MOBILE].shape[0] < k:
        solve_rows_alloc(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam)
        return
    # The rows grouped by chain (group g: members[start[g]:start[g + 1]]).
    members, start = ib[:k], ib[k:2 * k + 1]
    n_groups, kg_max, nc_max = group_rows_into(I, chain_of, chain_start, chain_end, members,
                                               start, ib[2 * k + 1:4 * k + 1],
                                               ib[4 * k + 1:4 * k + 1 + n_chains])
    # Per group: the responses rv, rw (kg, nc, 3), the joint scratch, W, the group's λ.
    if resp.shape[1] >= kg_max and resp.shape[2] >= nc_max:
        _solve_groups(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam, members,
                      start, n_groups, sc[SC_MOBILE], resp[0], resp[1], sc[SC_CDOT], sc[SC_W],
                      sc[SC_LC], sc[SC_DS])
    else:
        solve_rows_alloc(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam)


@njit(cache=True, inline='always')
def _solve_one_row(R, I, b, bound, h, inv_I, C, Lo, model, sc, dv_out, dw_out):
    """``solve_rows_into`` for one row (``sc``'s response scratch holding its chain): its
    impulse λ, returned, and the velocity change added to ``dv_out``, ``dw_out``. The
    operations of the general path in their order, so the same bits: the response
    (``row_response``), W and the mobility (``delassus``), the 1×1 symmetrised LCP
    (``lcp_into``) or friction step (``friction_step_into``, when ``bound`` is not empty).

    Why: a ponytail resting on its skull has one touching row in most steps (then one
    friction row), and for one row the general path's grouping, scratch views and dense
    problems cost more than the row's O(n) response."""
    chain_of, chain_start, chain_end = model[CHAIN_OF], model[CHAIN_START], model[CHAIN_END]
    inv_mass, is_first, has_child = model[INV_MASS], model[IS_FIRST], model[HAS_CHILD]
    inv_I_max = model[INV_I_MAX]
    g, p = I[0, SEG], I[0, PAR]
    c = chain_of[g]
    s, e = chain_start[c], chain_end[c]
    nc = e - s
    resp = sc[SC_RESP]
    rv, rw = resp[0][0, :nc], resp[1][0, :nc]
    row_response(R, I, np.int64(0), h, inv_I, C[s:e], Lo[s:e], is_first[s:e], inv_mass,
                 has_child, s, e, rv, rw, sc[SC_CDOT][:nc])
    # W and mobility as ``delassus`` forms them.
    lin, ang, ap = col3(R, 0, LIN), col3(R, 0, ANG), col3(R, 0, APAR)
    W = dot(lin, v3(rv, g - s)) + dot(ang, v3(rw, g - s))
    if p >= 0:
        W += dot(ap, v3(rw, p - s))
    free = dot(lin, lin) * inv_mass[g] + dot(ang, ang) * inv_I_max[g]
    if p >= 0:
        free += dot(ap, ap) * inv_I_max[p]
    la = 0.0
    b0 = b[0]
    if W > MOBILITY * free:
        Wc = 0.5 * (W + W)              # ``chain_impulses``' symmetrised W
        if bound.shape[0] > 0:
            # ``friction_step_into`` for k = 1: the regularised 1×1 solve, the clip, the
            # energy line search (its sums start at 0.0, as its loops').
            la = b0 / (Wc + REG * (0.0 + Wc) / 1)
            la = min(max(la, 0.0), bound[0])
            work = 0.0 + la * b0
            quad = 0.0 + (0.0 + la * Wc) * la
            if work <= 0.0 or quad <= 0.0:
                la = 0.0
            else:
                la *= min(1.0, work / quad)
        elif b0 < 0.0:
            la = max(-b0 / Wc, 0.0)     # ``lcp_into``'s k = 1 case
    if la != 0.0:                       # (``_solve_groups``' accumulation)
        for i in range(nc):
            for d in range(3):
                dv_out[s + i, d] += la * rv[i, d]
                dw_out[s + i, d] += la * rw[i, d]
    return la


@njit(cache=True, _nrt=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def solve_rows_alloc(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam):
    """``solve_rows_into`` with all its scratch allocated here, sized by the rows' groups
    (returns no array): for the calls whose rows outgrow the workspace's scratch."""
    chain_of, chain_start, chain_end = model[CHAIN_OF], model[CHAIN_START], model[CHAIN_END]
    k = R.shape[0]
    n_chains = chain_start.shape[0]
    ib = np.empty(4 * k + 1 + n_chains, dtype=np.int64)
    members, start = ib[:k], ib[k:2 * k + 1]
    n_groups, kg_max, nc_max = group_rows_into(I, chain_of, chain_start, chain_end, members,
                                               start, ib[2 * k + 1:4 * k + 1],
                                               ib[4 * k + 1:4 * k + 1 + n_chains])
    rv_all, rw_all = np.empty((kg_max, nc_max, 3)), np.empty((kg_max, nc_max, 3))
    c_dot_all, W_all, lc_all = np.empty((nc_max, 3)), np.empty((kg_max, kg_max)), np.empty(kg_max)
    _solve_groups(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam, members, start,
                  n_groups, np.empty(k, dtype=np.bool_), rv_all, rw_all, c_dot_all, W_all,
                  lc_all, dense_scratch(kg_max))


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def _solve_groups(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam, members, start,
                  n_groups, mobile, rv_all, rw_all, c_dot_all, W_all, lc_all, ds):
    """``solve_rows_into``'s loop over the chains' row groups, borrowing its scratch."""
    chain_of, chain_start, chain_end = model[CHAIN_OF], model[CHAIN_START], model[CHAIN_END]
    inv_mass, is_first, has_child = model[INV_MASS], model[IS_FIRST], model[HAS_CHILD]
    for gi in range(n_groups):
        mem = members[start[gi]:start[gi + 1]]
        kg = mem.shape[0]
        c = chain_of[I[mem[0], SEG]]
        s, e = chain_start[c], chain_end[c]
        nc = e - s
        rv, rw = rv_all[:kg, :nc], rw_all[:kg, :nc]
        c_dot, W, lc = c_dot_all[:nc], W_all[:kg, :kg], lc_all[:kg]
        Cg, Log, first = C[s:e], Lo[s:e], is_first[s:e]
        for a in range(kg):
            # (the response rows as ``_solve_one_row`` takes them, C-contiguous: one
            # specialisation of ``row_response``)
            row_response(R, I, mem[a], h, inv_I, Cg, Log, first, inv_mass, has_child, s, e,
                         rv_all[a, :nc], rw_all[a, :nc], c_dot)
        delassus(R, I, mem, s, rv, rw, model, W, mobile[:kg])
        chain_impulses(W, mobile[:kg], b, bound, mem, lc, ds)
        for a in range(kg):
            la = lc[a]
            lam[mem[a]] = la
            if la != 0.0:
                for i in range(nc):
                    for d in range(3):
                        dv_out[s + i, d] += la * rv[a, i, d]
                        dw_out[s + i, d] += la * rw[a, i, d]


@njit(cache=True)
def solve_rows(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out):
    """Impulses λ ``(k,)`` of the rows and the velocity change they cause, added to
    ``dv_out``, ``dw_out``: the exact LCP Wλ + b ≥ 0, λ ≥ 0, λ·(Wλ + b) = 0 (``bound``
    empty), or the energy-safe friction step bounded by ``bound`` ``(k,)`` (a run-time
    switch, not a compile-time one: one specialisation for both).

    Rows couple only within a chain: per chain, W = J_r P M⁻¹ J_rᵀ from one response per row;
    a row that the jointed chain moves less than ``MOBILITY`` times its free segment's
    mobility (a contact at the anchor) takes no impulse.
    """
    lam = np.zeros(R.shape[0])
    solve_rows_into(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam,
                    solve_scratch(0, 0, 0, 0))
    return lam


@njit(cache=True, inline='always')
def velocity_impulses(R, I, b, h, inv_I, C, Lo, model, v, w, ws):
    """Inelastic impulses on the rows (``b``: separation rates plus the speculative allowance),
    then Coulomb friction on the contacts that push; ``v``, ``w`` updated in place. ``ws``:
    the workspace (its vectors 2 and 3, impulses, friction rows, slip speeds and bounds)."""
    n = v.shape[0]
    k = R.shape[0]
    dv, dw = vec(ws, V_N2, n), vec(ws, V_N3, n)
    zero_pair(dv, dw)
    lam = ws[WS_ROWVEC][R_LAM][:k]
    solve_rows_into(R, I, b, ws[WS_ROWVEC][R_BOUND][:0], h, inv_I, C, Lo, model, dv, dw, lam,
                    ws[WS_SOLVE])
    for i in range(n):
        for a in range(3):
            v[i, a] += dv[i, a]
            w[i, a] += dw[i, a]
    # Friction rows: minus the sliding direction at each pushing contact that slides.
    Rf, If = ws[WS_TABLES][T_FRIC], ws[WS_IDS][T_FRIC]     # as long as the rows' table
    speed, bound = ws[WS_ROWVEC][R_SPEED], ws[WS_ROWVEC][R_BOUND]
    kf = 0
    for r in range(k):
        if not (I[r, CONTACT] and lam[r] > 0.0 and R[r, MU] > 0.0):
            continue
        g = I[r, SEG]
        arm = col3(R, r, ARM)
        nrm = col3(R, r, LIN)
        v_rel = sub(add(v3(v, g), cross(v3(w, g), arm)), col3(R, r, VOTH))
        slip = sub(v_rel, scale(dot(v_rel, nrm), nrm))
        sp = norm(slip)
        if not sp > 1e-9:
            continue
        t = (slip[0] / sp, slip[1] / sp, slip[2] / sp)
        ang = cross(arm, t)
        Rf[kf, :] = 0.0
        for a in range(3):
            Rf[kf, LIN + a] = -t[a]
            Rf[kf, ANG + a] = -ang[a]
        If[kf, SEG] = g
        If[kf, PAR] = -1
        If[kf, CONTACT] = 1
        speed[kf] = sp
        bound[kf] = R[r, MU] * lam[r]
        kf += 1
    if kf == 0:
        return
    zero_pair(dv, dw)
    # The normal impulses are spent: their buffer takes the friction impulses.
    solve_rows_into(Rf[:kf], If[:kf], speed[:kf], bound[:kf], h, inv_I, C, Lo, model, dv, dw,
                    lam[:kf], ws[WS_SOLVE])
    for i in range(n):
        for a in range(3):
            v[i, a] += dv[i, a]
            w[i, a] += dw[i, a]
