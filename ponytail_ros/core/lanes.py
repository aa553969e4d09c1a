"""The RK4 step of a crowd, chains side by side in SIMD lanes: bit for bit ``step.advance``.

A crowd (many chains of one segment count) is stepped ``LANES`` chains at a time: every
per-segment quantity of a block of chains is stored ``(segment, component, lane)``, and every
loop that does arithmetic runs innermost over the lanes, with a constant trip count, no
branches and no calls, so that LLVM vectorises it across chains (``<4 x double>``). Each lane
does exactly the floating-point operations of ``step.advance`` on its chain, in the same order:
IEEE arithmetic is the same in a SIMD lane as in a scalar register (no ``fastmath``, no FMA
contraction), so the results are identical bit for bit, which ``test/test_lanes.py`` checks.

What makes the loops vectorise (checked with ``inspect_asm``; see ``vector_report``):
  * the working arrays are allocated inside the kernel: LLVM then knows that they do not
    alias, where arrays passed in as arguments might (it gives up on a loop that stores to
    one array and loads from another it cannot tell apart);
  * ``sqrt`` is LLVM's intrinsic (``_sqrt``), not numba's call to libm's ``sqrt`` (a call
    stops the vectoriser; both are IEEE's correctly rounded square root, so the same bits);
  * ``error_model='numpy'``: a division is then a plain ``fdiv``, not a test for zero that
    raises (only a blown-up chain divides by zero: its status or the guard reports it);
  * what differs between the first joint and the others (the anchor as parent, the first
    pivot), or between the tip and the others, is chosen outside the lane loop: two loops.

Covered (the rest goes to ``step.advance``, see ``supports``): RK4, axisymmetric segments
(the gyroscopic term ω × Iω), gravity, explicit joint damping, linear and quadratic drag with
wind, external forces and torques, the O(n) joint solve (``chain_solve``'s block LDLᵀ, as
``step._accelerations`` does it), the projection (positions and velocities rebuilt from the
anchor), every chain of the same segment count. The state is transposed into the lane layout
once per call and back at its end; a last, partial block is filled with copies of its last
chain (their results discarded).

Frames and units: world frame, SI, as ``step``: ``x`` ``(n, 3)`` centres (m), ``q`` ``(n, 4)``
(x, y, z, w) body to world, ``v`` ``(n, 3)`` (m/s), ``w`` ``(n, 3)`` ω in the world frame
(rad/s); ``f_c`` ``(n, 3)`` the joint forces on the children at the last stage (N).
"""
import numba as nb
import numpy as np
from llvmlite import ir as llvm_ir
from numba.core import types
from numba.extending import intrinsic

from . import step
from .chain_solve import invert_pivot, pivot
from .kernel_cache import ensure_fresh
from .step import (JOINT_SOLVE_FAILED, OK, RK4, _G_axisymmetric, _cross,
                   _inv_inertia_axisymmetric, _qmul, _qrot)

ensure_fresh()

__all__ = ['LANES', 'MIN_CHAINS', 'advance', 'advance_lanes', 'crowd_layout', 'supports',
           'kernel_for']

# Chains per block. A compile-time constant: the lane loops' trip count, which LLVM splits
# into whole vectors. Chosen by measurement (``bench.step_cost``; the module docstring of
# ``bench.step_cost`` gives the figures).
LANES = 16
# Fewer chains than this run through ``step.advance``: a block padded with more copies than
# chains costs more than the chains one after another.
MIN_CHAINS = 4

_jit = nb.njit(cache=True, error_model='numpy')
_inline = nb.njit(cache=True, error_model='numpy', inline='always')

# The per-lane model, ``(n, _NP, LANES)``: the ``StepModel`` arrays a lane reads, and the
# constants the general step recomputes from them (the same expressions, so the same bits).
(_HALF, _IM, _I0, _I1, _II0, _II1, _FG0, _FG1, _FG2, _DAMP, _DL, _DQ, _LEN, _KT,
 _NP) = range(15)


@intrinsic
def _sqrt(typingctx, x):
    """IEEE square root as LLVM's ``llvm.sqrt.f64``: vectorisable, unlike numba's libm call
    (which returns the same, correctly rounded, value)."""
    sig = types.float64(types.float64)

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic('llvm.sqrt', [llvm_ir.DoubleType()])
        return builder.call(fn, args)
    return sig, codegen


