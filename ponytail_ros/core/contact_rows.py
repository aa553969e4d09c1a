"""The contact stage's rows: contact and limit rows built from the narrow phase, kept up to
date as the chain moves, and each row's response through the jointed chain with the
Delassus matrix W = J_r P M⁻¹ J_rᵀ of a chain's rows (numba, nopython, ``cache=True``).

Row layout: ``contact_model``. World frame, SI units.
"""
import numpy as np
from numba import njit

from .broad_phase import broad_phase_setup, near, near_pairs
from .chain_solve import solve_from
from .contact_joints import half_vectors, mat_vec
from .contact_model import (
    ANG,
    ANGLE_SKIN,
    APAR,
    ARM,
    CHAIN_END,
    CHAIN_OF,
    CHAIN_START,
    CONTACT,
    D_CHAINS,
    D_FRICTION,
    D_LENGTH,
    D_N_ROUND,
    D_RADIUS,
    D_SEG,
    DEPTH,
    DT_DEPTH,
    DT_S,
    DT_T,
    INV_I_MAX,
    INV_MASS,
    IS_FIRST,
    L_GAP,
    L_SEP,
    LENGTH,
    LIMITED,
    LIN,
    MOBILITY,
    MU,
    NCOL,
    P_A0,
    P_D2,
    P_NORMAL,
    P_OMEGA,
    P_ORIGIN,
    P_SPEED,
    P_VELOCITY,
    PAR,
    PARENT,
    S_COUNT,
    S_END,
    S_FIRST,
    SEG,
    SEP,
    SP_SLOT,
    SPECULATIVE_STEPS,
    SW_FASTEST,
    SW_ON,
    SWING_LIMIT,
    T_ROWS,
    TWIST_LIMIT,
    V_N1,
    VOTH,
    WS_AXIS,
    WS_CHAIN_SLOT,
    WS_DET,
    WS_IDS,
    WS_LIM,
    WS_OWN,
    WS_PAIRS,
    WS_SLOTS,
    WS_SWEEP,
    WS_TABLES,
    chain_anchor,
    chain_det,
    chain_is_free,
    chain_model,
    grown,
    resolve_workspace,
    rows_of,
    vec,
)
from .limit_kernels import limit_terms
from .narrow_phase import contact_frame
from .vec import add, cross, dot, norm, sub, v3


@njit(cache=True, inline='always')
def col3(R, r, c):
    """Row r's 3-vector at columns c:c+3 (e.g. ``col3(R, r, LIN)``; inlined: a call would
    compile once per literal column and row)."""
    return (R[r, c], R[r, c + 1], R[r, c + 2])


