"""The RK4 step of a crowd, chains side by side in SIMD lanes: bit for bit ``step.advance``.

A crowd (many chains of one segment count) is stepped ``LANES`` chains at a time: every
per-segment quantity of a block of chains is stored ``(segment, component, lane)``, and every
loop that does arithmetic runs innermost over the lanes, with a constant trip count, no
branches and no calls, so that LLVM vectorises it across chains (``<4 x double>``). Each lane
does exactly the floating-point operations of ``step.advance`` on its chain, in the same order:
IEEE arithmetic is the same in a SIMD lane as in a scalar register (no ``fastmath``, no FMA
contraction), so the results are identical bit for bit, which ``test/test_lanes.py`` checks.

What makes the loops vectorise (checked with LLVM's remarks: ``llvmlite.binding.set_option('',
'-pass-remarks=loop-vectorize')`` and ``-pass-remarks-missed=...``, then ``advance_lanes.py_func``
compiled uncached with ``debug=True, boundscheck=False`` for line numbers):
  * everything a block's steps touch per segment lives in one record array allocated inside
    the kernel, ``R[segment, field + component, lane]`` with compile-time field count and
    lane count: every address in a lane loop is a constant offset from one base, so LLVM
    proves the loop free of dependences (with one array per field, as a first version had,
    it could not tell them apart from each other or from the arguments and gave up);
  * ``sqrt`` is LLVM's intrinsic (``vec.sqrt_ieee``), not numba's call to libm's ``sqrt`` (a call
    stops the vectoriser; both are IEEE's correctly rounded square root, so the same bits);
  * ``error_model='numpy'``: a division is then a plain ``fdiv``, not a test for zero that
    raises (only a blown-up chain divides by zero: its status or the guard reports it);
  * what differs between the first joint and the others (the anchor as parent, the first
    pivot), or between the tip and the others, is chosen outside the lane loop: two loops.
At 4 lanes the loops of the joint solve (all joints but the first, both sweeps), the RK4 stage
updates, the step's start and the applied forces' gravity are vectorised (<4 x double>); the
first joint's loop, the projection, the joint damping and the drag loops are not (LLVM asks
for runtime checks it will not make there) and run lane by lane: the same bits, more time.
The bending stiffness takes three passes (``_joint_torques``): its rotation vectors' factors in
one flat loop over every joint of the block, which vectorises (``vec.rotvec_factor``:
no call, no branch).

Covered (the rest goes to ``step.advance``, see ``supports``): RK4, axisymmetric segments
(the gyroscopic term ω × Iω), gravity, explicit joint damping, bending stiffness, linear and
quadratic drag with wind, external forces and torques, the O(n) joint solve
(``chain_solve``'s block LDLᵀ, as ``step_rk4``'s accelerations does it), the projection
(positions and velocities rebuilt from the anchor), every chain of the same segment count.
``advance_lanes`` transposes the state into the lane layout once per call and back at its
end; ``crowd_records`` and ``step_blocks`` take one step at a time, the state gathered and
scattered at each, for the contact step loop (``step_unilateral``), which changes it between
steps. A last, partial block is filled with copies of its last chain (their results
discarded).

Frames and units: world frame, SI, as ``step``: ``x`` ``(n, 3)`` centres (m), ``q`` ``(n, 4)``
(x, y, z, w) body to world, ``v`` ``(n, 3)`` (m/s), ``w`` ``(n, 3)`` ω in the world frame
(rad/s); ``f_c`` ``(n, 3)`` the joint forces on the children at the last stage (N).
"""
import numba as nb
import numpy as np

from . import step
from .chain_solve import ZERO6, G_axisymmetric, inv_inertia_axisymmetric, joint_row
from .kernel_cache import ensure_fresh
from .step_model import JOINT_SOLVE_FAILED, OK, RK4
from .vec import cross_s, qaxis_x_s, qmul_s, qrot_s, rotvec_factor, sqrt_ieee

ensure_fresh()

__all__ = ['LANES', 'MIN_CHAINS', 'advance', 'advance_lanes', 'crowd_layout', 'supports',
           'kernel_for', 'crowd_records', 'step_blocks']

# Chains per block. A compile-time constant: the lane loops' trip count, which LLVM splits
# into whole vectors (<4 x double>: AVX2, and AVX-512 parts prefer 256-bit vectors). 4 lanes
# beat 8 and 16 at every crowd size of 16-segment chains (``ponytail_bench step``): the record
# of a wider block outgrows L1, and a partial block pads more copies.
LANES = 4
# Fewer chains than this run through ``step.advance`` (a padded block costs a full block).
MIN_CHAINS = 4

_jit = nb.njit(cache=True, error_model='numpy')
_inline = nb.njit(cache=True, error_model='numpy', inline='always')



def _offsets(*widths):
    """The first component of each field of widths ``widths``, and the total."""
    out = [0]
    for k in widths:
        out.append(out[-1] + k)
    return tuple(out)