# -- layout: the crowd into blocks of lanes and back -------------------------------------------
@_inline
def _chain_of_lane(b, l, n_chains):
    """The chain lane ``l`` of block ``b`` carries (a copy of the last chain past the end)."""
    return min(b * LANES + l, n_chains - 1)


@_inline
def _load_model(M, b, n_chains, m, P):
    """Block ``b``'s per-lane model ``P`` ``(m, _NP, LANES)`` from the ``StepModel`` ``M``."""
    for l in range(LANES):
        s = _chain_of_lane(b, l, n_chains) * m
        for i in range(m):
            j = s + i
            P[i, _HALF, l] = M.half[j]
            P[i, _IM, l] = M.inv_mass[j]
            P[i, _I0, l] = M.inertia[j, 0]
            P[i, _I1, l] = M.inertia[j, 1]
            P[i, _II0, l] = M.inv_inertia[j, 0]
            P[i, _II1, l] = M.inv_inertia[j, 1]
            P[i, _FG0, l] = M.mass[j] * M.gravity[0] if M.gravity_on else 0.0
            P[i, _FG1, l] = M.mass[j] * M.gravity[1] if M.gravity_on else 0.0
            P[i, _FG2, l] = M.mass[j] * M.gravity[2] if M.gravity_on else 0.0
            P[i, _DAMP, l] = M.damping[j]
            P[i, _DL, l] = M.drag_linear[j]
            P[i, _DQ, l] = M.drag_quadratic[j]
            P[i, _LEN, l] = M.length[j]
            P[i, _KT, l] = M.drag_linear[j] * (M.length[j] ** 3 / 12.0)


@_inline
def _gather(src, b, n_chains, m, dst):
    """Block ``b``'s rows of ``src`` ``(n, k)`` into ``dst`` ``(m, k, LANES)``."""
    for l in range(LANES):
        s = _chain_of_lane(b, l, n_chains) * m
        for i in range(m):
            for a in range(src.shape[1]):
                dst[i, a, l] = src[s + i, a]


@_inline
def _scatter(src, b, n_chains, m, dst):
    """``src`` ``(m, k, LANES)`` back into block ``b``'s rows of ``dst`` (real chains only)."""
    for l in range(min(LANES, n_chains - b * LANES)):
        s = (b * LANES + l) * m
        for i in range(m):
            for a in range(dst.shape[1]):
                dst[s + i, a] = src[i, a, l]


@_inline
def _gather_anchor(src, b, n_chains, dst):
    """Block ``b``'s columns of an anchor table field ``(S, C, 3)`` into ``(S, 3, LANES)``."""
    for r in range(src.shape[0]):
        for l in range(LANES):
            c = _chain_of_lane(b, l, n_chains)
            for a in range(3):
                dst[r, a, l] = src[r, c, a]


# -- the stages, each over all segments of a block ---------------------------------------------
@_inline
def _start(m, x, q, v, w, wb, w_s, xs, qs, vs, wbs):
    """The step's first stage: ω in the body frame (``wb``), the stage state = the state."""
    for i in range(m):
        for l in range(LANES):
            qx, qy, qz, qw = q[i, 0, l], q[i, 1, l], q[i, 2, l], q[i, 3, l]
            b0, b1, b2 = _qrot(-qx, -qy, -qz, qw, w[i, 0, l], w[i, 1, l], w[i, 2, l])
            wb[i, 0, l], wb[i, 1, l], wb[i, 2, l] = b0, b1, b2
            xs[i, 0, l], xs[i, 1, l], xs[i, 2, l] = x[i, 0, l], x[i, 1, l], x[i, 2, l]
            vs[i, 0, l], vs[i, 1, l], vs[i, 2, l] = v[i, 0, l], v[i, 1, l], v[i, 2, l]
            wbs[i, 0, l], wbs[i, 1, l], wbs[i, 2, l] = b0, b1, b2
            qs[i, 0, l], qs[i, 1, l], qs[i, 2, l], qs[i, 3, l] = qx, qy, qz, qw
            w_s[i, 0, l], w_s[i, 1, l], w_s[i, 2, l] = _qrot(qx, qy, qz, qw, b0, b1, b2)


