"""Compiled contacts and joint limits (numba, nopython, ``cache=True``, no fastmath).

One call of ``resolve`` does what ``collision.Unilateral.resolve`` documents (the method is
in the ``collision`` module docstring): broad phase, detection, the position passes, the
limits' exact projection, the joints' velocity projection, the inelastic impulses and
Coulomb friction. Nothing in it calls NumPy's linear algebra, SciPy or LAPACK: the joint
system J M⁻¹ Jᵀ is factorised by ``chain_solve`` (block-tridiagonal, O(n)) and each touching
chain's small complementarity problem is solved here (principal pivoting with an exact dense
solve, Lawson–Hanson active set as the fall-back). ``resolve`` runs its stages in order:
``position_stage``, ``limit_stage``, the joints' velocity projection, ``velocity_stage``.

Data. A row r (a contact normal or a limit) is one line of ``R`` ``(k, NCOL)`` (floats) and of
``I`` ``(k, 3)`` (integers), columns named below; its Jacobian acts on segment ``seg``
(linear ``lin``, angular ``ang``) and, for a limit, on the parent segment (``ang_par``;
``par = -1``: the anchor body, which never moves). ``depth`` (m or rad, > 0 violated),
``sep = J_r u`` (m/s or rad/s, < 0 closing), ``mu`` (Coulomb friction), ``arm`` (contact
point minus the segment's centre, m) and ``v_other`` (the collider material's velocity at the
point, m/s). All vectors are in the world frame, SI units.

The model's constants come in as tuples (``collision.Unilateral.model_args`` and
``detector_args``, named indices below); every kernel is callable from other njit code.
Kernels marked ``_nrt=False`` borrow every array they touch (they allocate nothing and return
no array; their callers own all of them): compiled without numba's reference counting, they
skip the atomic increment and decrement each array bound, sliced or passed costs otherwise.

numba's cache does not see edits of a callee in another file (``chain_solve``,
``limit_kernels``); ``kernel_cache.py`` drops the cache files when any kernel source changes.
"""
import math

import numpy as np
from numba import njit

from .chain_solve import blocks_ldl as _chain_factor
from .chain_solve import invert_pivot as _invert_pivot
from .chain_solve import pivot as _pivot
from .chain_solve import solve as _chain_solve
from .chain_solve import solve_from
from .chain_solve import store_factors as _store_factors
from .limit_kernels import limit_terms, project_limits
from .stages import PROFILE_POSITIONS, PROFILE_ROWS, PROFILE_VELOCITIES, cycles
from .vec import (add, cross, dot, norm, q4, qaxis_x, qfrom_rotvec, qmatrix, qmul, qnormalize,
                  qrotate, scale, sub, v3)

POSITION_ITERATIONS = 4      # passes of the position LCP per step, at most
POSITION_TOLERANCE = 1e-5    # m (contacts), rad (limits): stop once no violation exceeds this
POSITION_SKIN = 1e-3         # m: contacts this close (plus 4× the deepest violation) join the
                             # position LCP as inequalities (a correction must not push a
                             # neighbouring segment in)
ANGLE_SKIN = 1e-3            # rad: the same for limits
VELOCITY_SKIN = 1e-4         # m: a contact this close is touching for the velocity stage
SPECULATIVE_STEPS = 2.0      # a gap closing within this many steps joins the velocity stage
ROOT_LEVER = 0.5             # a rooted first segment is tested on s in [ROOT_LEVER, 1]
MAX_ROTATION = 0.25          # rad: largest rotation of one segment per position pass
MOBILITY = 1e-8              # a row the jointed chain moves less than this fraction of its
                             # free segment's mobility (a contact at the anchor) is left out
REG = 1e-9                   # relative regularisation of the (unit-diagonal) Delassus matrix
PIVOT_TOL = 1e-12            # sign tolerance of the principal pivoting (scaled units)
ROW_COLLIDERS = 8            # the row tables hold m × min(K, this) + 2 n_l rows (m colliding
                             # segments, K colliders, n_l limited joints); more are allocated
SWEEP_COLLIDERS = 16         # from this many round colliders on, the broad phase sweeps them
                             # sorted along one axis (``sweep_order``) instead of testing all
SWEEP_MARGIN = 1e-9          # relative: the sweep keeps colliders this much farther out
PAIR_MARGIN = 1e-3           # m: the per-pair broad phase keeps pairs this much farther out
                             # (rounding, and joints not exactly closed)

# Columns of a row.
LIN, ANG, APAR, ARM, VOTH, DEPTH, SEP, MU, NCOL = 0, 3, 6, 9, 12, 15, 16, 17, 18
SEG, PAR, CONTACT = 0, 1, 2

# The constant tuples (``collision.Unilateral.model_args``, ``_Detector.args``) and the pose.
(LENGTH, INV_MASS, INV_INERTIA, INV_I_MAX, IS_FIRST, HAS_CHILD, PARENT, CHAIN_OF, CHAIN_START,
 CHAIN_END, AXISYMMETRIC, LIMITED, SWING_LIMIT, TWIST_LIMIT) = range(14)
(D_SEG, D_RADIUS, D_LENGTH, D_INNER, D_FIRST_OF, D_FIRST_CHAIN, D_ROOT_FIXED, D_ROOTED_FIXED,
 D_SUM_RADIUS, D_CHAINS, D_CHAIN_REACH, D_MAX_HALF, D_N_SPHERE, D_N_ROUND, D_COL_RADIUS,
 D_FRICTION) = range(16)
P_A0, P_D2, P_NORMAL, P_ORIGIN, P_VELOCITY, P_OMEGA, P_SPEED = range(7)

# Status of ``resolve`` (``NO_ROOM``: of ``resolve_chains_into``, the row tables
# overflowed: its caller grows them and resolves that chain again).
OK, NOT_POSITIVE_DEFINITE, NO_ROOM = 0, 1, 2


@njit(cache=True)
def col3(R, r, c):
    """Row r's 3-vector at columns c:c+3 (e.g. ``col3(R, r, LIN)``)."""
    return (R[r, c], R[r, c + 1], R[r, c + 2])


@njit(cache=True)
def mat_vec(M, i, u):
    """M[i] u for a stack of 3×3 matrices ``M``."""
    return (M[i, 0, 0] * u[0] + M[i, 0, 1] * u[1] + M[i, 0, 2] * u[2],
            M[i, 1, 0] * u[0] + M[i, 1, 1] * u[1] + M[i, 1, 2] * u[2],
            M[i, 2, 0] * u[0] + M[i, 2, 1] * u[1] + M[i, 2, 2] * u[2])


# -- the chain's configuration: half-vectors, inverse inertias, the factorised J M⁻¹ Jᵀ ------
@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
def half_vectors(length, q, h):
    for i in range(q.shape[0]):
        hi = scale(0.5 * length[i], qaxis_x(q4(q, i)))
        for a in range(3):
            h[i, a] = hi[a]


# -- the colliders in the world ------------------------------------------------------------------
@njit(cache=True)
def collider_pose(body_position, body_orientation, body_velocity, body_omega, cols):
    """The colliders at one instant: ``(a0, d2, normal, origin, velocity, omega, speed)``
    (``collision.ColliderPose``), each collider's local ``a0``, ``d2`` and ``normal`` turned
    into the world by its body's pose (``body < 0``: the world, no motion). ``speed`` bounds
    the speed of its surface: |v_origin| + |ω| × its reach from the body origin (m/s).

    ``cols``: ``(body, local_a0, local_d2, local_normal, reach)``; the body arrays are the
    kinematic bodies' origins (``AnchorKinematics`` of the origins), world frame.
    """
    K = cols[0].shape[0]
    pose = (np.empty((K, 3)), np.empty((K, 3)), np.empty((K, 3)), np.empty((K, 3)),
            np.empty((K, 3)), np.empty((K, 3)), np.empty(K))
    collider_pose_into(body_position, body_orientation, body_velocity, body_omega, cols, pose)
    return pose