# One block's record: ``R[i, field + component, lane]``, ``(m, _NF, LANES)``, one array for
# everything the steps touch per segment, so that every address in a lane loop is a constant
# offset from one base (``_NF`` and ``LANES`` are compile-time constants): LLVM proves the
# loops free of dependences without alias analysis or runtime checks.
#   the state:       _X, _Q, _V, _W (ω world); _WB ω in the body frame;
#   an RK4 stage:    _XS, _QS, _VS, _WBS, _WS (its state, ω_b and ω world), _ACC (a), _ALPHA (α);
#                    _SX, _SV, _SQ, _SWB the stage derivatives' weighted sums;
#   the joint solve: _F, _T applied forces/torques, _HV h = (l/2) e, _IINV world I⁻¹
#                    (row-major), _G = [h]× I⁻¹ [h]× (upper triangle), _C = P⁻¹ (upper
#                    triangle), _LO = 𝓛 (row-major), _PA the distal point's acceleration,
#                    _FC the forward-substituted rhs, then λ = f_c; _BAD failed pivots so far;
#   the projection:  _PE, _UE the distal joint's position and velocity;
#   external:        _EXTF, _EXTT;
#   the model:       _HALF l/2, _IM 1/m, _I0, _I1 axial and perpendicular moments, _II0, _II1
#                    their inverses, _FG m g (gravity on), _DAMP c, _DL, _DQ drag
#                    coefficients, _LEN l, _KT c_lin l³/12 (the same expressions as
#                    ``step``'s, so the same bits), _STIFF k (bending), _QR the joint's rest
#                    rotation q_rest.
(_X, _Q, _V, _W, _WB, _XS, _QS, _VS, _WBS, _WS, _ACC, _ALPHA, _SX, _SV, _SQ, _SWB, _F, _T,
 _HV, _IINV, _G, _C, _LO, _PA, _FC, _BAD, _PE, _UE, _EXTF, _EXTT, _HALF, _IM, _I0, _I1, _II0,
 _II1, _FG, _DAMP, _DL, _DQ, _LEN, _KT, _STIFF, _QR, _NF) = _offsets(
    3, 4, 3, 3, 3, 3, 4, 3, 3, 3, 3, 3, 3, 3, 4, 3, 3, 3,
    3, 9, 6, 6, 9, 3, 3, 1, 3, 3, 3, 3, 1, 1, 1, 1, 1,
    1, 3, 1, 1, 1, 1, 1, 1, 4)


# -- layout: the crowd into blocks of lanes and back -------------------------------------------
@_inline
def _chain_of_lane(b, l, n_chains):
    """The chain lane ``l`` of block ``b`` carries (a copy of the last chain past the end)."""
    return min(b * LANES + l, n_chains - 1)


@_inline
def _load_model(M, b, n_chains, m, R):
    """Block ``b``'s per-lane model into the record ``R`` from the ``StepModel`` ``M``."""
    for l in range(LANES):
        s = _chain_of_lane(b, l, n_chains) * m
        for i in range(m):
            j = s + i
            R[i, _HALF, l] = M.half[j]
            R[i, _IM, l] = M.inv_mass[j]
            R[i, _I0, l] = M.inertia[j, 0]
            R[i, _I1, l] = M.inertia[j, 1]
            R[i, _II0, l] = M.inv_inertia[j, 0]
            R[i, _II1, l] = M.inv_inertia[j, 1]
            for a in range(3):
                R[i, _FG + a, l] = M.mass[j] * M.gravity[a] if M.gravity_on else 0.0
            R[i, _DAMP, l] = M.damping[j]
            R[i, _DL, l] = M.drag_linear[j]
            R[i, _DQ, l] = M.drag_quadratic[j]
            R[i, _LEN, l] = M.length[j]
            R[i, _KT, l] = M.drag_linear[j] * (M.length[j] ** 3 / 12.0)
            R[i, _STIFF, l] = M.stiffness[j]
            for a in range(4):
                R[i, _QR + a, l] = M.q_rest[j, a]


@_inline
def _gather(src, b, n_chains, m, R, f):
    """Block ``b``'s rows of ``src`` ``(n, k)`` into the record's field ``f``."""
    for l in range(LANES):
        s = _chain_of_lane(b, l, n_chains) * m
        for i in range(m):
            for a in range(src.shape[1]):
                R[i, f + a, l] = src[s + i, a]


@_inline
def _scatter(R, f, b, n_chains, m, dst):
    """The record's field ``f`` back into block ``b``'s rows of ``dst`` ``(n, k)`` (real
    chains only)."""
    for l in range(min(LANES, n_chains - b * LANES)):
        s = (b * LANES + l) * m
        for i in range(m):
            for a in range(dst.shape[1]):
                dst[s + i, a] = R[i, f + a, l]


@_inline
def _gather_anchors(A, r0, b, n_chains, E):
    """Block ``b``'s anchors ``E`` ``(S, _NE, LANES)``: position, velocity, acceleration,
    angular velocity and orientation (components ``_AX``, ``_AV``, ``_AA``, ``_AW``, ``_AQ``)
    at the stage times of the table ``A``'s rows ``r0 ..`` (as many as ``E`` has)."""
    for r in range(E.shape[0]):
        for l in range(LANES):
            c = _chain_of_lane(b, l, n_chains)
            for a in range(3):
                E[r, _AX + a, l] = A.position[r0 + r, c, a]
                E[r, _AV + a, l] = A.velocity[r0 + r, c, a]
                E[r, _AA + a, l] = A.acceleration[r0 + r, c, a]
                E[r, _AW + a, l] = A.angular_velocity[r0 + r, c, a]
            for a in range(4):
                E[r, _AQ + a, l] = A.orientation[r0 + r, c, a]


_AX, _AV, _AA, _AW, _AQ, _NE = 0, 3, 6, 9, 12, 16