@_inline
def _applied(m, row, P, qs, vs, w_s, ext_F, ext_T, anchor_w, wind0, wind1, wind2,
             explicit_damping, drag_on, external_on, F, T):
    """Applied forces ``F`` and torques ``T`` (N, N·m, world), ``step._applied``'s terms in its
    order: gravity, joint damping (τ on the child, -τ on the parent), drag, external."""
    for i in range(m):
        for l in range(LANES):
            F[i, 0, l], F[i, 1, l], F[i, 2, l] = P[i, _FG0, l], P[i, _FG1, l], P[i, _FG2, l]
            T[i, 0, l], T[i, 1, l], T[i, 2, l] = 0.0, 0.0, 0.0
    if explicit_damping:
        for l in range(LANES):          # the first joint: the anchor body is the parent
            k = P[0, _DAMP, l]
            T[0, 0, l] += 0.0 - k * (w_s[0, 0, l] - anchor_w[row, 0, l])
            T[0, 1, l] += 0.0 - k * (w_s[0, 1, l] - anchor_w[row, 1, l])
            T[0, 2, l] += 0.0 - k * (w_s[0, 2, l] - anchor_w[row, 2, l])
        for i in range(1, m):
            for l in range(LANES):
                k = P[i, _DAMP, l]
                tau0 = 0.0 - k * (w_s[i, 0, l] - w_s[i - 1, 0, l])
                tau1 = 0.0 - k * (w_s[i, 1, l] - w_s[i - 1, 1, l])
                tau2 = 0.0 - k * (w_s[i, 2, l] - w_s[i - 1, 2, l])
                T[i, 0, l] += tau0
                T[i, 1, l] += tau1
                T[i, 2, l] += tau2
                T[i - 1, 0, l] -= tau0
                T[i - 1, 1, l] -= tau1
                T[i - 1, 2, l] -= tau2
    if drag_on:
        for i in range(m):
            for l in range(LANES):
                u0 = vs[i, 0, l] - wind0
                u1 = vs[i, 1, l] - wind1
                u2 = vs[i, 2, l] - wind2
                speed = _sqrt(u0 * u0 + u1 * u1 + u2 * u2)
                c1 = P[i, _DL, l]
                k = (c1 + P[i, _DQ, l] * speed) * P[i, _LEN, l]
                F[i, 0, l] -= k * u0
                F[i, 1, l] -= k * u1
                F[i, 2, l] -= k * u2
                x, y, z, w = qs[i, 0, l], qs[i, 1, l], qs[i, 2, l], qs[i, 3, l]
                e0 = 1.0 - 2.0 * (y * y + z * z)
                e1 = 2.0 * (x * y + w * z)
                e2 = 2.0 * (x * z - w * y)
                w0, w1, w2 = w_s[i, 0, l], w_s[i, 1, l], w_s[i, 2, l]
                wa = w0 * e0 + w1 * e1 + w2 * e2
                kt = P[i, _KT, l]
                T[i, 0, l] -= kt * (w0 - wa * e0)
                T[i, 1, l] -= kt * (w1 - wa * e1)
                T[i, 2, l] -= kt * (w2 - wa * e2)
    if external_on:
        for i in range(m):
            for a in range(3):
                for l in range(LANES):
                    F[i, a, l] += ext_F[i, a, l]
                    T[i, a, l] += ext_T[i, a, l]


@_inline
def _free(qx, qy, qz, qw, w0, w1, w2, T0, T1, T2, F0, F1, F2, I0, I1, ia, ip, hl, im):
    """One segment's part of ``step._accelerations``' root-to-tip sweep, scalars only: its axis
    e, world I⁻¹ ``X`` (row-major), half-vector h = (l/2) e, free accelerations α (rad/s²) and
    a (m/s², without f_c), the tangential + centripetal acceleration t = α × h + ω × (ω × h)
    of its distal point relative to its centre, and its G = [h]× I⁻¹ [h]×."""
    e0 = 1.0 - 2.0 * (qy * qy + qz * qz)
    e1 = 2.0 * (qx * qy + qw * qz)
    e2 = 2.0 * (qx * qz - qw * qy)
    X = _inv_inertia_axisymmetric(e0, e1, e2, ia, ip)
    h0, h1, h2 = hl * e0, hl * e1, hl * e2
    s = (I0 - I1) * (e0 * w0 + e1 * w1 + e2 * w2)            # ω × Iω, axisymmetric
    c0, c1, c2 = _cross(w0, w1, w2, e0, e1, e2)
    y0, y1, y2 = s * c0, s * c1, s * c2
    v0, v1, v2 = T0 - y0, T1 - y1, T2 - y2
    a0 = X[0] * v0 + X[1] * v1 + X[2] * v2
    a1 = X[3] * v0 + X[4] * v1 + X[5] * v2
    a2 = X[6] * v0 + X[7] * v1 + X[8] * v2
    ac0, ac1, ac2 = F0 * im, F1 * im, F2 * im
    c0, c1, c2 = _cross(a0, a1, a2, h0, h1, h2)
    u0, u1, u2 = _cross(w0, w1, w2, h0, h1, h2)              # ω × h
    d0, d1, d2 = _cross(w0, w1, w2, u0, u1, u2)
    t = (c0 + d0, c1 + d1, c2 + d2)
    return X, (h0, h1, h2), (a0, a1, a2), (ac0, ac1, ac2), t, _G_axisymmetric(h0, h1, h2, ip)