@njit(cache=True, _nrt=False)
def collider_pose_into(body_position, body_orientation, body_velocity, body_omega, cols, pose):
    """``collider_pose`` into the arrays of ``pose`` (a step loop allocates them once)."""
    body, local_a0, local_d2, local_normal, reach = cols
    a0, d2, normal, origin, velocity, omega, speed = pose
    for j in range(body.shape[0]):
        b = body[j]
        la0, ld2, ln = v3(local_a0, j), v3(local_d2, j), v3(local_normal, j)
        if b < 0:
            wa0, wd2, wn = la0, ld2, ln
            for a in range(3):
                origin[j, a] = 0.0
                velocity[j, a] = 0.0
                omega[j, a] = 0.0
            speed[j] = 0.0
        else:
            qb = q4(body_orientation, b)
            o = v3(body_position, b)
            wa0 = add(o, qrotate(qb, la0))
            wd2 = qrotate(qb, ld2)
            wn = qrotate(qb, ln)
            vb, ob = v3(body_velocity, b), v3(body_omega, b)
            for a in range(3):
                origin[j, a] = o[a]
                velocity[j, a] = vb[a]
                omega[j, a] = ob[a]
            speed[j] = norm(vb) + norm(ob) * reach[j]
        for a in range(3):
            a0[j, a] = wa0[a]
            d2[j, a] = wd2[a]
            normal[j, a] = wn[a]


# -- detection ---------------------------------------------------------------------------------
@njit(cache=True)
def clip01(s):
    return 0.0 if s < 0.0 else min(s, 1.0)


@njit(cache=True)
def rooted(anchor, a0, d2, sum_radius, length):
    """Is a first segment's anchor inside, or within a quarter segment of, a round collider?"""
    e2 = max(dot(d2, d2), 1e-300)
    rel = sub(anchor, a0)
    ta = clip01(dot(rel, d2) / e2)
    return sum_radius - norm(sub(rel, scale(ta, d2))) > -0.25 * length


@njit(cache=True)
def closest_segment_segment(p0, d1, a0, d2):
    """Clamped closest points ``s``, ``t`` ∈ [0, 1] of segments ``p0 + s d1`` and
    ``a0 + t d2`` (``d2`` non-zero; Ericson, *Real-Time Collision Detection* 5.1.9)."""
    r = sub(p0, a0)
    a = dot(d1, d1)
    e = dot(d2, d2)
    b = dot(d1, d2)
    c = dot(d1, r)
    f = dot(d2, r)
    denom = a * e - b * b
    s = clip01((b * f - c * e) / denom) if denom > 1e-12 * a * e else 0.0
    t = (b * s + f) / e
    if t < 0.0:
        s = clip01(-c / a)
    elif t > 1.0:
        s = clip01((b - c) / a)
    return s, clip01(t)


@njit(cache=True, _nrt=False)
def detect_segments(x, h, anchor_position, pose, det, report, m0, m1, j, depth, s_out, t_out,
                    own):
    """``detect`` for colliding segments ``m0:m1`` and collider j: entries ``[m0:m1, j]`` of
    each table. The tuples' arrays are taken out once, before the segments' loop (each array
    bound inside the loop would cost a reference count per segment)."""
    seg = det[D_SEG]
    a0, d2, normal = pose[P_A0], pose[P_D2], pose[P_NORMAL]
    seg_radius, seg_length, inner = det[D_RADIUS], det[D_LENGTH], det[D_INNER]
    first_of, first_chain = det[D_FIRST_OF], det[D_FIRST_CHAIN]
    root_fixed, rooted_fixed = det[D_ROOT_FIXED], det[D_ROOTED_FIXED]
    sum_radius, n_sphere, n_round = det[D_SUM_RADIUS], det[D_N_SPHERE], det[D_N_ROUND]
    aj, dj = v3(a0, j), v3(d2, j)
    for m in range(m0, m1):
        # Segment m's core p0 + s d1, proximal to distal joint.
        g = seg[m]
        hg = v3(h, g)
        p0 = sub(v3(x, g), hg)
        d1 = scale(2.0, hg)
        f = first_of[m]
        if j >= n_round:
            nn = v3(normal, j)
            off = dot(aj, nn)
            s1 = dot(add(p0, d1), nn) - off
            if report:
                s1 = min(s1, dot(p0, nn) - off)
            depth[m, j] = seg_radius[m] - s1
            s_out[m, j] = 1.0
            t_out[m, j] = 0.0
            own[m, j] = True
            continue
        if j < n_sphere:
            s = clip01(dot(sub(aj, p0), d1) / (seg_length[m] * seg_length[m]))
            t = 0.0
        else:
            s, t = closest_segment_segment(p0, d1, aj, dj)
        if f >= 0:
            if root_fixed[f, j]:
                is_rooted = rooted_fixed[f, j]
            else:
                is_rooted = rooted(v3(anchor_position, first_chain[f]), aj, dj,
                                   sum_radius[m, j], seg_length[m])
            if is_rooted:
                e2 = max(dot(dj, dj), 1e-300)
                s = max(s, ROOT_LEVER)
                t = clip01(dot(sub(add(p0, scale(s, d1)), aj), dj) / e2)
        diff = sub(add(p0, scale(s, d1)), add(aj, scale(t, dj)))
        depth[m, j] = sum_radius[m, j] - norm(diff)
        s_out[m, j] = s
        t_out[m, j] = t
        own[m, j] = not (inner[m] and s <= 0.0)


@njit(cache=True, _nrt=False)
def detect(x, h, anchor_position, pose, det, report, depth, s_out, t_out, own):
    """Depth (m, > 0 inside) of every colliding segment (capsule) in every collider, the
    closest-point parameters ``s`` (on the segment, proximal 0 to distal 1) and ``t`` (on a
    capsule's core), and ``own`` (the pair may make a row), all ``(m, K)``.

    Spheres: clamped point–segment closest point; capsules: clamped segment–segment closest
    points (Ericson 5.1.9); planes: the distal end (``report``: the deeper end). A non-first
    segment's proximal joint is its parent's distal joint: no row there (``own`` False). A
    first segment rooted on a round collider is tested on ``s ≥ ROOT_LEVER``.
    """
    for j in range(pose[P_A0].shape[0]):
        detect_segments(x, h, anchor_position, pose, det, report, 0, det[D_SEG].shape[0], j,
                        depth, s_out, t_out, own)


@njit(cache=True, inline='always')
def anchor_distance(p, aj, dj, nn, is_round, radius):
    """Distance (m) from a chain's anchor ``p`` to a collider's surface: to a round
    collider's core ``aj + t dj`` minus its ``radius``, a plane's (through ``aj``, normal
    ``nn``) signed height. Vectors as 3-tuples: called per (chain, collider) pair, it binds
    no array."""
    if is_round:
        rel = sub(p, aj)
        e2 = max(dot(dj, dj), 1e-300)
        t = clip01(dot(rel, dj) / e2)
        return norm(sub(rel, scale(t, dj))) - radius
    return dot(p, nn) - dot(aj, nn)


@njit(cache=True, inline='always')
def outside_box(p, aj, dj, radius, reach):
    """Is the anchor ``p`` farther than ``reach`` (m) along some axis from the box around a
    round collider (its core ``aj + t dj``'s box grown by its radius)? Then it is farther
    than that from the collider (a cheap test before ``anchor_distance``: no square root)."""
    for a in range(3):
        e = aj[a] + dj[a]
        if p[a] < min(aj[a], e) - radius - reach or p[a] > max(aj[a], e) + radius + reach:
            return True
    return False


@njit(cache=True, inline='always')
def surface_speed(v, w, det, fastest):
    """A bound (m/s) on how fast any colliding segment's surface nears any collider: the
    fastest centre's speed, plus the fastest spin times the longest half segment, plus the
    fastest collider's surface speed ``fastest`` (``broad_phase_setup``)."""
    v2 = 0.0
    w2 = 0.0
    for i in range(v.shape[0]):
        v2 = max(v2, dot(v3(v, i), v3(v, i)))
        w2 = max(w2, dot(v3(w, i), v3(w, i)))
    return math.sqrt(v2) + math.sqrt(w2) * det[D_MAX_HALF] + fastest