# -- the stages, each over all segments of a block ---------------------------------------------
@_inline
def _start(m, R):
    """The step's first stage: ω in the body frame, the stage state = the state."""
    for i in range(m):
        for l in range(LANES):
            qx, qy, qz, qw = R[i, _Q, l], R[i, _Q + 1, l], R[i, _Q + 2, l], R[i, _Q + 3, l]
            b0, b1, b2 = qrot_s(-qx, -qy, -qz, qw, R[i, _W, l], R[i, _W + 1, l],
                               R[i, _W + 2, l])
            R[i, _WB, l], R[i, _WB + 1, l], R[i, _WB + 2, l] = b0, b1, b2
            for a in range(3):
                R[i, _XS + a, l] = R[i, _X + a, l]
                R[i, _VS + a, l] = R[i, _V + a, l]
            R[i, _WBS, l], R[i, _WBS + 1, l], R[i, _WBS + 2, l] = b0, b1, b2
            R[i, _QS, l], R[i, _QS + 1, l], R[i, _QS + 2, l], R[i, _QS + 3, l] = qx, qy, qz, qw
            R[i, _WS, l], R[i, _WS + 1, l], R[i, _WS + 2, l] = qrot_s(qx, qy, qz, qw, b0, b1, b2)


@_inline
def _applied(m, row, R, E, S, wind0, wind1, wind2, explicit_damping, stiffness_on, drag_on,
             external_on):
    """Applied forces and torques (N, N·m, world) at the stage state, ``applied_terms``'
    terms in its order: gravity, the joint torques (damping, then bending stiffness: τ on the
    child, -τ on the parent), drag, external."""
    for i in range(m):
        for l in range(LANES):
            for a in range(3):
                R[i, _F + a, l] = R[i, _FG + a, l]
                R[i, _T + a, l] = 0.0
    _joint_terms(m, row, R, E, S, explicit_damping, stiffness_on)
    if drag_on:
        _drag(m, R, wind0, wind1, wind2)
    if external_on:
        for i in range(m):
            for l in range(LANES):
                for a in range(3):
                    R[i, _F + a, l] += R[i, _EXTF + a, l]
                    R[i, _T + a, l] += R[i, _EXTT + a, l]


@_inline
def _joint_terms(m, row, R, E, S, explicit_damping, stiffness_on):
    """The joint torques switched on: damping alone, or with bending stiffness."""
    if stiffness_on:
        _joint_torques(m, row, R, E, S, explicit_damping)
    elif explicit_damping:
        _joint_damping(m, row, R, E)


@_inline
def _joint_damping(m, row, R, E):
    """τ = -c (ω_child - ω_parent) at every joint, on the child, and -τ on the parent."""
    for l in range(LANES):              # the first joint: the anchor body is the parent
        k = R[0, _DAMP, l]
        for a in range(3):
            R[0, _T + a, l] += 0.0 - k * (R[0, _WS + a, l] - E[row, _AW + a, l])
    for i in range(1, m):
        for l in range(LANES):
            k = R[i, _DAMP, l]
            for a in range(3):
                tau = 0.0 - k * (R[i, _WS + a, l] - R[i - 1, _WS + a, l])
                R[i, _T + a, l] += tau
                R[i - 1, _T + a, l] -= tau


@_inline
def _deviation(R, i, l, px, py, pz, pw, S):
    """Joint i's deviation from rest in lane l, its parent's orientation p given: q = p ⊗
    q_rest ⊗ q_err, q_err = (p ⊗ q_rest)* ⊗ q into ``S``'s quaternions (``applied_terms``'
    expressions, so the same bits)."""
    rx, ry, rz, rw = qmul_s(px, py, pz, pw, R[i, _QR, l], R[i, _QR + 1, l], R[i, _QR + 2, l],
                           R[i, _QR + 3, l])
    ex, ey, ez, ew = qmul_s(-rx, -ry, -rz, rw, R[i, _QS, l], R[i, _QS + 1, l],
                           R[i, _QS + 2, l], R[i, _QS + 3, l])
    Sq = S[0]
    k = i * LANES + l
    Sq[0, k], Sq[1, k], Sq[2, k], Sq[3, k] = ex, ey, ez, ew


@_inline
def _joint_torques(m, row, R, E, S, explicit_damping):
    """Joint damping (if ``explicit_damping``) and bending stiffness at every joint: τ =
    -c (ω_child - ω_parent) - k θ_err (summed in ``applied_terms``' order), on the child, and
    -τ on the parent. In three passes over the block's joints: their deviations q_err into
    the scratch ``S`` (``stiffness_scratch``), the rotation vectors' factors
    (``vec.rotvec_factor``, one flat loop over every joint of every lane: it
    vectorises, where called per lane it ran lane by lane), then the torques."""
    for l in range(LANES):              # the first joint: the anchor body is the parent
        _deviation(R, 0, l, E[row, _AQ, l], E[row, _AQ + 1, l], E[row, _AQ + 2, l],
                   E[row, _AQ + 3, l], S)
    for i in range(1, m):
        for l in range(LANES):
            _deviation(R, i, l, R[i - 1, _QS, l], R[i - 1, _QS + 1, l], R[i - 1, _QS + 2, l],
                       R[i - 1, _QS + 3, l], S)
    Sq, Sf = S
    for k in range(m * LANES):
        Sf[k] = rotvec_factor(Sq[0, k], Sq[1, k], Sq[2, k], Sq[3, k])
    for i in range(m):
        for l in range(LANES):
            tau0, tau1, tau2 = 0.0, 0.0, 0.0
            if explicit_damping:
                if i == 0:              # the first joint: the anchor body is the parent
                    pw0, pw1, pw2 = E[row, _AW, l], E[row, _AW + 1, l], E[row, _AW + 2, l]
                else:
                    pw0, pw1, pw2 = (R[i - 1, _WS, l], R[i - 1, _WS + 1, l],
                                     R[i - 1, _WS + 2, l])
                c = R[i, _DAMP, l]
                tau0 -= c * (R[i, _WS, l] - pw0)
                tau1 -= c * (R[i, _WS + 1, l] - pw1)
                tau2 -= c * (R[i, _WS + 2, l] - pw2)
            k = i * LANES + l
            f = Sf[k]
            s0, s1, s2 = qrot_s(R[i, _QS, l], R[i, _QS + 1, l], R[i, _QS + 2, l],
                               R[i, _QS + 3, l], Sq[0, k] * f, Sq[1, k] * f, Sq[2, k] * f)
            stiff = R[i, _STIFF, l]
            tau0 -= stiff * s0
            tau1 -= stiff * s1
            tau2 -= stiff * s2
            R[i, _T, l] += tau0
            R[i, _T + 1, l] += tau1
            R[i, _T + 2, l] += tau2
            if i > 0:
                R[i - 1, _T, l] -= tau0
                R[i - 1, _T + 1, l] -= tau1
                R[i - 1, _T + 2, l] -= tau2