@_inline
def _store_free(i, l, X, h, a, ac, g, Iinv, hv, alpha, acc, G):
    for j in range(9):
        Iinv[i, j, l] = X[j]
    for j in range(6):
        G[i, j, l] = g[j]
    for j in range(3):
        hv[i, j, l] = h[j]
        alpha[i, j, l] = a[j]
        acc[i, j, l] = ac[j]


@_inline
def _forward(m, row, P, qs, w_s, F, T, anchor_acc, Iinv, hv, alpha, acc, G, C, Lo, z, pa,
             bad):
    """Root to tip (``step._accelerations``' first sweep): per segment its free motion, joint
    i's right-hand side (parent point minus child point acceleration), joint i's row of
    A = J M⁻¹ Jᵀ factorised (``C`` = P⁻¹ upper triangle, ``Lo`` = 𝓛) and the right-hand side
    forward-substituted into ``z``. ``bad[l]`` counts the pivots of lane l that were not
    positive definite (its chain's joint solve failed)."""
    for i in range(m):
        if i == 0:
            for l in range(LANES):
                X, h, a, ac, t, gi = _free(
                    qs[i, 0, l], qs[i, 1, l], qs[i, 2, l], qs[i, 3, l], w_s[i, 0, l],
                    w_s[i, 1, l], w_s[i, 2, l], T[i, 0, l], T[i, 1, l], T[i, 2, l],
                    F[i, 0, l], F[i, 1, l], F[i, 2, l], P[i, _I0, l], P[i, _I1, l],
                    P[i, _II0, l], P[i, _II1, l], P[i, _HALF, l], P[i, _IM, l])
                _store_free(i, l, X, h, a, ac, gi, Iinv, hv, alpha, acc, G)
                for j in range(3):
                    z[i, j, l] = anchor_acc[row, j, l] - (ac[j] - t[j])
                    pa[i, j, l] = ac[j] + t[j]
                im = P[i, _IM, l]
                g00, g01, g02, g11, g12, g22 = gi
                ok, pinv = invert_pivot((im - g00, -g01, -g02, im - g11, -g12, im - g22))
                for j in range(6):
                    C[i, j, l] = pinv[j]
                for j in range(9):
                    Lo[i, j, l] = 0.0
                bad[l] += 0.0 if ok else 1.0
        else:
            for l in range(LANES):
                X, h, a, ac, t, gi = _free(
                    qs[i, 0, l], qs[i, 1, l], qs[i, 2, l], qs[i, 3, l], w_s[i, 0, l],
                    w_s[i, 1, l], w_s[i, 2, l], T[i, 0, l], T[i, 1, l], T[i, 2, l],
                    F[i, 0, l], F[i, 1, l], F[i, 2, l], P[i, _I0, l], P[i, _I1, l],
                    P[i, _II0, l], P[i, _II1, l], P[i, _HALF, l], P[i, _IM, l])
                _store_free(i, l, X, h, a, ac, gi, Iinv, hv, alpha, acc, G)
                r0 = pa[i - 1, 0, l] - (ac[0] - t[0])
                r1 = pa[i - 1, 1, l] - (ac[1] - t[1])
                r2 = pa[i - 1, 2, l] - (ac[2] - t[2])
                for j in range(3):
                    pa[i, j, l] = ac[j] + t[j]
                im, imp = P[i, _IM, l], P[i - 1, _IM, l]
                g00, g01, g02, g11, g12, g22 = gi
                p00, p01, p02, p11, p12, p22 = (G[i - 1, 0, l], G[i - 1, 1, l], G[i - 1, 2, l],
                                                G[i - 1, 3, l], G[i - 1, 4, l], G[i - 1, 5, l])
                s = im + imp
                d = (s - g00 - p00, -g01 - p01, -g02 - p02, s - g11 - p11, -g12 - p12,
                     s - g22 - p22)
                lb = (-imp - p00, -p01, -p02, -p01, -imp - p11, -p12, -p02, -p12, -imp - p22)
                pp = (C[i - 1, 0, l], C[i - 1, 1, l], C[i - 1, 2, l], C[i - 1, 3, l],
                      C[i - 1, 4, l], C[i - 1, 5, l])
                ok, lo, pinv = pivot(d, lb, pp)
                for j in range(6):
                    C[i, j, l] = pinv[j]
                for j in range(9):
                    Lo[i, j, l] = lo[j]
                bad[l] += 0.0 if ok else 1.0
                z0, z1, z2 = z[i - 1, 0, l], z[i - 1, 1, l], z[i - 1, 2, l]
                r0 -= lo[0] * z0 + lo[1] * z1 + lo[2] * z2
                r1 -= lo[3] * z0 + lo[4] * z1 + lo[5] * z2
                r2 -= lo[6] * z0 + lo[7] * z1 + lo[8] * z2
                z[i, 0, l], z[i, 1, l], z[i, 2, l] = r0, r1, r2