@njit(cache=True, inline='always')
def contact_rows(x, q, v, w, anchor_position, pose, model, det, dt, R, I, ws):
    """The contact rows into ``R``, ``I`` (segment-major, from row 0, with room left for the
    limit rows): returns their number, -1 if the tables could be too small.
    ``ws``: the workspace (its half-vectors and detection tables are overwritten); only the
    pairs ``near_pairs`` keeps are detected."""
    seg, seg_length, friction = det[D_SEG], det[D_LENGTH], det[D_FRICTION]
    seg_radius, n_round = det[D_RADIUS], det[D_N_ROUND]
    a0, d2, normal = pose[P_A0], pose[P_D2], pose[P_NORMAL]
    origin, col_vel, col_om, col_speed = (pose[P_ORIGIN], pose[P_VELOCITY], pose[P_OMEGA],
                                          pose[P_SPEED])
    chain_of = model[CHAIN_OF]
    m = seg.shape[0]
    # The workspace's second (n, 3) vector: build_rows' callers keep nothing there.
    h = vec(ws, V_N1, q.shape[0])
    half_vectors(model[LENGTH], q, h)
    depth, s, t, own = ws[WS_DET][DT_DEPTH], ws[WS_DET][DT_S], ws[WS_DET][DT_T], ws[WS_OWN]
    skin = near_pairs(x, h, anchor_position, pose, v, w, model, det, dt, ws)
    pair_list, count, slot = ws[WS_PAIRS], ws[WS_SLOTS][S_COUNT], ws[WS_CHAIN_SLOT]
    first_seg, end_seg = ws[WS_SLOTS][S_FIRST], ws[WS_SLOTS][S_END]
    # Room for every kept pair's segments, and for the limit rows after them.
    most = 2 * model[LIMITED].shape[0]
    for c in range(det[D_CHAINS].shape[0]):
        most += (end_seg[c] - first_seg[c]) * count[c]
    if most > R.shape[0]:
        return -1                   # the caller grows the tables (``grown``) and starts over
    k = 0
    for i in range(m):
        g = seg[i]
        speed = norm(v3(v, g)) + norm(v3(w, g)) * 0.5 * seg_length[i]
        c = slot[chain_of[g]]
        for jj in range(count[c]):
            j = pair_list[c, jj]
            reach = skin + SPECULATIVE_STEPS * dt * (speed + col_speed[j])
            if not (own[i, j] and depth[i, j] > -reach):
                continue
            nrm, point = contact_frame(v3(x, g), v3(h, g), s[i, j], t[i, j], v3(a0, j),
                                       v3(d2, j), v3(normal, j), seg_radius[i], j < n_round)
            arm = sub(point, v3(x, g))
            v_col = add(v3(col_vel, j), cross(v3(col_om, j), sub(point, v3(origin, j))))
            rel = sub(add(v3(v, g), cross(v3(w, g), arm)), v_col)
            ang = cross(arm, nrm)
            R[k, :] = 0.0
            for a in range(3):
                R[k, LIN + a] = nrm[a]
                R[k, ANG + a] = ang[a]
                R[k, ARM + a] = arm[a]
                R[k, VOTH + a] = v_col[a]
            R[k, DEPTH] = depth[i, j]
            R[k, SEP] = dot(nrm, rel)
            R[k, MU] = friction[j]
            I[k, SEG] = g
            I[k, PAR] = -1
            I[k, CONTACT] = 1
            k += 1
    return k


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def limit_rows(q, w, anchor, q_rest, model, dt, R, I, k, axis, gap, sep):
    """The limit rows (swing rows, then twist rows) into ``R``, ``I`` from row ``k`` on;
    returns the new number of rows. A limit is kept if violated, within ``ANGLE_SKIN`` plus
    4× the deepest violation (so that a correction does not push a neighbouring joint past
    its limit unseen), or closing within ``SPECULATIVE_STEPS`` steps. ``axis`` ``(2 n_l, 3)``,
    ``gap``, ``sep`` ``(2 n_l)``: scratch (``limit_terms``)."""
    lim_idx, swing_limit, twist_limit = model[LIMITED], model[SWING_LIMIT], model[TWIST_LIMIT]
    nl = lim_idx.shape[0]
    limit_terms(q, w, anchor[2], anchor[3], q_rest, model[IS_FIRST], model[CHAIN_OF], lim_idx,
                swing_limit, twist_limit, axis, gap, sep)
    deepest_gap = 0.0
    for r in range(gap.shape[0]):
        deepest_gap = max(deepest_gap, -gap[r])
    skin = ANGLE_SKIN + 4.0 * deepest_gap
    for r in range(2 * nl):
        joint = lim_idx[r % nl]
        limit = swing_limit[joint] if r < nl else twist_limit[joint]
        closing = sep[r] < 0.0 and gap[r] < -SPECULATIVE_STEPS * dt * sep[r]
        if not (np.isfinite(limit) and (gap[r] < skin or closing)):
            continue
        R[k, :] = 0.0
        for a in range(3):
            R[k, ANG + a] = -axis[r, a]
            R[k, APAR + a] = axis[r, a]
        R[k, DEPTH] = -gap[r]
        R[k, SEP] = sep[r]
        I[k, SEG] = joint
        I[k, PAR] = model[PARENT][joint]
        I[k, CONTACT] = 0
        k += 1
    return k


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def build_rows_into(x, q, v, w, anchor, q_rest, pose, model, det, has_colliders, dt, ws):
    """``build_rows`` into the workspace's row table (``rows_of``): returns the number of
    rows, -1 (and no rows) when the table is too small (``grown`` gives a workspace whose
    tables hold every candidate row). Not inlined: its three call sites would each compile
    the broad phase and the detection again."""
    nl = model[LIMITED].shape[0]
    R, I = ws[WS_TABLES][T_ROWS], ws[WS_IDS][T_ROWS]
    k = 0
    # With the sweep on, ``near_pairs`` finds the pairs within reach faster than ``near``
    # tests every collider (a crowd's); without a pair in ``near``'s reach it makes no row.
    sw = ws[WS_SWEEP]
    if has_colliders and (sw[SW_ON] != 0.0 or near(anchor[0], pose, v, w, det, dt,
                                                    sw[SW_FASTEST])):
        k = contact_rows(x, q, v, w, anchor[0], pose, model, det, dt, R, I, ws)
        if k < 0:
            return -1
    if nl:
        k = limit_rows(q, w, anchor, q_rest, model, dt, R, I, k, ws[WS_AXIS][:2 * nl],
                       ws[WS_LIM][L_GAP][:2 * nl], ws[WS_LIM][L_SEP][:2 * nl])
    return k