@_inline
def stiffness_scratch(m):
    """The bending stiffness's scratch for blocks of m segments per chain: the joints'
    deviations ``(4, m LANES)`` and rotation-vector factors ``(m LANES,)``, joint-major (its
    own arrays, allocated where the loops are: see ``advance_lanes``)."""
    return np.empty((4, m * LANES)), np.empty(m * LANES)


@_inline
def _drag(m, R, wind0, wind1, wind2):
    """Linear and quadratic drag on the velocity relative to the wind, and the linear
    drag's torque on the swing (ω less its axial part)."""
    for i in range(m):
        for l in range(LANES):
            u0 = R[i, _VS, l] - wind0
            u1 = R[i, _VS + 1, l] - wind1
            u2 = R[i, _VS + 2, l] - wind2
            speed = sqrt_ieee(u0 * u0 + u1 * u1 + u2 * u2)
            c1 = R[i, _DL, l]
            k = (c1 + R[i, _DQ, l] * speed) * R[i, _LEN, l]
            R[i, _F, l] -= k * u0
            R[i, _F + 1, l] -= k * u1
            R[i, _F + 2, l] -= k * u2
            x, y, z, w = R[i, _QS, l], R[i, _QS + 1, l], R[i, _QS + 2, l], R[i, _QS + 3, l]
            e0, e1, e2 = qaxis_x_s(x, y, z, w)
            w0, w1, w2 = R[i, _WS, l], R[i, _WS + 1, l], R[i, _WS + 2, l]
            wa = w0 * e0 + w1 * e1 + w2 * e2
            kt = R[i, _KT, l]
            R[i, _T, l] -= kt * (w0 - wa * e0)
            R[i, _T + 1, l] -= kt * (w1 - wa * e1)
            R[i, _T + 2, l] -= kt * (w2 - wa * e2)


@_inline
def _free(R, i, l):
    """Segment i's part of ``step_rk4``'s accelerations' root-to-tip sweep, stored in the record:
    its world I⁻¹, h = (l/2) e, free accelerations α (rad/s²) and a (m/s², without f_c), G;
    returns a, G and t = α × h + ω × (ω × h), the acceleration of its distal point relative
    to its centre."""
    qx, qy, qz, qw = R[i, _QS, l], R[i, _QS + 1, l], R[i, _QS + 2, l], R[i, _QS + 3, l]
    w0, w1, w2 = R[i, _WS, l], R[i, _WS + 1, l], R[i, _WS + 2, l]
    e0, e1, e2 = qaxis_x_s(qx, qy, qz, qw)
    X = inv_inertia_axisymmetric(e0, e1, e2, R[i, _II0, l], R[i, _II1, l])
    hl = R[i, _HALF, l]
    h0, h1, h2 = hl * e0, hl * e1, hl * e2
    s = (R[i, _I0, l] - R[i, _I1, l]) * (e0 * w0 + e1 * w1 + e2 * w2)    # ω × Iω
    c0, c1, c2 = cross_s(w0, w1, w2, e0, e1, e2)
    y0, y1, y2 = s * c0, s * c1, s * c2
    v0, v1, v2 = R[i, _T, l] - y0, R[i, _T + 1, l] - y1, R[i, _T + 2, l] - y2
    a0 = X[0] * v0 + X[1] * v1 + X[2] * v2
    a1 = X[3] * v0 + X[4] * v1 + X[5] * v2
    a2 = X[6] * v0 + X[7] * v1 + X[8] * v2
    im = R[i, _IM, l]
    ac0, ac1, ac2 = R[i, _F, l] * im, R[i, _F + 1, l] * im, R[i, _F + 2, l] * im
    c0, c1, c2 = cross_s(a0, a1, a2, h0, h1, h2)
    u0, u1, u2 = cross_s(w0, w1, w2, h0, h1, h2)              # ω × h
    d0, d1, d2 = cross_s(w0, w1, w2, u0, u1, u2)
    g = G_axisymmetric(h0, h1, h2, R[i, _II1, l])
    for j in range(9):
        R[i, _IINV + j, l] = X[j]
    for j in range(6):
        R[i, _G + j, l] = g[j]
    R[i, _HV, l], R[i, _HV + 1, l], R[i, _HV + 2, l] = h0, h1, h2
    R[i, _ALPHA, l], R[i, _ALPHA + 1, l], R[i, _ALPHA + 2, l] = a0, a1, a2
    R[i, _ACC, l], R[i, _ACC + 1, l], R[i, _ACC + 2, l] = ac0, ac1, ac2
    return (ac0, ac1, ac2), (c0 + d0, c1 + d1, c2 + d2), g