@_inline
def _back_segment(i, l, f0, f1, f2, g0, g1, g2, P, Iinv, hv, acc, alpha, f_c):
    """Segment i's joint forces applied: + λ_i = f at its proximal end, - λ_{i+1} = g at its
    distal end (``step._accelerations``' second sweep)."""
    f_c[i, 0, l], f_c[i, 1, l], f_c[i, 2, l] = f0, f1, f2
    im = P[i, _IM, l]
    acc[i, 0, l] += (f0 - g0) * im
    acc[i, 1, l] += (f1 - g1) * im
    acc[i, 2, l] += (f2 - g2) * im
    # (-h) × f_c + h × (-f_next) = (f_c + f_next) × h
    t0, t1, t2 = _cross(f0 + g0, f1 + g1, f2 + g2, hv[i, 0, l], hv[i, 1, l], hv[i, 2, l])
    alpha[i, 0, l] += Iinv[i, 0, l] * t0 + Iinv[i, 1, l] * t1 + Iinv[i, 2, l] * t2
    alpha[i, 1, l] += Iinv[i, 3, l] * t0 + Iinv[i, 4, l] * t1 + Iinv[i, 5, l] * t2
    alpha[i, 2, l] += Iinv[i, 6, l] * t0 + Iinv[i, 7, l] * t1 + Iinv[i, 8, l] * t2


@_inline
def _pinv_z(i, l, C, z):
    """P_i⁻¹ z_i (P⁻¹ symmetric, from its upper triangle, as ``step._block`` reads it)."""
    p0, p1, p2, p3, p4, p5 = (C[i, 0, l], C[i, 1, l], C[i, 2, l], C[i, 3, l], C[i, 4, l],
                              C[i, 5, l])
    z0, z1, z2 = z[i, 0, l], z[i, 1, l], z[i, 2, l]
    return (p0 * z0 + p1 * z1 + p2 * z2, p1 * z0 + p3 * z1 + p4 * z2,
            p2 * z0 + p4 * z1 + p5 * z2)


@_inline
def _backward(m, P, Iinv, hv, C, Lo, z, acc, alpha, f_c):
    """Tip to root: (1 + 𝓛)ᵀ λ = P⁻¹ z, the joint forces λ into ``f_c`` and each segment's
    applied to its accelerations."""
    i = m - 1
    for l in range(LANES):              # the tip: no joint beyond it
        f0, f1, f2 = _pinv_z(i, l, C, z)
        _back_segment(i, l, f0, f1, f2, 0.0, 0.0, 0.0, P, Iinv, hv, acc, alpha, f_c)
    for i in range(m - 2, -1, -1):
        for l in range(LANES):
            f0, f1, f2 = _pinv_z(i, l, C, z)
            l0, l1, l2 = f_c[i + 1, 0, l], f_c[i + 1, 1, l], f_c[i + 1, 2, l]    # λ_{i+1}
            f0 -= Lo[i + 1, 0, l] * l0 + Lo[i + 1, 3, l] * l1 + Lo[i + 1, 6, l] * l2
            f1 -= Lo[i + 1, 1, l] * l0 + Lo[i + 1, 4, l] * l1 + Lo[i + 1, 7, l] * l2
            f2 -= Lo[i + 1, 2, l] * l0 + Lo[i + 1, 5, l] * l1 + Lo[i + 1, 8, l] * l2
            _back_segment(i, l, f0, f1, f2, l0, l1, l2, P, Iinv, hv, acc, alpha, f_c)