@njit(cache=True, _nrt=False)
def near(anchor_position, pose, v, w, det, dt, fastest):
    """Broad phase: could any collider be within reach of a chain? A chain lies in the ball of
    its length (plus radius) about its anchor; its surface moves at most at
    ``surface_speed``."""
    det_chains, chain_reach = det[D_CHAINS], det[D_CHAIN_REACH]
    a0, d2, normal = pose[P_A0], pose[P_D2], pose[P_NORMAL]
    col_radius, n_round = det[D_COL_RADIUS], det[D_N_ROUND]
    speed = surface_speed(v, w, det, fastest)
    for c in range(det_chains.shape[0]):
        reach = chain_reach[c] + POSITION_SKIN + 2.0 * SPECULATIVE_STEPS * dt * speed
        p = v3(anchor_position, det_chains[c])
        for j in range(a0.shape[0]):
            if anchor_distance(p, v3(a0, j), v3(d2, j), v3(normal, j), j < n_round,
                               col_radius[j]) < reach:
                return True
    return False


# -- the workspace of one ``resolve`` call -------------------------------------------------------
# Every array the stages need, allocated once per call (~100 allocations a step otherwise), as
# few arrays as possible: each array in the tuple costs a reference-count increment and
# decrement wherever the tuple is bound, and the stages bind it several times a step. Sizes:
# n segments, m colliding segments, K colliders, n_l limited joints, k_max = m K + 2 n_l
# candidate rows, cap the row tables' rows (``ROW_COLLIDERS``). Indices into the tuple, and
# into the first axis of its stacked arrays:
(WS_VEC, WS_MAT, WS_R3, WS_TABLES, WS_IDS, WS_DET, WS_OWN, WS_Q, WS_AXIS, WS_LIM, WS_ROWVEC,
 WS_KEEP, WS_PAIRS, WS_SLOTS, WS_CHAIN_SLOT, WS_STATE, WS_BOX, WS_TOUCHED, WS_SOLVE,
 WS_ORDER, WS_SWEEP) = range(21)
# WS_VEC (7, n, 3): the half-vectors of the factorisation, four scratch vectors, then the
# step's velocities on entry (kept to resolve it again if the row tables overflow).
V_H, V_N0, V_N1, V_N2, V_N3, V_V0, V_W0 = range(7)
# WS_MAT (4, n, 3, 3): the factorisation (I⁻¹, pivots, Lo: ``factor_chain``), the blocks G.
M_INV_I, M_PIVOTS, M_LO, M_G = range(4)
# WS_TABLES (3, cap, NCOL) floats and WS_IDS (3, cap, 3) integers: the row tables.
T_ROWS, T_SEL, T_FRIC = range(3)
# WS_DET (3, m, K): detection (``detect``); WS_LIM (2, 2 n_l): the limits' gaps and rates.
DT_DEPTH, DT_S, DT_T = range(3)
L_GAP, L_SEP = range(2)
# WS_ROWVEC (4, k_max): per-row right-hand side, impulses, slip speeds, friction bounds.
R_B, R_LAM, R_SPEED, R_BOUND = range(4)
# WS_PAIRS (nd, K) and WS_SLOTS (3, nd) integers, WS_STATE (nd, K) bytes, WS_BOX (K, 7)
# floats and WS_ORDER (K,) integers: the per-pair broad phase (``near_pairs``: kept pairs,
# slots, pair states, the round colliders' boxes and their sweep order, ``sweep_order``).
S_COUNT, S_FIRST, S_END = range(3)
# WS_SWEEP (5,) floats: what ``broad_phase_setup`` found for this step's colliders (whether
# the sweep is on, its axis, the widest box along it, the largest bound, the fastest
# collider's surface speed), for every chain's ``near_pairs``.
SW_ON, SW_AXIS, SW_WIDEST, SW_BOUND, SW_FASTEST = range(5)
# WS_TOUCHED (2, C) integers: a mark per chain and the list of the chains with rows
# (``factor_touched``).
# WS_SOLVE: ``solve_rows_into``'s scratch (``solve_scratch``), sized for the usual row groups.
# Indices into it:
SC_INT, SC_MOBILE, SC_RESP, SC_CDOT, SC_W, SC_LC, SC_DS = range(7)


# The workspace is sized for the largest chain (``resolve_workspace``) and a call resolves one
# chain: its per-segment arrays are taken at that chain's length (leading-axis views, the same
# C-contiguous types), so that no loop over an array's length reads another chain's leftovers.
@njit(cache=True, inline='always')
def zero_pair(a, b):
    """``a[:] = 0; b[:] = 0`` for two ``(n, 3)`` arrays, as plain loops (a slice assignment
    of a 2-D view costs more than its few stores, and these are zeroed at every step)."""
    for i in range(a.shape[0]):
        for k in range(3):
            a[i, k] = 0.0
            b[i, k] = 0.0


@njit(cache=True, inline='always')
def vec(ws, i, n):
    """The workspace's vector ``i`` (``V_*``), ``(n, 3)``."""
    return ws[WS_VEC][i][:n]


@njit(cache=True, inline='always')
def mat(ws, i, n):
    """The workspace's block array ``i`` (``M_*``), ``(n, 3, 3)``."""
    return ws[WS_MAT][i][:n]


@njit(cache=True, inline='always')
def factors(ws, n):
    """The factorisation in the workspace (half-vectors, I⁻¹, pivots, Lo) of ``n`` segments."""
    return vec(ws, V_H, n), mat(ws, M_INV_I, n), mat(ws, M_PIVOTS, n), mat(ws, M_LO, n)
SOLVE_GROUP_ROWS = 32        # the workspace's solve scratch holds row groups up to this many
                             # rows (a larger group's scratch is allocated by its call)


@njit(cache=True, inline='always')
def solve_scratch(k, kg, nc, n_chains):
    """Scratch of ``solve_rows_into`` for up to ``k`` rows, groups of up to ``kg`` rows and
    chains of up to ``nc`` segments (``n_chains`` chains): the row grouping's integers
    (``group_rows_into``), the rows' mobility mask, the responses ``(2, kg, nc, 3)``, the joint
    scratch ``(nc, 3)``, W ``(kg, kg)``, a group's λ ``(kg,)`` and the dense problems'
    scratch (``dense_scratch``)."""
    return (np.empty(4 * k + 1 + n_chains, dtype=np.int64), np.empty(k, dtype=np.bool_),
            np.empty((2, kg, nc, 3)), np.empty((nc, 3)), np.empty((kg, kg)), np.empty(kg),
            dense_scratch(kg))


@njit(cache=True, inline='always')
def workspace(n, m, K, nl, nd, n_chains, nc_max):
    """The workspace of ``resolve`` (indices ``WS_*`` and, within the stacked arrays, the
    names above): half-vectors and scratch vectors, the factorisation and its blocks, two 3×3,
    the row tables (all rows, a selection, friction rows; ``grown`` gives larger ones when
    needed), detection tables ``(m, K)``, one ``(n, 4)``, the limits' axes ``(2 n_l, 3)``,
    gaps and rates, per-row vectors and a mask ``(k_max)``, the per-pair broad phase's
    tables (nd colliding chains of n_chains), the touched chains' marks and the row solve's
    scratch (chains of up to ``nc_max`` segments)."""
    k_max = m * K + 2 * nl
    # The row tables' capacity: a crowd's segments each near a few colliders of many (a
    # workspace this small is reused by malloc, not mapped and faulted in at every call).
    cap = m * min(K, ROW_COLLIDERS) + 2 * nl
    return (np.empty((7, n, 3)), np.empty((4, n, 3, 3)), np.empty((2, 3, 3)),
            np.empty((3, cap, NCOL)), np.empty((3, cap, 3), dtype=np.int64),
            np.empty((3, m, K)), np.empty((m, K), dtype=np.bool_), np.empty((n, 4)),
            np.empty((2 * nl, 3)), np.empty((2, 2 * nl)), np.empty((4, k_max)),
            np.empty(k_max, dtype=np.bool_), np.empty((nd, K), dtype=np.int64),
            np.empty((3, nd), dtype=np.int64), np.empty(n_chains, dtype=np.int64),
            np.empty((nd, K), dtype=np.uint8), np.empty((K, 7)),
            np.empty((2, n_chains), dtype=np.int64),
            solve_scratch(cap, min(cap, SOLVE_GROUP_ROWS), nc_max, n_chains),
            np.empty(K, dtype=np.int64), np.empty(5))