@_inline
def _forward(m, row, R, E):
    """Root to tip (``step_rk4``'s accelerations' first sweep): per segment its free motion, joint
    i's right-hand side (parent point minus child point acceleration), joint i's row of
    A = J M⁻¹ Jᵀ factorised (``_C`` = P⁻¹, ``_LO`` = 𝓛) and the right-hand side
    forward-substituted (``_FC``). ``_BAD`` counts, root to segment, the pivots that were not
    positive definite (the chain's joint solve failed)."""
    for l in range(LANES):              # joint 0: the parent point is the anchor
        ac, t, g = _free(R, 0, l)
        for j in range(3):
            R[0, _FC + j, l] = E[row, _AA + j, l] - (ac[j] - t[j])
            R[0, _PA + j, l] = ac[j] + t[j]
        ok, lo, pinv = joint_row(True, ZERO6, R[0, _IM, l], 0.0, g, ZERO6)
        for j in range(6):
            R[0, _C + j, l] = pinv[j]
        for j in range(9):
            R[0, _LO + j, l] = lo[j]
        R[0, _BAD, l] = 0.0 if ok else 1.0
    for i in range(1, m):
        for l in range(LANES):
            ac, t, g = _free(R, i, l)
            r0 = R[i - 1, _PA, l] - (ac[0] - t[0])
            r1 = R[i - 1, _PA + 1, l] - (ac[1] - t[1])
            r2 = R[i - 1, _PA + 2, l] - (ac[2] - t[2])
            for j in range(3):
                R[i, _PA + j, l] = ac[j] + t[j]
            gp = (R[i - 1, _G, l], R[i - 1, _G + 1, l], R[i - 1, _G + 2, l],
                  R[i - 1, _G + 3, l], R[i - 1, _G + 4, l], R[i - 1, _G + 5, l])
            pp = (R[i - 1, _C, l], R[i - 1, _C + 1, l], R[i - 1, _C + 2, l],
                  R[i - 1, _C + 3, l], R[i - 1, _C + 4, l], R[i - 1, _C + 5, l])
            ok, lo, pinv = joint_row(False, pp, R[i, _IM, l], R[i - 1, _IM, l], g, gp)
            for j in range(6):
                R[i, _C + j, l] = pinv[j]
            for j in range(9):
                R[i, _LO + j, l] = lo[j]
            R[i, _BAD, l] = R[i - 1, _BAD, l] + (0.0 if ok else 1.0)
            z0, z1, z2 = R[i - 1, _FC, l], R[i - 1, _FC + 1, l], R[i - 1, _FC + 2, l]
            r0 -= lo[0] * z0 + lo[1] * z1 + lo[2] * z2
            r1 -= lo[3] * z0 + lo[4] * z1 + lo[5] * z2
            r2 -= lo[6] * z0 + lo[7] * z1 + lo[8] * z2
            R[i, _FC, l], R[i, _FC + 1, l], R[i, _FC + 2, l] = r0, r1, r2


@_inline
def _failed(m, R):
    """Whether some lane's joint solve failed at the last ``_forward`` (``_BAD`` counts the
    failed pivots from the root: the tip's count is the chain's)."""
    bad = False
    for l in range(LANES):
        bad |= R[m - 1, _BAD, l] != 0.0
    return bad


@_inline
def _pinv_z(R, i, l):
    """P_i⁻¹ z_i (P⁻¹ symmetric, from its upper triangle, as ``chain_solve.block`` reads it)."""
    p0, p1, p2 = R[i, _C, l], R[i, _C + 1, l], R[i, _C + 2, l]
    p3, p4, p5 = R[i, _C + 3, l], R[i, _C + 4, l], R[i, _C + 5, l]
    z0, z1, z2 = R[i, _FC, l], R[i, _FC + 1, l], R[i, _FC + 2, l]
    return (p0 * z0 + p1 * z1 + p2 * z2, p1 * z0 + p3 * z1 + p4 * z2,
            p2 * z0 + p4 * z1 + p5 * z2)


@_inline
def _joint_forces(R, i, l, f0, f1, f2, g0, g1, g2):
    """Segment i's joint forces applied: + λ_i = f at its proximal end, - λ_{i+1} = g at its
    distal end (``step_rk4``'s accelerations' second sweep); λ_i stored as f_c."""
    R[i, _FC, l], R[i, _FC + 1, l], R[i, _FC + 2, l] = f0, f1, f2
    im = R[i, _IM, l]
    R[i, _ACC, l] += (f0 - g0) * im
    R[i, _ACC + 1, l] += (f1 - g1) * im
    R[i, _ACC + 2, l] += (f2 - g2) * im
    # (-h) × f_c + h × (-f_next) = (f_c + f_next) × h
    t0, t1, t2 = cross_s(f0 + g0, f1 + g1, f2 + g2, R[i, _HV, l], R[i, _HV + 1, l],
                        R[i, _HV + 2, l])
    for a in range(3):
        R[i, _ALPHA + a, l] += (R[i, _IINV + 3 * a, l] * t0 + R[i, _IINV + 3 * a + 1, l] * t1
                                + R[i, _IINV + 3 * a + 2, l] * t2)