@_inline
def _stage_sum(s, weight, total, d):
    """RK4's d₁ + 2 d₂ + 2 d₃ + d₄, summed as the stage derivatives ``d`` come
    (``step._rk4_sum``)."""
    return d if s == 0 else total + weight * d


@_inline
def _derivatives(i, l, qs, wbs, vs, acc, alpha):
    """Stage derivatives of segment i: ẋ = v, v̇ = a, ω̇_b = Rᵀ α, q̇ = ½ q ⊗ ω_b."""
    qx, qy, qz, qw = qs[i, 0, l], qs[i, 1, l], qs[i, 2, l], qs[i, 3, l]
    d0, d1, d2, d3 = _qmul(qx, qy, qz, qw, wbs[i, 0, l], wbs[i, 1, l], wbs[i, 2, l], 0.0)
    e0, e1, e2 = _qrot(-qx, -qy, -qz, qw, alpha[i, 0, l], alpha[i, 1, l], alpha[i, 2, l])
    return ((vs[i, 0, l], vs[i, 1, l], vs[i, 2, l]), (acc[i, 0, l], acc[i, 1, l], acc[i, 2, l]),
            (e0, e1, e2), (0.5 * d0, 0.5 * d1, 0.5 * d2, 0.5 * d3))


@_inline
def _next_stage(m, s, weight, c, x, q, v, wb, qs, wbs, vs, xs, w_s, acc, alpha, sx, sv, swb,
                sq):
    """Stages 1-3: the stage derivatives summed, and the next stage's state at offset ``c``."""
    for i in range(m):
        for l in range(LANES):
            dx, dv, dwb, dq = _derivatives(i, l, qs, wbs, vs, acc, alpha)
            for a in range(3):
                sx[i, a, l] = _stage_sum(s, weight, sx[i, a, l], dx[a])
                sv[i, a, l] = _stage_sum(s, weight, sv[i, a, l], dv[a])
                swb[i, a, l] = _stage_sum(s, weight, swb[i, a, l], dwb[a])
            for a in range(4):
                sq[i, a, l] = _stage_sum(s, weight, sq[i, a, l], dq[a])
            for a in range(3):
                xs[i, a, l] = x[i, a, l] + c * dx[a]
                vs[i, a, l] = v[i, a, l] + c * dv[a]
                wbs[i, a, l] = wb[i, a, l] + c * dwb[a]
            for a in range(4):
                qs[i, a, l] = q[i, a, l] + c * dq[a]
            w_s[i, 0, l], w_s[i, 1, l], w_s[i, 2, l] = _qrot(
                qs[i, 0, l], qs[i, 1, l], qs[i, 2, l], qs[i, 3, l],
                wbs[i, 0, l], wbs[i, 1, l], wbs[i, 2, l])


@_inline
def _finish(m, h, x, q, v, w, wb, qs, wbs, vs, acc, alpha, sx, sv, swb, sq):
    """The last stage's derivatives summed and the step taken: x, v, ω_b, q advanced by h/6 of
    the sums, q normalised, ω back in the world frame."""
    sixth = h / 6.0
    for i in range(m):
        for l in range(LANES):
            dx, dv, dwb, dq = _derivatives(i, l, qs, wbs, vs, acc, alpha)
            for a in range(3):
                x[i, a, l] = x[i, a, l] + sixth * (sx[i, a, l] + dx[a])
                v[i, a, l] = v[i, a, l] + sixth * (sv[i, a, l] + dv[a])
                wb[i, a, l] = wb[i, a, l] + sixth * (swb[i, a, l] + dwb[a])
            for a in range(4):
                q[i, a, l] = q[i, a, l] + sixth * (sq[i, a, l] + dq[a])
            r = 1.0 / _sqrt(q[i, 0, l] ** 2 + q[i, 1, l] ** 2 + q[i, 2, l] ** 2
                            + q[i, 3, l] ** 2)
            q[i, 0, l] *= r
            q[i, 1, l] *= r
            q[i, 2, l] *= r
            q[i, 3, l] *= r
            w[i, 0, l], w[i, 1, l], w[i, 2, l] = _qrot(q[i, 0, l], q[i, 1, l], q[i, 2, l],
                                                       q[i, 3, l], wb[i, 0, l], wb[i, 1, l],
                                                       wb[i, 2, l])