@njit(cache=True)
def build_rows(x, q, v, w, anchor, q_rest, pose, model, det, split, has_colliders, dt):
    """Contact and limit rows within reach of this step's stages: ``(R, I)`` (new arrays),
    chain by chain (each chain's as ``resolve`` builds them), segments numbered in the whole
    model.

    A pair is a candidate if it is inside, within the position skin, or could close within
    ``SPECULATIVE_STEPS`` steps at a bound of the two surfaces' speeds (after the broad
    phase, ``near``). Per chain: contacts first (segment-major), then the limits
    (``limit_rows``).
    """
    ws = resolve_workspace(model, det, split, pose, has_colliders)
    if has_colliders:
        broad_phase_setup(pose, det, ws)
    R_all, I_all = np.empty((0, NCOL)), np.empty((0, 3), dtype=np.int64)
    k = 0
    for copy_pass in range(2):          # count the rows, then copy them
        if copy_pass == 1:
            R_all, I_all = np.empty((k, NCOL)), np.empty((k, 3), dtype=np.int64)
        k = 0
        for c in range(model[CHAIN_START].shape[0]):
            if chain_is_free(split, has_colliders, c):
                continue
            s, e = model[CHAIN_START][c], model[CHAIN_END][c]
            collides = has_colliders and split[SP_SLOT][c] >= 0
            sub, sub_det = chain_model(model, split, c), chain_det(det, split, c)
            kc = build_rows_into(x[s:e], q[s:e], v[s:e], w[s:e], chain_anchor(anchor, c),
                                 q_rest[s:e], pose, sub, sub_det, collides, dt, ws)
            if kc < 0:
                ws = grown(ws)
                kc = build_rows_into(x[s:e], q[s:e], v[s:e], w[s:e], chain_anchor(anchor, c),
                                     q_rest[s:e], pose, sub, sub_det, collides, dt, ws)
            R, I = rows_of(ws, kc)
            if copy_pass == 1:
                for r in range(R.shape[0]):
                    R_all[k + r, :] = R[r, :]
                    I_all[k + r, SEG] = I[r, SEG] + s
                    I_all[k + r, PAR] = I[r, PAR] + s if I[r, PAR] >= 0 else -1
                    I_all[k + r, CONTACT] = I[r, CONTACT]
            k += R.shape[0]
    return R_all, I_all


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def take(R, I, keep, R2, I2):
    """The rows where ``keep``, into ``R2``, ``I2`` (tables at least as long as ``R``, ``I``):
    returns their number."""
    k = 0
    for r in range(keep.shape[0]):
        if keep[r]:
            for c in range(NCOL):
                R2[k, c] = R[r, c]
            for c in range(3):
                I2[k, c] = I[r, c]
            k += 1
    return k


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def moved_rows(R, I, dx, dth):
    """The rows after a small displacement (centres ``dx``, rotations ``dth``), to first order,
    in place: depths change by -J_r·(dx, dth); lever arms turn with their segments (a contact's
    angular Jacobian is then arm × normal again)."""
    for r in range(R.shape[0]):
        g, p = I[r, SEG], I[r, PAR]
        rate = (dot(col3(R, r, LIN), v3(dx, g))
                + dot(col3(R, r, ANG), v3(dth, g)))
        if p >= 0:
            rate += dot(col3(R, r, APAR), v3(dth, p))
        arm = col3(R, r, ARM)
        arm = add(arm, cross(v3(dth, g), arm))
        R[r, DEPTH] -= rate
        for a in range(3):
            R[r, ARM + a] = arm[a]
        if I[r, CONTACT]:
            ang = cross(arm, col3(R, r, LIN))
            for a in range(3):
                R[r, ANG + a] = ang[a]


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def refresh_sep(R, I, v, w, anchor_omega, chain_of):
    """The rows' separation rates for new velocities (geometry unchanged), in place."""
    for r in range(R.shape[0]):
        g, p = I[r, SEG], I[r, PAR]
        w_par = v3(w, p) if p >= 0 else v3(anchor_omega, chain_of[g])
        R[r, SEP] = (dot(col3(R, r, LIN),
                         sub(v3(v, g), col3(R, r, VOTH)))
                     + dot(col3(R, r, ANG), v3(w, g))
                     + dot(col3(R, r, APAR), w_par))