@njit(cache=True, _nrt=True)
def grown(ws):
    """``ws`` with row tables that hold every candidate row (``k_max``: each colliding segment
    in each collider, and each limit twice), for the rare call whose rows overflow the usual
    ones (a segment near more than ``ROW_COLLIDERS`` colliders)."""
    k_max = ws[WS_ROWVEC].shape[1]
    return (ws[WS_VEC], ws[WS_MAT], ws[WS_R3], np.empty((3, k_max, NCOL)),
            np.empty((3, k_max, 3), dtype=np.int64), ws[WS_DET], ws[WS_OWN], ws[WS_Q],
            ws[WS_AXIS], ws[WS_LIM], ws[WS_ROWVEC], ws[WS_KEEP], ws[WS_PAIRS], ws[WS_SLOTS],
            ws[WS_CHAIN_SLOT], ws[WS_STATE], ws[WS_BOX], ws[WS_TOUCHED], ws[WS_SOLVE],
            ws[WS_ORDER], ws[WS_SWEEP])


@njit(cache=True, inline='always')
def resolve_workspace(model, det, split, pose, has_colliders):
    """``workspace`` for resolving a model's chains one at a time (``resolve_chains_into``):
    sized for its largest chain (segments, colliding segments, limited joints), against all
    the colliders."""
    chain_start, chain_end = model[CHAIN_START], model[CHAIN_END]
    lim, rows = split[SP_LIM_RANGE], split[SP_DET_RANGE]
    n = m = nl = 0
    for c in range(chain_start.shape[0]):
        n = max(n, chain_end[c] - chain_start[c])
        m = max(m, rows[1, c] - rows[0, c])
        nl = max(nl, lim[1, c] - lim[0, c])
    if not has_colliders:
        return workspace(n, 0, 0, nl, 0, 1, n)
    return workspace(n, m, pose[P_A0].shape[0], nl, 1, 1, n)


# -- one chain at a time ----------------------------------------------------------------------
# Chains do not touch one another (colliders are kinematic bodies), so each chain's contacts
# and limits are resolved on their own: its own rows, skin, deepest violation, position passes,
# factorisation and projections, as if it were alone with all the colliders. A stage that
# pooled the chains (one skin, one deepest violation, passes and re-projection of all of
# them) made a character's motion depend on what the others touched.
# The split of the constant tuples (``collision.Unilateral.split_args``), what a chain's own
# tuples (``chain_model``, ``chain_det``) take besides views of the whole model's: parent
# indices in chain numbering (n), zeros (n), each chain's segment count (C), the limited
# joints in chain numbering (n_l, chain by chain) and each chain's range of them (2, C), each
# chain's range of the colliding segments (2, C), those in chain numbering (m) and their index
# among the chain's first segments (0 or -1, m), each chain's slot among the colliding chains
# and the index of its first segment among all first colliding segments (C, -1: none), and
# each chain's longest half colliding segment (C, m).
(SP_PARENT, SP_ZERO, SP_COUNT, SP_LIMITED, SP_LIM_RANGE, SP_DET_RANGE, SP_DET_SEG,
 SP_FIRST_OF, SP_SLOT, SP_FIRST, SP_MAX_HALF) = range(11)


@njit(cache=True, inline='always')
def chain_model(model, split, c):
    """The model tuple of chain ``c`` alone (views of ``model`` and ``split``)."""
    s, e = model[CHAIN_START][c], model[CHAIN_END][c]
    ls, le = split[SP_LIM_RANGE][0, c], split[SP_LIM_RANGE][1, c]
    zero = split[SP_ZERO]
    return (model[LENGTH][s:e], model[INV_MASS][s:e], model[INV_INERTIA][s:e],
            model[INV_I_MAX][s:e], model[IS_FIRST][s:e], model[HAS_CHILD][s:e],
            split[SP_PARENT][s:e], zero[s:e], zero[0:1], split[SP_COUNT][c:c + 1],
            model[AXISYMMETRIC], split[SP_LIMITED][ls:le], model[SWING_LIMIT][s:e],
            model[TWIST_LIMIT][s:e])


@njit(cache=True, inline='always')
def chain_det(det, split, c):
    """The detector tuple of chain ``c`` alone, with every collider (views)."""
    ms, me = split[SP_DET_RANGE][0, c], split[SP_DET_RANGE][1, c]
    slot, f = split[SP_SLOT][c], split[SP_FIRST][c]
    ns, nf = (1 if slot >= 0 else 0), (1 if f >= 0 else 0)
    slot, f = max(slot, 0), max(f, 0)
    zero = split[SP_ZERO]
    return (split[SP_DET_SEG][ms:me], det[D_RADIUS][ms:me], det[D_LENGTH][ms:me],
            det[D_INNER][ms:me], split[SP_FIRST_OF][ms:me], zero[0:nf],
            det[D_ROOT_FIXED][f:f + nf], det[D_ROOTED_FIXED][f:f + nf],
            det[D_SUM_RADIUS][ms:me], zero[0:ns], det[D_CHAIN_REACH][slot:slot + ns],
            split[SP_MAX_HALF][c], det[D_N_SPHERE], det[D_N_ROUND], det[D_COL_RADIUS],
            det[D_FRICTION])


@njit(cache=True, inline='always')
def chain_anchor(anchor, c):
    """Chain ``c``'s row of the anchors' ``(position, velocity, orientation, ω)`` (views)."""
    return (anchor[0][c:c + 1], anchor[1][c:c + 1], anchor[2][c:c + 1], anchor[3][c:c + 1])


@njit(cache=True)
def chain_args(model, det, split, c):
    """``(chain_model, chain_det)`` of chain ``c`` (for callers in Python)."""
    return chain_model(model, split, c), chain_det(det, split, c)


@njit(cache=True, inline='always')
def chain_is_free(split, has_colliders, c):
    """Whether chain ``c`` has nothing to resolve (no colliding segment, no limit)."""
    collides = has_colliders and split[SP_SLOT][c] >= 0
    return not collides and split[SP_LIM_RANGE][1, c] == split[SP_LIM_RANGE][0, c]


# -- rows ----------------------------------------------------------------------------------------
@njit(cache=True)
def contact_frame(xg, hg, s, t, aj, dj, nj, radius, is_round):
    """Normal (from the collider to the segment) and touching point on the surface of the
    segment (centre ``xg``, half-vector ``hg``) for the closest points ``s`` (segment) and
    ``t`` (a round collider's core ``aj + t dj``; a plane: its normal ``nj``). Vectors as
    3-tuples: called per row, it binds no array."""
    ps = add(xg, scale(2.0 * s - 1.0, hg))
    if not is_round:
        nrm = nj
    else:
        diff = sub(ps, add(aj, scale(t, dj)))
        dist = norm(diff)
        if dist > 1e-12:
            nrm = (diff[0] / dist, diff[1] / dist, diff[2] / dist)
        else:
            # On the core: any direction perpendicular to the segment.
            ref = (1.0, 0.0, 0.0) if abs(hg[0]) < 0.9 else (0.0, 1.0, 0.0)
            p = cross(hg, ref)
            npn = norm(p)
            nrm = (p[0] / npn, p[1] / npn, p[2] / npn)
    return nrm, sub(ps, scale(radius, nrm))


@njit(cache=True, inline='always')
def test_pair(state, c, j, p, reach, box, a0, d2, normal, n_round, col_radius, pair_list,
              count):
    """``near_pairs``' test of the pair (chain slot c at anchor ``p``, collider j), unless
    decided already: kept (state 1, appended to ``pair_list[c]``, ``count[c]`` of them) when
    the collider's surface is within ``reach``, a round collider's box tested first
    (``outside_box`` with the bounds of ``box``)."""
    if state[c, j] != 0:
        return
    if j < n_round and (p[0] < box[j, 0] - reach or p[0] > box[j, 3] + reach
                        or p[1] < box[j, 1] - reach or p[1] > box[j, 4] + reach
                        or p[2] < box[j, 2] - reach or p[2] > box[j, 5] + reach):
        return
    if anchor_distance(p, v3(a0, j), v3(d2, j), v3(normal, j), j < n_round,
                       col_radius[j]) < reach:
        state[c, j] = 1
        pair_list[c, count[c]] = j
        count[c] += 1