@_inline
def _project(m, row, P, x, q, v, w, anchor_x, anchor_v, pc, uc):
    """Centres rebuilt so every joint closes exactly from the anchor outward, and the centre
    velocities from the anchor point's velocity and ω (``step._project`` for RK4); ``pc``,
    ``uc`` ``(3, LANES)``: the position and velocity of the joint reached so far."""
    for l in range(LANES):
        for a in range(3):
            pc[a, l] = anchor_x[row, a, l]
            uc[a, l] = anchor_v[row, a, l]
    for i in range(m):
        for l in range(LANES):
            qx, qy, qz, qw = q[i, 0, l], q[i, 1, l], q[i, 2, l], q[i, 3, l]
            hl = P[i, _HALF, l]
            h0 = hl * (1.0 - 2.0 * (qy * qy + qz * qz))
            h1 = hl * (2.0 * (qx * qy + qw * qz))
            h2 = hl * (2.0 * (qx * qz - qw * qy))
            x0, x1, x2 = pc[0, l] + h0, pc[1, l] + h1, pc[2, l] + h2
            x[i, 0, l], x[i, 1, l], x[i, 2, l] = x0, x1, x2
            pc[0, l], pc[1, l], pc[2, l] = x0 + h0, x1 + h1, x2 + h2
            c0, c1, c2 = _cross(w[i, 0, l], w[i, 1, l], w[i, 2, l], h0, h1, h2)
            v0, v1, v2 = uc[0, l] + c0, uc[1, l] + c1, uc[2, l] + c2
            v[i, 0, l], v[i, 1, l], v[i, 2, l] = v0, v1, v2
            uc[0, l], uc[1, l], uc[2, l] = v0 + c0, v1 + c1, v2 + c2


# -- the call ----------------------------------------------------------------------------------
@_inline
def _lanes(m, k):
    return np.empty((m, k, LANES))


@_inline
def _block_steps(M, n_steps, h, P, anchor_x, anchor_v, anchor_a, anchor_w, ext_F, ext_T,
                 x, q, v, w, f_c, rk, bad):
    """All ``n_steps`` RK4 steps of one block (``step._rk4``, then ``step._project``): the
    state ``x, q, v, w`` and ``f_c`` ``(m, k, LANES)`` in place; ``rk`` the scratch. Returns
    ``OK`` or ``JOINT_SOLVE_FAILED`` (some lane's A was not positive definite). Inlined into
    ``advance_lanes``, where its arrays are allocated: that is what tells LLVM they are
    distinct."""
    m = x.shape[0]
    wb, w_s, xs, qs, vs, wbs, acc, sx, sv, sq, swb, alpha = rk[:12]
    F, T, hv, Iinv, C, Lo, G, pa, pc, uc = rk[12:]
    wind0, wind1, wind2 = M.wind[0], M.wind[1], M.wind[2]
    hh = 0.5 * h
    for k in range(n_steps):
        _start(m, x, q, v, w, wb, w_s, xs, qs, vs, wbs)
        for s in range(4):
            row = 2 * k + (0 if s == 0 else (1 if s < 3 else 2))
            _applied(m, row, P, qs, vs, w_s, ext_F, ext_T, anchor_w, wind0, wind1, wind2,
                     M.explicit_damping, M.drag_on, M.external_on, F, T)
            for l in range(LANES):
                bad[l] = 0.0
            _forward(m, row, P, qs, w_s, F, T, anchor_a, Iinv, hv, alpha, acc, G, C, Lo, f_c,
                     pa, bad)
            failed = 0.0
            for l in range(LANES):
                failed += bad[l]
            if failed != 0.0:
                return JOINT_SOLVE_FAILED
            _backward(m, P, Iinv, hv, C, Lo, f_c, acc, alpha, f_c)
            if s < 3:
                _next_stage(m, s, 1.0 if s == 0 else 2.0, hh if s < 2 else h, x, q, v, wb, qs,
                            wbs, vs, xs, w_s, acc, alpha, sx, sv, swb, sq)
            else:
                _finish(m, h, x, q, v, w, wb, qs, wbs, vs, acc, alpha, sx, sv, swb, sq)
        if M.projection:
            _project(m, 2 * k + 2, P, x, q, v, w, anchor_x, anchor_v, pc, uc)
    return OK