# -- the rows' impulses and the chain's response ------------------------------------------------
@njit(cache=True, inline='always')
def joint_error(bv, bw, bv_prev, bw_prev, h, i, j, first_row):
    """Joint i's velocity error (``row_response``): parent's distal point minus child's
    proximal point, for centre and angular velocities ``bv``, ``bw`` of the child (segment
    ``j`` of ``h``) and ``bv_prev``, ``bw_prev`` of the parent (read unless ``first_row``)."""
    d = sub(cross(bw, v3(h, j)), bv)
    if not first_row:
        d = add(d, add(bv_prev, cross(bw_prev, v3(h, j - 1))))
    return d


@njit(cache=True, inline='always')
def free_joint_errors(vg, wg, wp, has_parent, gl, s, h, c_dot):
    """Ċ of a free response (``vg``, ``wg`` on local segment gl, ``wp`` on its parent if
    ``has_parent``) into ``c_dot``: zero but at joints gl - 1 (with a parent), gl, gl + 1."""
    zero = (0.0, 0.0, 0.0)
    for i in range(c_dot.shape[0]):
        for a in range(3):
            c_dot[i, a] = 0.0
    if has_parent:
        d = joint_error(zero, wp, zero, zero, h, gl - 1, s + gl - 1, gl - 1 == 0)
        for a in range(3):
            c_dot[gl - 1, a] = d[a]
    d = joint_error(vg, wg, zero, wp, h, gl, s + gl, gl == 0)
    for a in range(3):
        c_dot[gl, a] = d[a]
    if gl + 1 < c_dot.shape[0]:
        d = joint_error(zero, zero, vg, wg, h, gl + 1, s + gl + 1, False)
        for a in range(3):
            c_dot[gl + 1, a] = d[a]


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def row_response(R, I, r, h, inv_I, C, Lo, first, inv_mass, has_child, s, e, dv, dw, c_dot):
    """Velocity change ``(dv, dw)`` ``(e - s, 3)`` of one chain (segments ``s:e``) under a unit
    impulse along row r's Jacobian, joints closed: M⁻¹ (J_rᵀ + Jᵀ λ_joint), A λ_joint = Ċ.
    ``C``, ``Lo``, ``first``: the chain's factors and ``is_first`` (from s); ``c_dot``
    ``(e - s, 3)``: scratch. Plain arrays, not the model's tuple: called per row.

    The impulse moves segment g (and a limit's parent p = g - 1) only: Ċ is zero but at the
    joints of g and g + 1 (and p), the solve's forward pass starts at the first of them
    (``solve_from``), and the free response (M⁻¹ J_rᵀ) is added to the joints' term where
    it is not zero: the operations of zeroing ``dv``, ``dw`` and adding both terms, less
    those on zeros."""
    g, p = I[r, SEG], I[r, PAR]
    gl = g - s
    pl = p - s if p >= 0 else -2
    zero = (0.0, 0.0, 0.0)
    lin = col3(R, r, LIN)
    vg = (lin[0] * inv_mass[g], lin[1] * inv_mass[g], lin[2] * inv_mass[g])
    wg = mat_vec(inv_I, g, col3(R, r, ANG))
    wp = mat_vec(inv_I, p, col3(R, r, APAR)) if p >= 0 else zero
    free_joint_errors(vg, wg, wp, p >= 0, gl, s, h, c_dot)
    solve_from(C, Lo, first, c_dot, pl if p >= 0 else gl)
    # apply_joint_impulses onto the free response.
    for i in range(s, e):
        ln = v3(c_dot, i - s + 1) if has_child[i] else zero
        li = v3(c_dot, i - s)
        dwi = mat_vec(inv_I, i, cross(add(li, ln), v3(h, i)))
        if i - s == gl:
            bv, bw = vg, wg
        elif i - s == pl:
            bv, bw = zero, wp
        else:
            bv, bw = zero, zero
        for a in range(3):
            dv[i - s, a] = bv[a] + (li[a] - ln[a]) * inv_mass[i]
            dw[i - s, a] = bw[a] + dwi[a]