@njit(cache=True, _nrt=False)
def sweep_order(box, nr, order):
    """The broad phase's sweep over many round colliders (``near_pairs``): ``(sweep, axis,
    widest, bound)``; sweep False (test every pair) for fewer than ``SWEEP_COLLIDERS`` or a
    box that is not finite. Else ``order`` ``(nr,)`` receives the colliders sorted by their
    box's lower bound along the axis of the largest spread (column 6 of ``box``: that bound),
    ``widest`` is the widest box along it, ``bound`` the largest magnitude of a bound."""
    if nr < SWEEP_COLLIDERS:
        return False, 0, 0.0, 0.0
    bound = 0.0
    ax, spread = 0, -1.0
    for a in range(3):
        lo, hi = np.inf, -np.inf
        for j in range(nr):
            if not (np.isfinite(box[j, a]) and np.isfinite(box[j, 3 + a])):
                return False, 0, 0.0, 0.0
            lo = min(lo, box[j, a])
            hi = max(hi, box[j, a])
            bound = max(bound, max(abs(box[j, a]), abs(box[j, 3 + a])))
        if hi - lo > spread:
            ax, spread = a, hi - lo
    wmax = 0.0
    for j in range(nr):
        order[j] = j
        box[j, 6] = box[j, ax]
        wmax = max(wmax, box[j, 3 + ax] - box[j, ax])
    # Shell sort of the order by the lower bounds (Ciura's gaps; few colliders).
    for gap in (701, 301, 132, 57, 23, 10, 4, 1):
        for i in range(gap, nr):
            t = order[i]
            key = box[t, 6]
            k = i
            while k >= gap and box[order[k - gap], 6] > key:
                order[k] = order[k - gap]
                k -= gap
            order[k] = t
    return True, ax, wmax, bound


@njit(cache=True, _nrt=False)
def broad_phase_setup(pose, det, ws):
    """What the broad phase of every chain shares in a step (``WS_BOX``, ``WS_ORDER``,
    ``WS_SWEEP``): the round colliders' boxes (``outside_box``'s bounds before the reach), their
    sweep order (``sweep_order``) and the fastest collider's surface speed; once per step, not
    once per chain and detection."""
    a0, d2, col_radius, n_round = pose[P_A0], pose[P_D2], det[D_COL_RADIUS], det[D_N_ROUND]
    box, sweep = ws[WS_BOX], ws[WS_SWEEP]
    K = a0.shape[0]
    nr = min(K, n_round)
    for j in range(nr):
        for a in range(3):
            e = a0[j, a] + d2[j, a]
            box[j, a] = min(a0[j, a], e) - col_radius[j]
            box[j, 3 + a] = max(a0[j, a], e) + col_radius[j]
    on, ax, wmax, bound = sweep_order(box, nr, ws[WS_ORDER][:nr])
    col_speed = pose[P_SPEED]
    fastest = 0.0
    for j in range(col_speed.shape[0]):
        fastest = max(fastest, col_speed[j])
    sweep[SW_ON] = 1.0 if on else 0.0
    sweep[SW_AXIS] = ax
    sweep[SW_WIDEST] = wmax
    sweep[SW_BOUND] = bound
    sweep[SW_FASTEST] = fastest


@njit(cache=True, inline='always')
def near_pairs(x, h, anchor_position, pose, v, w, model, det, dt, ws):  # noqa: C901 (kernel loops)
    """Broad phase per (colliding chain, collider) pair, then detection (``detect_segments``) of
    every segment of the pairs kept; returns the position skin (``POSITION_SKIN`` plus 4×
    the deepest violation, at least ``VELOCITY_SKIN``), as if every pair had been detected.

    A pair is kept when the collider's surface is within the chain's reach (its length plus
    radius about its anchor, ``near``) plus the skin, ``2 SPECULATIVE_STEPS dt`` times
    ``surface_speed`` and ``PAIR_MARGIN``: a pair left out is then deeper outside than any
    row could reach (its depth ≤ -(distance - reach)), so it would make no row and no depth
    of it could raise the skin. Kept pairs can raise the skin, which can keep more pairs:
    repeated until the skin stands. Pairs kept, per chain slot c (``det[D_CHAINS][c]``):
    colliders ``ws[WS_PAIRS][c, :ws[WS_SLOTS][S_COUNT][c]]``, in column order."""
    seg, det_chains, chain_reach = det[D_SEG], det[D_CHAINS], det[D_CHAIN_REACH]
    a0, d2, normal = pose[P_A0], pose[P_D2], pose[P_NORMAL]
    col_radius, n_round = det[D_COL_RADIUS], det[D_N_ROUND]
    chain_of = model[CHAIN_OF]
    depth, s, t, own = ws[WS_DET][DT_DEPTH], ws[WS_DET][DT_S], ws[WS_DET][DT_T], ws[WS_OWN]
    state, pair_list, count = ws[WS_STATE], ws[WS_PAIRS], ws[WS_SLOTS][S_COUNT]
    first_seg, end_seg, slot = ws[WS_SLOTS][S_FIRST], ws[WS_SLOTS][S_END], ws[WS_CHAIN_SLOT]
    box, sw = ws[WS_BOX], ws[WS_SWEEP]
    nd, K = det_chains.shape[0], a0.shape[0]
    # Each chain's colliding segments are consecutive in det[D_SEG].
    for c in range(nd):
        slot[det_chains[c]] = c
        first_seg[c] = seg.shape[0]
        end_seg[c] = 0
    for i in range(seg.shape[0]):
        c = slot[chain_of[seg[i]]]
        first_seg[c] = min(first_seg[c], i)
        end_seg[c] = i + 1
    state[:] = 0            # 0: left out, 1: kept in this pass, 2: detected
    count[:nd] = 0
    speed = surface_speed(v, w, det, sw[SW_FASTEST])
    deepest = 0.0
    skin = max(POSITION_SKIN + 4.0 * deepest, VELOCITY_SKIN)
    tested = -1.0
    # (the boxes and their order: ``broad_phase_setup``, once per step)
    order = ws[WS_ORDER][:min(K, n_round)]
    sweep, ax, wmax, bound = sw[SW_ON] != 0.0, int(sw[SW_AXIS]), sw[SW_WIDEST], sw[SW_BOUND]
    while skin > tested:
        tested = skin
        for c in range(nd):
            # The pairs kept in this pass are appended to the chain's list (not marked in a
            # table scanned over every collider: a crowd's chain is near one collider of
            # hundreds), then detected in collider order, as a scan would.
            kept = count[c]
            reach = (chain_reach[c] + skin + 2.0 * SPECULATIVE_STEPS * dt * speed
                     + PAIR_MARGIN)
            p = v3(anchor_position, det_chains[c])
            if not sweep:
                for j in range(K):
                    test_pair(state, c, j, p, reach, box, a0, d2, normal, n_round, col_radius,
                              pair_list, count)
            else:
                # Only the round colliders whose box can be within reach along the axis
                # ``ax`` (boxes sorted by their lower bound there, none wider than ``wmax``),
                # with a margin far above rounding: every pair left out fails the box test.
                margin = SWEEP_MARGIN * (1.0 + abs(p[ax]) + reach + wmax + bound)
                left = p[ax] - reach - wmax - margin
                right = p[ax] + reach + margin
                lo, hi = 0, order.shape[0]
                while lo < hi:
                    mid = (lo + hi) // 2
                    if box[order[mid], 6] < left:
                        lo = mid + 1
                    else:
                        hi = mid
                while lo < order.shape[0] and box[order[lo], 6] <= right:
                    test_pair(state, c, order[lo], p, reach, box, a0, d2, normal, n_round,
                              col_radius, pair_list, count)
                    lo += 1
                for j in range(order.shape[0], K):
                    test_pair(state, c, j, p, reach, box, a0, d2, normal, n_round, col_radius,
                              pair_list, count)
            sort_ints(pair_list[c, kept:count[c]])
            for jj in range(kept, count[c]):
                j = pair_list[c, jj]
                state[c, j] = 2
                detect_segments(x, h, anchor_position, pose, det, False, first_seg[c],
                                end_seg[c], j, depth, s, t, own)
                for i in range(first_seg[c], end_seg[c]):
                    deepest = max(deepest, depth[i, j])
        skin = max(POSITION_SKIN + 4.0 * deepest, VELOCITY_SKIN)
    for c in range(nd):
        sort_ints(pair_list[c, :count[c]])
    return skin


@njit(cache=True, inline='always')
def sort_ints(a):
    """``a`` sorted in place, ascending (insertion sort: a chain keeps a few pairs)."""
    for i in range(1, a.shape[0]):
        key = a[i]
        k = i
        while k > 0 and a[k - 1] > key:
            a[k] = a[k - 1]
            k -= 1
        a[k] = key