@_jit
def advance_lanes(M, A, n_steps, h, x, q, v, w, ext_F, ext_T, f_c):
    """``step.advance`` for a crowd that ``supports`` allows (same arguments, same results
    bit for bit, same status): the chains in blocks of ``LANES``, each block through all the
    steps of the call before the next (its working set stays in the cache)."""
    if n_steps <= 0:
        return OK
    starts = np.nonzero(M.is_first)[0]
    n_chains = starts.shape[0]
    m = x.shape[0] // n_chains
    S = A.position.shape[0]
    P = np.empty((m, _NP, LANES))
    X, Q, V, W, FC = _lanes(m, 3), _lanes(m, 4), _lanes(m, 3), _lanes(m, 3), _lanes(m, 3)
    ax, av, aa = (np.empty((S, 3, LANES)), np.empty((S, 3, LANES)),
                  np.empty((S, 3, LANES)))
    aw = np.empty((S, 3, LANES)) if M.explicit_damping else np.empty((0, 3, LANES))
    eF = _lanes(m, 3) if M.external_on else np.empty((0, 3, LANES))
    eT = _lanes(m, 3) if M.external_on else np.empty((0, 3, LANES))
    rk = (_lanes(m, 3), _lanes(m, 3), _lanes(m, 3), _lanes(m, 4), _lanes(m, 3), _lanes(m, 3),
          _lanes(m, 3), _lanes(m, 3), _lanes(m, 3), _lanes(m, 4), _lanes(m, 3), _lanes(m, 3),
          _lanes(m, 3), _lanes(m, 3), _lanes(m, 3), _lanes(m, 9), _lanes(m, 6), _lanes(m, 9),
          _lanes(m, 6), _lanes(m, 3), np.empty((3, LANES)), np.empty((3, LANES)))
    bad = np.empty(LANES)
    for b in range((n_chains + LANES - 1) // LANES):
        _load_model(M, b, n_chains, m, P)
        _gather(x, b, n_chains, m, X)
        _gather(q, b, n_chains, m, Q)
        _gather(v, b, n_chains, m, V)
        _gather(w, b, n_chains, m, W)
        _gather_anchor(A.position, b, n_chains, ax)
        _gather_anchor(A.velocity, b, n_chains, av)
        _gather_anchor(A.acceleration, b, n_chains, aa)
        if M.explicit_damping:
            _gather_anchor(A.angular_velocity, b, n_chains, aw)
        if M.external_on:
            _gather(ext_F, b, n_chains, m, eF)
            _gather(ext_T, b, n_chains, m, eT)
        status = _block_steps(M, n_steps, h, P, ax, av, aa, aw, eF, eT, X, Q, V, W, FC, rk,
                              bad)
        if status != OK:
            return status
        _scatter(X, b, n_chains, m, x)
        _scatter(Q, b, n_chains, m, q)
        _scatter(V, b, n_chains, m, v)
        _scatter(W, b, n_chains, m, w)
        _scatter(FC, b, n_chains, m, f_c)
    return OK


# -- dispatch ----------------------------------------------------------------------------------
def crowd_layout(model):
    """``(chains, segments per chain)`` if ``model``'s structure suits the lanes (at least
    ``MIN_CHAINS`` chains, all of one segment count, no colliders or joint limits), else None.
    The structure of a ``Model`` never changes: the simulator asks once."""
    counts = np.asarray(model.chain_end) - np.asarray(model.chain_start)
    if (model.n_chains < MIN_CHAINS or np.any(counts != counts[0]) or model.has_colliders
            or model.has_limits):
        return None
    return int(model.n_chains), int(counts[0])


def supports(M):
    """Whether the lanes kernel runs the ``StepModel`` ``M``'s switches: RK4, axisymmetric
    segments, no implicit damping, no bending stiffness, no Baumgarte terms (the rest:
    gravity, explicit damping, drag, external forces, projection on or off, are covered)."""
    return bool(M.integrator == RK4 and M.axisymmetric and not M.implicit_damping
                and not M.stiffness_on and M.baumgarte_stiffness == 0.0
                and M.baumgarte_damping == 0.0)


def kernel_for(M, layout):
    """The compiled step for the ``StepModel`` ``M`` of a model of ``crowd_layout``
    ``layout``: ``advance_lanes`` if it runs it, else ``step.advance`` (same arguments, same
    results)."""
    return advance_lanes if layout is not None and supports(M) else step.advance


def advance(M, A, n_steps, h, x, q, v, w, ext_F, ext_T, f_c, layout):
    """``step.advance`` through ``kernel_for(M, layout)``."""
    return kernel_for(M, layout)(M, A, n_steps, h, x, q, v, w, ext_F, ext_T, f_c)