@_inline
def _backward(m, R):
    """Tip to root: (1 + 𝓛)ᵀ λ = P⁻¹ z, the joint forces λ into ``_FC`` and each segment's
    applied to its accelerations."""
    for l in range(LANES):              # the tip: no joint beyond it
        f0, f1, f2 = _pinv_z(R, m - 1, l)
        _joint_forces(R, m - 1, l, f0, f1, f2, 0.0, 0.0, 0.0)
    for i in range(m - 2, -1, -1):
        for l in range(LANES):
            f0, f1, f2 = _pinv_z(R, i, l)
            l0, l1, l2 = R[i + 1, _FC, l], R[i + 1, _FC + 1, l], R[i + 1, _FC + 2, l]  # λ_i+1
            f0 -= R[i + 1, _LO, l] * l0 + R[i + 1, _LO + 3, l] * l1 + R[i + 1, _LO + 6, l] * l2
            f1 -= (R[i + 1, _LO + 1, l] * l0 + R[i + 1, _LO + 4, l] * l1
                   + R[i + 1, _LO + 7, l] * l2)
            f2 -= (R[i + 1, _LO + 2, l] * l0 + R[i + 1, _LO + 5, l] * l1
                   + R[i + 1, _LO + 8, l] * l2)
            _joint_forces(R, i, l, f0, f1, f2, l0, l1, l2)


@_inline
def _derivatives(R, i, l):
    """Stage derivatives of segment i: ẋ = v, v̇ = a, ω̇_b = Rᵀ α, q̇ = ½ q ⊗ ω_b."""
    qx, qy, qz, qw = R[i, _QS, l], R[i, _QS + 1, l], R[i, _QS + 2, l], R[i, _QS + 3, l]
    d0, d1, d2, d3 = qmul_s(qx, qy, qz, qw, R[i, _WBS, l], R[i, _WBS + 1, l],
                           R[i, _WBS + 2, l], 0.0)
    e0, e1, e2 = qrot_s(-qx, -qy, -qz, qw, R[i, _ALPHA, l], R[i, _ALPHA + 1, l],
                       R[i, _ALPHA + 2, l])
    return ((R[i, _VS, l], R[i, _VS + 1, l], R[i, _VS + 2, l]),
            (R[i, _ACC, l], R[i, _ACC + 1, l], R[i, _ACC + 2, l]),
            (e0, e1, e2), (0.5 * d0, 0.5 * d1, 0.5 * d2, 0.5 * d3))


@_inline
def _stage_sum(s, weight, total, d):
    """``step_rk4``'s stage sum: d for the first stage, else total + weight·d (a select, not a
    branch: the loop stays vectorisable)."""
    return d if s == 0 else total + weight * d


@_inline
def _next_stage(m, s, weight, c, R):
    """After stage ``s`` (0-2): its derivatives summed into RK4's d₁ + 2 d₂ + 2 d₃ + d₄, and
    the next stage's state at offset ``c`` from the step's start."""
    for i in range(m):
        for l in range(LANES):
            dx, dv, dwb, dq = _derivatives(R, i, l)
            for a in range(3):
                R[i, _SX + a, l] = _stage_sum(s, weight, R[i, _SX + a, l], dx[a])
                R[i, _SV + a, l] = _stage_sum(s, weight, R[i, _SV + a, l], dv[a])
                R[i, _SWB + a, l] = _stage_sum(s, weight, R[i, _SWB + a, l], dwb[a])
            for a in range(4):
                R[i, _SQ + a, l] = _stage_sum(s, weight, R[i, _SQ + a, l], dq[a])
            for a in range(3):
                R[i, _XS + a, l] = R[i, _X + a, l] + c * dx[a]
                R[i, _VS + a, l] = R[i, _V + a, l] + c * dv[a]
                R[i, _WBS + a, l] = R[i, _WB + a, l] + c * dwb[a]
            for a in range(4):
                R[i, _QS + a, l] = R[i, _Q + a, l] + c * dq[a]
            R[i, _WS, l], R[i, _WS + 1, l], R[i, _WS + 2, l] = qrot_s(
                R[i, _QS, l], R[i, _QS + 1, l], R[i, _QS + 2, l], R[i, _QS + 3, l],
                R[i, _WBS, l], R[i, _WBS + 1, l], R[i, _WBS + 2, l])


@_inline
def _finish(m, h, R):
    """The last stage's derivatives summed (weight 1: d added, the same bits as 1·d) and the
    step taken: x, v, ω_b, q advanced by h/6 of the sums, q normalised, ω back in the world
    frame."""
    sixth = h / 6.0
    for i in range(m):
        for l in range(LANES):
            dx, dv, dwb, dq = _derivatives(R, i, l)
            for a in range(3):
                R[i, _X + a, l] = R[i, _X + a, l] + sixth * (R[i, _SX + a, l] + dx[a])
                R[i, _V + a, l] = R[i, _V + a, l] + sixth * (R[i, _SV + a, l] + dv[a])
                R[i, _WB + a, l] = R[i, _WB + a, l] + sixth * (R[i, _SWB + a, l] + dwb[a])
            q0 = R[i, _Q, l] + sixth * (R[i, _SQ, l] + dq[0])
            q1 = R[i, _Q + 1, l] + sixth * (R[i, _SQ + 1, l] + dq[1])
            q2 = R[i, _Q + 2, l] + sixth * (R[i, _SQ + 2, l] + dq[2])
            q3 = R[i, _Q + 3, l] + sixth * (R[i, _SQ + 3, l] + dq[3])
            r = 1.0 / sqrt_ieee(q0 ** 2 + q1 ** 2 + q2 ** 2 + q3 ** 2)
            q0, q1, q2, q3 = q0 * r, q1 * r, q2 * r, q3 * r
            R[i, _Q, l], R[i, _Q + 1, l], R[i, _Q + 2, l], R[i, _Q + 3, l] = q0, q1, q2, q3
            R[i, _W, l], R[i, _W + 1, l], R[i, _W + 2, l] = qrot_s(
                q0, q1, q2, q3, R[i, _WB, l], R[i, _WB + 1, l], R[i, _WB + 2, l])