@njit(cache=True, inline='always')
def contact_rows(x, q, v, w, anchor_position, pose, model, det, dt, R, I, ws):
    """The contact rows into ``R``, ``I`` (segment-major, from row 0, with room left for the
    limit rows): returns ``(number, R, I)``, number -1 if the tables could be too small.
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
        return -1, R, I             # the caller grows the tables (``grown``) and starts over
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
    return k, R, I


@njit(cache=True, _nrt=False)
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


@njit(cache=True, inline='always')
def build_rows_into(x, q, v, w, anchor, q_rest, pose, model, det, has_colliders, dt, ws):
    """``build_rows`` into the workspace's row table: ``(fits, R, I)``, ``R``, ``I`` views of
    it valid until the next call; ``fits`` False (and no rows) when the table is too small
    (``grown`` gives a workspace whose tables hold every candidate row)."""
    nl = model[LIMITED].shape[0]
    R, I = ws[WS_TABLES][T_ROWS], ws[WS_IDS][T_ROWS]
    k = 0
    # With the sweep on, ``near_pairs`` finds the pairs within reach faster than ``near``
    # tests every collider (a crowd's); without a pair in ``near``'s reach it makes no row.
    sw = ws[WS_SWEEP]
    if has_colliders and (sw[SW_ON] != 0.0 or near(anchor[0], pose, v, w, det, dt,
                                                    sw[SW_FASTEST])):
        k, R, I = contact_rows(x, q, v, w, anchor[0], pose, model, det, dt, R, I, ws)
        if k < 0:
            return False, R[:0], I[:0]
    if nl:
        k = limit_rows(q, w, anchor, q_rest, model, dt, R, I, k, ws[WS_AXIS][:2 * nl],
                       ws[WS_LIM][L_GAP][:2 * nl], ws[WS_LIM][L_SEP][:2 * nl])
    return True, R[:k], I[:k]


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
            fits, R, I = build_rows_into(x[s:e], q[s:e], v[s:e], w[s:e], chain_anchor(anchor, c),
                                         q_rest[s:e], pose, sub, sub_det, collides, dt, ws)
            if not fits:
                ws = grown(ws)
                fits, R, I = build_rows_into(x[s:e], q[s:e], v[s:e], w[s:e],
                                             chain_anchor(anchor, c), q_rest[s:e], pose, sub,
                                             sub_det, collides, dt, ws)
            if copy_pass == 1:
                for r in range(R.shape[0]):
                    R_all[k + r, :] = R[r, :]
                    I_all[k + r, SEG] = I[r, SEG] + s
                    I_all[k + r, PAR] = I[r, PAR] + s if I[r, PAR] >= 0 else -1
                    I_all[k + r, CONTACT] = I[r, CONTACT]
            k += R.shape[0]
    return R_all, I_all


@njit(cache=True, inline='always')
def take(R, I, keep, R2, I2):
    """The rows where ``keep``, into ``R2``, ``I2`` (tables at least as long as ``R``, ``I``):
    views of their first rows."""
    k = 0
    for r in range(keep.shape[0]):
        if keep[r]:
            for c in range(NCOL):
                R2[k, c] = R[r, c]
            for c in range(3):
                I2[k, c] = I[r, c]
            k += 1
    return R2[:k], I2[:k]


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
def refresh_sep(R, I, v, w, anchor_omega, chain_of):
    """The rows' separation rates for new velocities (geometry unchanged), in place."""
    for r in range(R.shape[0]):
        g, p = I[r, SEG], I[r, PAR]
        w_par = v3(w, p) if p >= 0 else v3(anchor_omega, chain_of[g])
        R[r, SEP] = (dot(col3(R, r, LIN),
                         sub(v3(v, g), col3(R, r, VOTH)))
                     + dot(col3(R, r, ANG), v3(w, g))
                     + dot(col3(R, r, APAR), w_par))


# -- small dense problems ------------------------------------------------------------------------
@njit(cache=True, _nrt=False)
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


@njit(cache=True)
def dense_scratch(k):
    """Fresh scratch for dense problems of up to k rows (indices ``DS_*``)."""
    return (np.empty((4, k, k)), np.empty((7, k)), np.empty((2, k), dtype=np.int64),
            np.empty((2, k), dtype=np.bool_))


@njit(cache=True, inline='always')
def square(A, k):
    """The leading k×k block of the matrix ``A``."""
    return A[:k, :k]


@njit(cache=True, _nrt=False)
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


@njit(cache=True)
def solve_active(Ws, bs, active, lam):
    """λ_A = -W_AA⁻¹ b_A on the active set A, λ = 0 elsewhere (into ``lam``)."""
    k = bs.shape[0]
    solve_active_into(Ws, bs, active, lam, np.empty((k, k)), np.empty((k, k)), np.empty(k),
                      np.empty(k), np.empty(k, dtype=np.int64))


@njit(cache=True, _nrt=False)
def row_dot(A, i, x):
    """Σ_j A[i, j] x[j] (no BLAS)."""
    s = 0.0
    for j in range(x.shape[0]):
        s += A[i, j] * x[j]
    return s


@njit(cache=True, _nrt=False)
def entering_variable(Ws, bs, lam, passive):
    """Lawson–Hanson: the bound variable with the largest dual -(Wλ + b)_i > 1e-12, or -1."""
    best, j = 1e-12, -1
    for i in range(bs.shape[0]):
        if not passive[i]:
            g = -bs[i] - row_dot(Ws, i, lam)
            if g > best:
                best, j = g, i
    return j


@njit(cache=True)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=True)
def _lcp_fallback(Ws, bs, d, out):
    """``lcp``'s Lawson–Hanson fallback into ``out`` (it allocates: kept out of the
    borrowing ``lcp_into``)."""
    lam_fb = nnls_quadratic(Ws, bs)
    for i in range(out.shape[0]):
        out[i] = lam_fb[i] * d[i]


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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