@njit(cache=True)
def group_rows(I, chain_of, chain_start, chain_end, members, start):
    """The rows grouped by chain, in the order of each chain's first row, in row order within
    a group (group g: ``members[start[g]:start[g + 1]]``): a counting sort, O(rows + chains)
    however many chains have rows. Returns the number of groups and the largest group's
    rows and segments."""
    k = I.shape[0]
    return group_rows_into(I, chain_of, chain_start, chain_end, members, start,
                           np.empty(2 * k, dtype=np.int64),
                           np.empty(chain_start.shape[0], dtype=np.int64))


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def group_rows_into(I, chain_of, chain_start, chain_end, members, start, scratch, group_of):
    """``group_rows`` with its scratch given: ``scratch`` ``(≥ 2k)``, ``group_of`` ``(C,)``
    (only the entries of the rows' chains are written, then read)."""
    k = I.shape[0]
    group, fill = scratch[:k], scratch[k:2 * k]
    for r in range(k):
        group_of[chain_of[I[r, SEG]]] = -1
    n_groups, nc_max = 0, 0
    for r in range(k):
        c = chain_of[I[r, SEG]]
        if group_of[c] < 0:
            group_of[c] = n_groups
            fill[n_groups] = 0
            n_groups += 1
            nc_max = max(nc_max, chain_end[c] - chain_start[c])
        group[r] = group_of[c]
        fill[group[r]] += 1
    o, kg_max = 0, 0
    for g in range(n_groups):
        start[g] = o
        o += fill[g]
        kg_max = max(kg_max, fill[g])
        fill[g] = start[g]
    start[n_groups] = o
    for r in range(k):
        members[fill[group[r]]] = r
        fill[group[r]] += 1
    return n_groups, kg_max, nc_max


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def delassus(R, I, members, s, rv, rw, model, W, mobile):
    """W[a, b] = J_a · (response to a unit impulse along row b), the Delassus matrix of one
    chain's rows (segments from s), and which rows the jointed chain can move: W_aa above
    ``MOBILITY`` times the row's mobility on its free segment(s)."""
    inv_mass, inv_I_max = model[INV_MASS], model[INV_I_MAX]
    kg = W.shape[0]
    for a in range(kg):
        r = members[a]
        g, p = I[r, SEG], I[r, PAR]
        lin, ang, ap = col3(R, r, LIN), col3(R, r, ANG), col3(R, r, APAR)
        for bb in range(kg):
            W[a, bb] = dot(lin, v3(rv[bb], g - s)) + dot(ang, v3(rw[bb], g - s))
            if p >= 0:
                W[a, bb] += dot(ap, v3(rw[bb], p - s))
        free = dot(lin, lin) * inv_mass[g] + dot(ang, ang) * inv_I_max[g]
        if p >= 0:
            free += dot(ap, ap) * inv_I_max[p]
        mobile[a] = W[a, a] > MOBILITY * free


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def deepest(R, I, with_limits):
    """The deepest violation (≥ 0) of the contact rows (and of the limit rows if asked)."""
    worst = 0.0
    for r in range(R.shape[0]):
        if I[r, CONTACT] or with_limits:
            worst = max(worst, R[r, DEPTH])
    return worst