@_inline
def _project_segment(R, i, l, p0, p1, p2, u0, u1, u2):
    """Segment i's centre on its proximal joint at p (velocity u); its distal joint's kept."""
    qx, qy, qz, qw = R[i, _Q, l], R[i, _Q + 1, l], R[i, _Q + 2, l], R[i, _Q + 3, l]
    e0, e1, e2 = qaxis_x_s(qx, qy, qz, qw)
    hl = R[i, _HALF, l]
    h0, h1, h2 = hl * e0, hl * e1, hl * e2
    x0, x1, x2 = p0 + h0, p1 + h1, p2 + h2
    R[i, _X, l], R[i, _X + 1, l], R[i, _X + 2, l] = x0, x1, x2
    R[i, _PE, l], R[i, _PE + 1, l], R[i, _PE + 2, l] = x0 + h0, x1 + h1, x2 + h2
    c0, c1, c2 = cross_s(R[i, _W, l], R[i, _W + 1, l], R[i, _W + 2, l], h0, h1, h2)
    v0, v1, v2 = u0 + c0, u1 + c1, u2 + c2
    R[i, _V, l], R[i, _V + 1, l], R[i, _V + 2, l] = v0, v1, v2
    R[i, _UE, l], R[i, _UE + 1, l], R[i, _UE + 2, l] = v0 + c0, v1 + c1, v2 + c2


@_inline
def _project(m, row, R, E):
    """Centres rebuilt so every joint closes exactly from the anchor outward, and the centre
    velocities from the anchor point's velocity and ω (``step``'s projection for RK4)."""
    for l in range(LANES):
        _project_segment(R, 0, l, E[row, _AX, l], E[row, _AX + 1, l], E[row, _AX + 2, l],
                         E[row, _AV, l], E[row, _AV + 1, l], E[row, _AV + 2, l])
    for i in range(1, m):
        for l in range(LANES):
            _project_segment(R, i, l, R[i - 1, _PE, l], R[i - 1, _PE + 1, l],
                             R[i - 1, _PE + 2, l], R[i - 1, _UE, l], R[i - 1, _UE + 1, l],
                             R[i - 1, _UE + 2, l])


# -- the call ----------------------------------------------------------------------------------
@_inline
def _block_step(M, k, h, R, E, S):
    """Step ``k`` of the table for one block (``step_rk4.rk4``, then ``step``'s projection), its
    record ``R``, anchors ``E`` and stiffness scratch ``S`` given. Returns ``OK`` or
    ``JOINT_SOLVE_FAILED`` (some lane's A was not positive definite)."""
    m = R.shape[0]
    _start(m, R)
    for s in range(4):
        row = 2 * k + (0 if s == 0 else (1 if s < 3 else 2))
        _applied(m, row, R, E, S, M.wind[0], M.wind[1], M.wind[2], M.explicit_damping,
                 M.stiffness_on, M.drag_on, M.external_on)
        _forward(m, row, R, E)
        if _failed(m, R):
            return JOINT_SOLVE_FAILED
        _backward(m, R)
        if s < 3:
            _next_stage(m, s, 1.0 if s == 0 else 2.0, 0.5 * h if s < 2 else h, R)
        else:
            _finish(m, h, R)
    if M.projection:
        _project(m, 2 * k + 2, R, E)
    return OK


@_inline
def _load_block(M, A, b, n_chains, m, ext_F, ext_T, R, E):
    """Block ``b``'s model, external forces and anchors into its record and anchor table."""
    _load_model(M, b, n_chains, m, R)
    if M.external_on:
        _gather(ext_F, b, n_chains, m, R, _EXTF)
        _gather(ext_T, b, n_chains, m, R, _EXTT)
    _gather_anchors(A, 0, b, n_chains, E)


@_inline
def _gather_state(b, n_chains, m, x, q, v, w, R):
    _gather(x, b, n_chains, m, R, _X)
    _gather(q, b, n_chains, m, R, _Q)
    _gather(v, b, n_chains, m, R, _V)
    _gather(w, b, n_chains, m, R, _W)


@_inline
def _scatter_state(R, b, n_chains, m, x, q, v, w, f_c):
    _scatter(R, _X, b, n_chains, m, x)
    _scatter(R, _Q, b, n_chains, m, q)
    _scatter(R, _V, b, n_chains, m, v)
    _scatter(R, _W, b, n_chains, m, w)
    _scatter(R, _FC, b, n_chains, m, f_c)


@_inline
def _n_chains(M):
    n_chains = 0
    for i in range(M.is_first.shape[0]):
        n_chains += 1 if M.is_first[i] else 0
    return n_chains