@njit(cache=True, _nrt=False)
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
    counting), else sized by them (``_solve_rows_alloc``: a few allocations, whatever the
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
        _solve_rows_alloc(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam)
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
        _solve_groups_alloc(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam,
                            members, start, n_groups, kg_max, nc_max, sc[SC_MOBILE])


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
    row_response(R, I, 0, h, inv_I, C[s:e], Lo[s:e], is_first[s:e], inv_mass, has_child, s, e,
                 rv, rw, sc[SC_CDOT][:nc])
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


@njit(cache=True, _nrt=True)
def _solve_rows_alloc(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam):
    """``solve_rows_into`` with all its scratch allocated here (returns no array)."""
    chain_of, chain_start, chain_end = model[CHAIN_OF], model[CHAIN_START], model[CHAIN_END]
    k = R.shape[0]
    n_chains = chain_start.shape[0]
    ib = np.empty(4 * k + 1 + n_chains, dtype=np.int64)
    members, start = ib[:k], ib[k:2 * k + 1]
    n_groups, kg_max, nc_max = group_rows_into(I, chain_of, chain_start, chain_end, members,
                                               start, ib[2 * k + 1:4 * k + 1],
                                               ib[4 * k + 1:4 * k + 1 + n_chains])
    _solve_groups_alloc(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam, members,
                        start, n_groups, kg_max, nc_max, np.empty(k, dtype=np.bool_))


@njit(cache=True, _nrt=True)
def _solve_groups_alloc(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam, members,
                        start, n_groups, kg_max, nc_max, mobile):
    """``_solve_groups`` with the per-group scratch allocated for groups of up to ``kg_max``
    rows and chains of up to ``nc_max`` segments (returns no array)."""
    rv_all, rw_all = np.empty((kg_max, nc_max, 3)), np.empty((kg_max, nc_max, 3))
    c_dot_all, W_all, lc_all = np.empty((nc_max, 3)), np.empty((kg_max, kg_max)), np.empty(kg_max)
    ds = dense_scratch(kg_max)
    _solve_groups(R, I, b, bound, h, inv_I, C, Lo, model, dv_out, dw_out, lam, members, start,
                  n_groups, mobile, rv_all, rw_all, c_dot_all, W_all, lc_all, ds)


@njit(cache=True, _nrt=False)
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
            row_response(R, I, mem[a], h, inv_I, Cg, Log, first, inv_mass, has_child, s, e,
                         rv[a], rw[a], c_dot)
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


# -- the pass after a step ------------------------------------------------------------------------
@njit(cache=True, _nrt=False)
def deepest(R, I, with_limits):
    """The deepest violation (≥ 0) of the contact rows (and of the limit rows if asked)."""
    worst = 0.0
    for r in range(R.shape[0]):
        if I[r, CONTACT] or with_limits:
            worst = max(worst, R[r, DEPTH])
    return worst


@njit(cache=True, _nrt=False)
def rotate_segments(q, dth, length):
    """Turn every segment by its rotation vector ``dth`` (clamped in place to
    ``MAX_ROTATION``): q ← normalise(exp(dth) ⊗ q). Returns whether the pass was small: no
    clamp and max l θ² below a tenth of ``POSITION_TOLERANCE`` (its linearisation holds)."""
    unclamped = True
    small = 0.0
    for i in range(q.shape[0]):
        th = v3(dth, i)
        ang2 = dot(th, th)
        clamp = min(1.0, MAX_ROTATION / math.sqrt(max(ang2, 1e-300)))
        unclamped = unclamped and clamp == 1.0
        small = max(small, ang2 * length[i])
        th = scale(clamp, th)
        qi = qnormalize(qmul(qfrom_rotvec(th), q4(q, i)))
        for a in range(3):
            dth[i, a] = th[a]
        for a in range(4):
            q[i, a] = qi[a]
    return unclamped and small < 0.1 * POSITION_TOLERANCE


@njit(cache=True, inline='always')
def factor_ws(q, model, ws):
    """``factor_chain`` into the workspace's factorisation (``V_H``, ``M_INV_I`` … ``M_LO``),
    every chain (``factor_segments`` over all segments)."""
    n = q.shape[0]
    return factor_segments(q, model, 0, n, vec(ws, V_H, n), mat(ws, M_INV_I, n),
                           mat(ws, M_PIVOTS, n), mat(ws, M_LO, n), mat(ws, M_G, n), ws[WS_R3])


@njit(cache=True, _nrt=False)
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


@njit(cache=True, inline='always')
def position_stage(x, q, v, w, anchor, q_rest, pose, model, det, has_colliders, dt, ws, stats,  # noqa: C901, E501
                   profile):
    """Positions: passes of the linearised LCP ``W μ - depth ≥ 0, μ ≥ 0`` over the violated
    rows and those within the skin (plus 4× the deepest violation), each displacement
    ``P M⁻¹ J_rᵀ μ`` applied as segment rotations, positions rebuilt from the anchor, while a
    contact is deeper than ``POSITION_TOLERANCE`` (limits: the first pass). ``x``, ``q`` in
    place. Returns ``(status, moved, R, I)``: the rows at the final pose (views of the
    workspace ``ws``). The cycles of its row builds are added to ``profile``'s rows."""
    length = model[LENGTH]
    h, inv_I, C, Lo = factors(ws, q.shape[0])
    t0 = cycles()
    fits, R, I = build_rows_into(x, q, v, w, anchor, q_rest, pose, model, det, has_colliders,
                                 dt, ws)
    profile[PROFILE_ROWS] += cycles() - t0
    if not fits:
        return NO_ROOM, False, R, I
    moved = False
    for passes in range(POSITION_ITERATIONS):
        if R.shape[0] == 0:
            break
        worst = deepest(R, I, passes == 0)
        if worst <= POSITION_TOLERANCE:
            break
        active = ws[WS_KEEP][:R.shape[0]]
        for r in range(R.shape[0]):
            skin = POSITION_SKIN if I[r, CONTACT] else ANGLE_SKIN
            active[r] = R[r, DEPTH] > -skin - 4.0 * worst
        Rs, Is = take(R, I, active, ws[WS_TABLES][T_SEL], ws[WS_IDS][T_SEL])
        # Only the selected rows' chains are solved for: their factors alone.
        if not factor_rows_ws(q, model, Is, ws):
            return NOT_POSITIVE_DEFINITE, moved, R, I
        ks = Rs.shape[0]
        b = ws[WS_ROWVEC][R_B][:ks]
        for r in range(ks):
            b[r] = -Rs[r, DEPTH]
        # The displacements (centres unused: positions are rebuilt from the rotations).
        dx, dth = vec(ws, V_N2, x.shape[0]), vec(ws, V_N3, x.shape[0])
        zero_pair(dx, dth)
        solve_rows_into(Rs, Is, b, ws[WS_ROWVEC][R_BOUND][:0], h, inv_I, C, Lo, model, dx, dth,
                        ws[WS_ROWVEC][R_LAM][:ks], ws[WS_SOLVE])
        small = rotate_segments(q, dth, length)
        stats[2] = passes + 1
        moved = True
        x_old = vec(ws, V_N0, x.shape[0])
        for i in range(x.shape[0]):
            for a in range(3):
                x_old[i, a] = x[i, a]
        half_vectors(length, q, h)
        project_positions(anchor[0], h, model, x)
        if small:
            # The predicted depths stand (error ~ l θ²), no second detection.
            for i in range(x.shape[0]):
                for a in range(3):
                    dx[i, a] = x[i, a] - x_old[i, a]
            moved_rows(R, I, dx, dth)
            break
        t0 = cycles()
        fits, R, I = build_rows_into(x, q, v, w, anchor, q_rest, pose, model, det,
                                     has_colliders, dt, ws)
        profile[PROFILE_ROWS] += cycles() - t0
        if not fits:
            return NO_ROOM, moved, R, I
    return OK, moved, R, I


@njit(cache=True, inline='always')
def limit_stage(x, q, anchor, q_rest, model, ws):
    """The limits' exact projection (``project_limits``) for what the linearisation of their
    cones left; ``x``, ``q`` in place. Returns whether anything moved."""
    q_lim = ws[WS_Q][:q.shape[0]]
    if not project_limits(q, anchor[2], q_rest, model[IS_FIRST], model[CHAIN_OF],
                          model[CHAIN_START], model[CHAIN_END], model[LIMITED],
                          model[SWING_LIMIT], model[TWIST_LIMIT], POSITION_TOLERANCE, q_lim):
        return False
    for i in range(q.shape[0]):
        for a in range(4):
            q[i, a] = q_lim[i, a]
    h = vec(ws, V_N1, q.shape[0])
    half_vectors(model[LENGTH], q, h)
    project_positions(anchor[0], h, model, x)
    return True


@njit(cache=True, _nrt=False)
def unprojected_positions(x0, q0, q, anchor, model, x, h, p0, p1):
    """Without projection the centres move by the rotations about the joints only:
    x = x0 + (joint-closed centres at q) - (joint-closed centres at q0). ``h``, ``p0``,
    ``p1`` ``(n, 3)``: scratch."""
    half_vectors(model[LENGTH], q0, h)
    project_positions(anchor[0], h, model, p0)
    half_vectors(model[LENGTH], q, h)
    project_positions(anchor[0], h, model, p1)
    for i in range(x.shape[0]):
        for a in range(3):
            x[i, a] = x0[i, a] + (p1[i, a] - p0[i, a])


@njit(cache=True, inline='always')
def velocity_stage(R, I, q, v, w, anchor, model, project, dt, have_factor, ws, stats):
    """Velocities: every row touching, or whose gap would close within ``SPECULATIVE_STEPS``
    steps at its current rate, gets the inelastic impulse of the LCP
    ``W λ + sep + max(gap, 0)/dt ≥ 0``, then friction; ``v``, ``w`` in place. Returns the
    status (the chain is factorised here if it was not yet)."""
    h, inv_I, C, Lo = factors(ws, q.shape[0])
    k = R.shape[0]
    keep = ws[WS_KEEP][:k]
    for r in range(k):
        gap = -R[r, DEPTH]
        sep = R[r, SEP]
        skin = VELOCITY_SKIN if I[r, CONTACT] else ANGLE_SKIN
        keep[r] = gap < skin or (sep < 0.0 and gap < -SPECULATIVE_STEPS * dt * sep)
    Rv, Iv = take(R, I, keep, ws[WS_TABLES][T_SEL], ws[WS_IDS][T_SEL])
    kv = Rv.shape[0]
    b = ws[WS_ROWVEC][R_B][:kv]
    closing = False
    for r in range(kv):
        stats[0 if Iv[r, CONTACT] else 1] += 1
        b[r] = Rv[r, SEP] + max(-Rv[r, DEPTH], 0.0) / dt
        closing = closing or b[r] < 0.0
    if not closing:
        return OK
    if not have_factor and not factor_rows_ws(q, model, Iv, ws):
        return NOT_POSITIVE_DEFINITE
    velocity_impulses(Rv, Iv, b, h, inv_I, C, Lo, model, v, w, ws)
    if project:
        project_velocities(anchor[1], w, h, model, v)
    return OK


@njit(cache=True, _nrt=False)
def resolve_chains_into(x0, q0, x, q, v, w, anchor, pose, model, det, split, q_rest,  # noqa: C901
                        has_colliders, project, dt, stats, own, ws, first, profile):
    """``resolve`` on ``x``, ``q``, ``v``, ``w`` in place (on entry: the step's state), chain
    by chain (``chain_model``, ``chain_det``, ``chain_anchor``): each chain is resolved as if
    it were alone with all the colliders, so that what one chain touches never changes
    another's step. Chains with nothing to resolve (no colliding segment, no limit) are
    skipped; the broad phase's per-step setup (``broad_phase_setup``) is done once, for all.
    ``x0``, ``q0``: a copy of the step's positions (not ``x``, ``q`` themselves). ``ws``: the
    workspace (``resolve_workspace`` of this model, detector and colliders: a step loop
    allocates it once for all its steps; every stage writes what it reads there first, as it
    must of ``np.empty``'s contents). ``stats``: the contacts and limits summed over the
    chains, the most position passes any took. ``own`` ``(3,)`` int64: scratch.

    Returns ``(status, chain)``: a chain that fails stops the call; ``NO_ROOM``: chain
    ``chain``'s candidate rows overflowed the row tables (a segment near more than
    ``ROW_COLLIDERS`` colliders), that chain is restored to its entry state and the caller
    resolves again from it (``first``) with ``grown(ws)``, kept for the next steps.
    ``first`` 0 starts a step (the stats and the broad phase's setup). ``profile``: the
    step's profile (``stages.PROFILE_SIZE`` int64), whose contact stages
    (``stages.CONTACT_STAGES``) get the cycles of each chain's rows, positions and velocities.

    It allocates nothing and borrows every array (``_nrt=False``): entering a function
    that counts references costs an atomic increment of each of its arrays (the model's, the
    detector's, the workspace's) and a decrement on the way out, at every step."""
    if first == 0:
        stats[:] = 0
        if has_colliders:
            broad_phase_setup(pose, det, ws)
    chain_start, chain_end = model[CHAIN_START], model[CHAIN_END]
    for c in range(first, chain_start.shape[0]):
        if chain_is_free(split, has_colliders, c):
            continue
        s, e = chain_start[c], chain_end[c]
        n = e - s
        v0, w0 = vec(ws, V_V0, n), vec(ws, V_W0, n)
        for i in range(n):
            for a in range(3):
                v0[i, a] = v[s + i, a]
                w0[i, a] = w[s + i, a]
        collides = has_colliders and split[SP_SLOT][c] >= 0
        status = _resolve_stages(x0[s:e], q0[s:e], x[s:e], q[s:e], v[s:e], w[s:e],
                                 chain_anchor(anchor, c), pose, chain_model(model, split, c),
                                 chain_det(det, split, c), q_rest[s:e], collides, project,
                                 dt, own, ws, profile)
        if status == NO_ROOM:
            for i in range(n):
                for a in range(3):
                    x[s + i, a] = x0[s + i, a]
                    v[s + i, a] = v0[i, a]
                    w[s + i, a] = w0[i, a]
                for a in range(4):
                    q[s + i, a] = q0[s + i, a]
            return status, c
        stats[0] += own[0]
        stats[1] += own[1]
        stats[2] = max(stats[2], own[2])
        if status != OK:
            return status, c
    return OK, chain_start.shape[0]


@njit(cache=True, _nrt=False)
def _resolve_stages(x0, q0, x, q, v, w, anchor, pose, model, det, q_rest, has_colliders,
                    project, dt, stats, ws, profile):
    """One chain's stages (``resolve``), in order, borrowing every array (no reference
    counting); ``NO_ROOM`` if the row tables overflow. Their cycles go to ``profile``'s
    contact stages (``stages.CONTACT_STAGES``)."""
    stats[:] = 0
    h, inv_I, C, Lo = factors(ws, q.shape[0])
    t0 = cycles()
    rows0 = profile[PROFILE_ROWS]
    status, moved, R, I = position_stage(x, q, v, w, anchor, q_rest, pose, model, det,
                                         has_colliders, dt, ws, stats, profile)
    if status != OK:
        return status
    stale = model[LIMITED].shape[0] > 0 and limit_stage(x, q, anchor, q_rest, model, ws)
    moved = moved or stale
    if moved:
        if not project:
            n = x.shape[0]
            unprojected_positions(x0, q0, q, anchor, model, x, vec(ws, V_N1, n),
                                  vec(ws, V_N0, n), vec(ws, V_N2, n))
        if not factor_ws(q, model, ws):
            return NOT_POSITIVE_DEFINITE
        n = x.shape[0]
        joint_projection(v, w, anchor[1], h, inv_I, C, Lo, model, vec(ws, V_N0, n),
                         vec(ws, V_N2, n), vec(ws, V_N3, n))
        if stale:
            t = cycles()
            fits, R, I = build_rows_into(x, q, v, w, anchor, q_rest, pose, model, det,
                                         has_colliders, dt, ws)
            profile[PROFILE_ROWS] += cycles() - t
            if not fits:
                return NO_ROOM
        else:
            refresh_sep(R, I, v, w, anchor[3], model[CHAIN_OF])
    t1 = cycles()
    profile[PROFILE_POSITIONS] += (t1 - t0) - (profile[PROFILE_ROWS] - rows0)
    if R.shape[0]:
        status = velocity_stage(R, I, q, v, w, anchor, model, project, dt, moved, ws, stats)
        if status != OK:
            return status
    if moved and project:
        half_vectors(model[LENGTH], q, h)
        project_velocities(anchor[1], w, h, model, v)
    profile[PROFILE_VELOCITIES] += cycles() - t1
    return OK


@njit(cache=True)
def resolve(x, q, v, w, anchor, pose, model, det, split, q_rest, has_colliders, project, dt,
            stats):
    """Contacts and limits at the end of a step of length ``dt`` (s): positions, then
    velocities (inelastic impulses, then friction). Returns ``(status, x, q, v, w)`` (new
    arrays; the inputs are not changed); ``stats`` ``(3,)`` receives the contacts and limits
    of the velocity stage and the position passes taken.

    ``anchor``: ``(position, velocity, orientation, angular_velocity)`` of every chain's
    attachment (C rows); ``pose``: ``(a0, d2, normal, origin, velocity, omega, speed)`` of the
    colliders (``collision.ColliderPose``); ``model`` and ``det``: the constant tuples built by
    ``collision.Unilateral`` and ``split`` their split by chain (``SP_*``); ``q_rest``: the
    joints' rest rotations (``Model.q_rest``). Chains are resolved one at a time
    (``resolve_chains_into``).

    Stages, in order: ``position_stage``, ``limit_stage``, then (if anything moved) the
    unchanged velocities projected M-orthogonally onto the moved joints (never adding kinetic
    energy), ``velocity_stage``, and the centre velocities rebuilt from ω. All scratch is one
    workspace (``workspace``), a few allocations per call (``resolve_chains_into``: the same
    in place, on a workspace kept across steps).
    """
    x1, q1, v1, w1 = x.copy(), q.copy(), v.copy(), w.copy()
    ws = resolve_workspace(model, det, split, pose, has_colliders)
    own = np.empty(3, dtype=np.int64)
    profile = np.zeros(PROFILE_VELOCITIES + 1, dtype=np.int64)     # (not reported)
    status, c = resolve_chains_into(x, q, x1, q1, v1, w1, anchor, pose, model, det, split,
                                    q_rest, has_colliders, project, dt, stats, own, ws, 0,
                                    profile)
    while status == NO_ROOM:
        ws = grown(ws)
        status, c = resolve_chains_into(x, q, x1, q1, v1, w1, anchor, pose, model, det,
                                        split, q_rest, has_colliders, project, dt, stats, own,
                                        ws, c, profile)
    return status, x1, q1, v1, w1