@_jit
def advance_lanes(M, A, n_steps, h, x, q, v, w, ext_F, ext_T, f_c):
    """``step.advance`` for a crowd that ``supports`` and ``crowd_layout`` allow (the same
    arguments, results bit for bit and status): the chains in blocks of ``LANES``, each block
    through all the steps of the call before the next (its record stays in the cache). The
    record and anchors are allocated here, where the loops are (``_block_step`` is inlined):
    that is what lets LLVM see they are distinct from the arguments."""
    if n_steps <= 0:
        return OK
    n_chains = _n_chains(M)
    m = x.shape[0] // n_chains
    R = np.zeros((m, _NF, LANES))
    E = np.empty((A.position.shape[0], _NE, LANES))
    S = stiffness_scratch(m)
    for b in range((n_chains + LANES - 1) // LANES):
        _load_block(M, A, b, n_chains, m, ext_F, ext_T, R, E)
        _gather_state(b, n_chains, m, x, q, v, w, R)
        for k in range(n_steps):
            status = _block_step(M, k, h, R, E, S)
            if status != OK:
                return status
        _scatter_state(R, b, n_chains, m, x, q, v, w, f_c)
    return OK


@_inline
def crowd_records(M, n, in_lanes):
    """One block's record, anchor rows and stiffness scratch, ``(m, _NF, LANES)`` (m
    segments per chain of the ``n``), ``(3, _NE, LANES)`` and ``stiffness_scratch(m)``, and
    every block's model fields (``_model_blocks``), for ``step_blocks`` (empty unless
    ``in_lanes``). Inline: the caller that allocates them is the one whose loops use them
    (see ``advance_lanes``)."""
    m = n // _n_chains(M) if in_lanes else 0
    R = np.zeros((m, _NF, LANES))
    return R, np.empty((3, _NE, LANES)), stiffness_scratch(m), _model_blocks(M, m, R)


@_inline
def _model_blocks(M, m, R):
    """The model fields of the record (``_HALF`` on, its last) of every block,
    ``(blocks, m, _NF - _HALF, LANES)``, loaded once for the steps of a call (``R``: a record
    to load them in): ``step_blocks`` copies a block's instead of loading it from the
    ``StepModel``'s arrays at every step."""
    if m == 0:
        return np.empty((0, 0, _NF - _HALF, LANES))
    n_chains = _n_chains(M)
    n_blocks = (n_chains + LANES - 1) // LANES
    MB = np.empty((n_blocks, m, _NF - _HALF, LANES))
    for b in range(n_blocks):
        _load_model(M, b, n_chains, m, R)
        for i in range(m):
            for f in range(_NF - _HALF):
                for l in range(LANES):
                    MB[b, i, f, l] = R[i, _HALF + f, l]
    return MB


@_inline
def step_blocks(M, A, k, h, x, q, v, w, ext_F, ext_T, f_c, R, E, S, MB):
    """Step ``k`` of the table ``A`` for every chain, block by block, in one block's record
    ``R``, anchor rows ``E`` and stiffness scratch ``S`` (``crowd_records``): each
    block's model (a copy of its ``MB``), anchors of the step and state are loaded, the step
    taken and the state scattered back, since the caller changes it between steps
    (contacts). A record kept per block across the steps would be slower: the records of a
    crowd outgrow the cache the contact stage needs between two steps. The same bits as
    ``step.advance``'s step ``k``."""
    m = R.shape[0]
    n_chains = x.shape[0] // m          # (every chain has m segments: ``crowd_layout``)
    for b in range((n_chains + LANES - 1) // LANES):
        for i in range(m):
            for f in range(_NF - _HALF):
                for l in range(LANES):
                    R[i, _HALF + f, l] = MB[b, i, f, l]
        if M.external_on:
            _gather(ext_F, b, n_chains, m, R, _EXTF)
            _gather(ext_T, b, n_chains, m, R, _EXTT)
        _gather_anchors(A, 2 * k, b, n_chains, E)
        _gather_state(b, n_chains, m, x, q, v, w, R)
        status = _block_step(M, 0, h, R, E, S)
        if status != OK:
            return status
        _scatter_state(R, b, n_chains, m, x, q, v, w, f_c)
    return OK


# -- dispatch ----------------------------------------------------------------------------------
def crowd_layout(model):
    """``(chains, segments per chain)`` if ``model``'s structure suits the lanes (at least
    ``MIN_CHAINS`` chains, all of one segment count), else None. Colliders and joint limits
    do not matter: ``step_unilateral`` resolves them between the lanes' steps. The structure
    of a ``Model`` never changes: the simulator asks once."""
    counts = np.asarray(model.chain_end) - np.asarray(model.chain_start)
    if model.n_chains < MIN_CHAINS or np.any(counts != counts[0]):
        return None
    return int(model.n_chains), int(counts[0])


def supports(M):
    """Whether the lanes kernel runs the ``StepModel`` ``M``'s switches: RK4, axisymmetric
    segments, no implicit damping, no Baumgarte terms (the rest: gravity, explicit damping,
    bending stiffness, drag, external forces, projection on or off, are covered)."""
    return bool(M.integrator == RK4 and M.axisymmetric and not M.implicit_damping
                and M.baumgarte_stiffness == 0.0 and M.baumgarte_damping == 0.0)


def kernel_for(M, layout):
    """The compiled step for the ``StepModel`` ``M`` of a model of ``crowd_layout``
    ``layout``: ``advance_lanes`` if it runs it, else ``step.advance_rk4`` (RK4) or
    ``step.advance`` (same arguments, same results)."""
    if layout is not None and supports(M):
        return advance_lanes
    return step.advance_rk4 if M.integrator == RK4 else step.advance


def advance(M, A, n_steps, h, x, q, v, w, ext_F, ext_T, f_c, layout):
    """``step.advance`` through ``kernel_for(M, layout)``."""
    return kernel_for(M, layout)(M, A, n_steps, h, x, q, v, w, ext_F, ext_T, f_c)
