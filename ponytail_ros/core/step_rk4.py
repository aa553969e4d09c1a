"""The classical RK4 step of the compiled step (``oracle.integrators.rk4``): four stages, each with
the joint forces solved (A f_c = b, ``chain_solve``'s factorisation fused with the stage's
sweep over the segments).

Frames and units: world frame (REP 103), SI; the state arrays are ``step``'s.
"""
import numba as nb

from .applied_forces import applied_terms
from .chain_solve import (
    ZERO6,
    block,
    joint_row,
    mass_properties,
    mul9,
    segment_G,
    store_block,
    store_factors,
)
from .vec import cross_s, qmul_s, qnormalize_at, qrot_s

__all__ = ['rk4']

# Kernels called from compiled code only are compiled without the wrappers that make a
# function callable from Python (``_INTERNAL``): numba would generate them at every
# specialisation's compile (for a ``StepModel`` argument, code unboxing its 27 fields), and
# nothing would call them.
_INTERNAL = dict(no_cpython_wrapper=True, no_cfunc_wrapper=True)
_jit = nb.njit(cache=True, _nrt=True, **_INTERNAL)
_inline = nb.njit(cache=True, inline='always')
_borrow = nb.njit(cache=True, _nrt=False, **_INTERNAL)


@_inline
def _gyroscopic(axisymmetric, I0, I1, I2, e0, e1, e2, qx, qy, qz, qw, w0, w1, w2):
    """ω × Iω (world) of a segment of principal moments (I0, I1, I2), axis e, orientation q.
    Scalars only: an inline helper taking arrays would pay their reference counts per call."""
    if axisymmetric:
        s = (I0 - I1) * (e0 * w0 + e1 * w1 + e2 * w2)
        c0, c1, c2 = cross_s(w0, w1, w2, e0, e1, e2)
        return s * c0, s * c1, s * c2
    b0, b1, b2 = qrot_s(-qx, -qy, -qz, qw, w0, w1, w2)
    l0, l1, l2 = qrot_s(qx, qy, qz, qw, I0 * b0, I1 * b1, I2 * b2)
    return cross_s(w0, w1, w2, l0, l1, l2)


@_inline
def _accelerations(row, x, q, v, w, F, T, hv, Iinv, C, Lo, acc, alpha, f_c, half, inv_mass,
                   inertia, inv_inertia, chain_of, is_first, has_child, axisymmetric,
                   baumgarte_stiffness, baumgarte_damping, anchor_position, anchor_velocity,
                   anchor_acceleration):
    """Linear and angular accelerations (m/s², rad/s²) with every joint enforced
    (``oracle.solver.Dynamics.accelerations``) under the applied forces ``F``, ``T``, ``f_c`` the
    joint forces (N); False if A is not positive definite.

    Two sweeps, the factorisation's own (``chain_solve``):
      root to tip, per segment i: its mass properties and free accelerations (Eq. 11 without
        f_c), joint i's right-hand side (Eq. 3), joint i's row of A factorised and the
        right-hand side forward-substituted. The factorisation is a chain of dependent
        divisions from joint to joint; the segment's own work beside it fills the wait.
      tip to root: the back substitution, and each segment's joint forces applied.
    The factorisation's arithmetic is ``chain_solve.factor``'s (``joint_row``), the solve's
    ``chain_solve.solve``'s, the joint forces applied as ``step_constrained`` applies its
    impulses."""
    n = x.shape[0]
    baumgarte = baumgarte_stiffness != 0.0 or baumgarte_damping != 0.0
    g = pinv = ZERO6                   # G and P⁻¹ of the previous segment / joint
    z0 = z1 = z2 = 0.0                  # the previous joint's forward-substituted rhs
    pa0 = pa1 = pa2 = 0.0               # the previous segment's distal-point acceleration
    for i in range(n):
        first = is_first[i]
        e0, e1, e2, X = mass_properties(axisymmetric, q[i, 0], q[i, 1], q[i, 2], q[i, 3],
                                         inv_inertia[i, 0], inv_inertia[i, 1],
                                         inv_inertia[i, 2])
        store_block(Iinv, i, X)
        hl = half[i]
        h0, h1, h2 = hl * e0, hl * e1, hl * e2
        hv[i, 0], hv[i, 1], hv[i, 2] = h0, h1, h2
        # Free accelerations (Eq. 11 without f_c) and the joint points' under them (Eq. 3):
        # r_d = h, r_p = -h.
        w0, w1, w2 = w[i, 0], w[i, 1], w[i, 2]
        y0, y1, y2 = _gyroscopic(axisymmetric, inertia[i, 0], inertia[i, 1],
                                 inertia[i, 2], e0, e1, e2, q[i, 0], q[i, 1], q[i, 2],
                                 q[i, 3], w0, w1, w2)
        a0, a1, a2 = mul9(X, T[i, 0] - y0, T[i, 1] - y1, T[i, 2] - y2)
        alpha[i, 0], alpha[i, 1], alpha[i, 2] = a0, a1, a2
        im = inv_mass[i]
        ac0, ac1, ac2 = F[i, 0] * im, F[i, 1] * im, F[i, 2] * im
        acc[i, 0], acc[i, 1], acc[i, 2] = ac0, ac1, ac2
        c0, c1, c2 = cross_s(a0, a1, a2, h0, h1, h2)
        u0, u1, u2 = cross_s(w0, w1, w2, h0, h1, h2)              # ω × h
        d0, d1, d2 = cross_s(w0, w1, w2, u0, u1, u2)
        t0, t1, t2 = c0 + d0, c1 + d1, c2 + d2                   # tangential + centripetal
        # Joint i's right-hand side: parent point minus child point acceleration.
        if first:
            c = chain_of[i]
            pa0 = anchor_acceleration[row, c, 0]
            pa1 = anchor_acceleration[row, c, 1]
            pa2 = anchor_acceleration[row, c, 2]
        r0, r1, r2 = pa0 - (ac0 - t0), pa1 - (ac1 - t1), pa2 - (ac2 - t2)
        if baumgarte:
            b0, b1, b2 = _baumgarte(row, x, v, w, hv, i, (u0, u1, u2), chain_of, is_first,
                                    anchor_position, anchor_velocity, baumgarte_stiffness,
                                    baumgarte_damping)
            r0 += b0
            r1 += b1
            r2 += b2
        pa0, pa1, pa2 = ac0 + t0, ac1 + t1, ac2 + t2
        # Joint i's row of A, factorised; forward substitution (1 + 𝓛) z = b.
        gi = segment_G(axisymmetric, h0, h1, h2, inv_inertia[i, 1], X)
        imp = 0.0 if first else inv_mass[i - 1]
        ok, lo, pinv = joint_row(first, pinv, im, imp, gi, g)
        if not ok:
            return False
        store_factors(C, Lo, i, pinv, lo)
        g = gi
        if not first:
            r0 -= lo[0] * z0 + lo[1] * z1 + lo[2] * z2
            r1 -= lo[3] * z0 + lo[4] * z1 + lo[5] * z2
            r2 -= lo[6] * z0 + lo[7] * z1 + lo[8] * z2
        f_c[i, 0], f_c[i, 1], f_c[i, 2] = r0, r1, r2
        z0, z1, z2 = r0, r1, r2
    # Tip to root: (1 + 𝓛)ᵀ λ = P⁻¹ z, then each segment's joint forces: + λ_i on it at its
    # proximal end, - λ_{i+1} at its distal end (as ``step_constrained`` applies impulses).
    l0 = l1 = l2 = 0.0                  # λ_{i+1}
    for i in range(n - 1, -1, -1):
        z0, z1, z2 = f_c[i, 0], f_c[i, 1], f_c[i, 2]
        P = block(C, i)
        f0, f1, f2 = mul9(P, z0, z1, z2)
        if i + 1 < n and not is_first[i + 1]:
            f0 -= Lo[i + 1, 0, 0] * l0 + Lo[i + 1, 1, 0] * l1 + Lo[i + 1, 2, 0] * l2
            f1 -= Lo[i + 1, 0, 1] * l0 + Lo[i + 1, 1, 1] * l1 + Lo[i + 1, 2, 1] * l2
            f2 -= Lo[i + 1, 0, 2] * l0 + Lo[i + 1, 1, 2] * l1 + Lo[i + 1, 2, 2] * l2
        f_c[i, 0], f_c[i, 1], f_c[i, 2] = f0, f1, f2
        g0, g1, g2 = (l0, l1, l2) if has_child[i] else (0.0, 0.0, 0.0)
        im = inv_mass[i]
        acc[i, 0] += (f0 - g0) * im
        acc[i, 1] += (f1 - g1) * im
        acc[i, 2] += (f2 - g2) * im
        # (-h) × f_c + h × (-f_next) = (f_c + f_next) × h
        t0, t1, t2 = cross_s(f0 + g0, f1 + g1, f2 + g2, hv[i, 0], hv[i, 1], hv[i, 2])
        b0, b1, b2 = mul9(block(Iinv, i), t0, t1, t2)
        alpha[i, 0] += b0
        alpha[i, 1] += b1
        alpha[i, 2] += b2
        l0, l1, l2 = f0, f1, f2
    return True


@_borrow
def _baumgarte(row, x, v, w, hv, i, wxh, chain_of, is_first, anchor_position, anchor_velocity,
               baumgarte_stiffness, baumgarte_damping):
    """Joint i's Baumgarte term 2ζ Ċ + κ C (``wxh`` = ω × h of segment i; segment i-1's
    ``hv`` already set)."""
    if is_first[i]:
        c = chain_of[i]
        pp = (anchor_position[row, c, 0], anchor_position[row, c, 1], anchor_position[row, c, 2])
        pv = (anchor_velocity[row, c, 0], anchor_velocity[row, c, 1], anchor_velocity[row, c, 2])
    else:
        pp = (x[i - 1, 0] + hv[i - 1, 0], x[i - 1, 1] + hv[i - 1, 1], x[i - 1, 2] + hv[i - 1, 2])
        pu0, pu1, pu2 = cross_s(w[i - 1, 0], w[i - 1, 1], w[i - 1, 2],
                                hv[i - 1, 0], hv[i - 1, 1], hv[i - 1, 2])
        pv = (v[i - 1, 0] + pu0, v[i - 1, 1] + pu1, v[i - 1, 2] + pu2)
    return (_baumgarte_axis(x, v, hv, i, 0, pp[0], pv[0], wxh[0], baumgarte_stiffness,
                            baumgarte_damping),
            _baumgarte_axis(x, v, hv, i, 1, pp[1], pv[1], wxh[1], baumgarte_stiffness,
                            baumgarte_damping),
            _baumgarte_axis(x, v, hv, i, 2, pp[2], pv[2], wxh[2], baumgarte_stiffness,
                            baumgarte_damping))


@_inline
def _baumgarte_axis(x, v, hv, i, a, pp, pv, wxh, baumgarte_stiffness, baumgarte_damping):
    gap = pp - (x[i, a] - hv[i, a])
    rate = pv - (v[i, a] - wxh)
    return baumgarte_damping * rate + baumgarte_stiffness * gap


@_inline
def _rk4_sum(s, weight, total, d):
    """RK4's d₁ + 2 d₂ + 2 d₃ + d₄, summed as the stage derivatives ``d`` come (``s`` =
    0..3)."""
    return d if s == 0 else total + weight * d


@_borrow
def rk4(M, A, k, h, x, q, v, w, ext_F, ext_T, ws, rws, f_c):  # noqa: C901 (the stages' per-segment loops)
    """One classical RK4 step (``oracle.integrators.rk4``), ω carried in the body frame inside.
    A call, not inlined into the step loop: numba's inliner copies a callee's IR block by
    block, each copy with all the callee's variables, quadratic in a body this large (its
    stages' helpers inlined): a third of the free step's compile, for one call per step.

    The right-hand side is (ẋ = v, q̇ = ½ q ⊗ ω_b, v̇ = a, ω̇_b = Rᵀ α), with a, α from
    ``accelerations`` at the stage's world ω = R ω_b (``w_s``). The stage derivatives are
    summed as they come (d1 + 2 d2 + 2 d3 + d4, in that order), so no stage is stored; each
    segment's derivative, sums and next stage are done in one pass."""
    n = x.shape[0]
    F, T, _, hv, Iinv, C, Lo = ws
    wb, w_s, xs, qs, vs, wbs, acc, _, sx, sv, sq, swb, alpha = rws
    for i in range(n):
        qx, qy, qz, qw = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
        b0, b1, b2 = qrot_s(-qx, -qy, -qz, qw, w[i, 0], w[i, 1], w[i, 2])
        wb[i, 0], wb[i, 1], wb[i, 2] = b0, b1, b2
        for a in range(3):
            xs[i, a] = x[i, a]
            vs[i, a] = v[i, a]
        wbs[i, 0], wbs[i, 1], wbs[i, 2] = b0, b1, b2
        qs[i, 0], qs[i, 1], qs[i, 2], qs[i, 3] = qx, qy, qz, qw
        w_s[i, 0], w_s[i, 1], w_s[i, 2] = qrot_s(qx, qy, qz, qw, b0, b1, b2)
    hh = 0.5 * h
    for s in range(4):
        row = 2 * k + (0 if s == 0 else (1 if s < 3 else 2))
        applied_terms(row, xs, qs, vs, w_s, ext_F, ext_T, F, T, M.mass, M.length, M.chain_of,
                 M.is_first, M.damping, M.stiffness, M.q_rest, M.drag_linear, M.drag_quadratic,
                 M.gravity, M.wind, M.gravity_on, M.explicit_damping, M.stiffness_on, M.drag_on,
                 M.external_on, A.orientation, A.angular_velocity)
        if not _accelerations(row, xs, qs, vs, w_s, F, T, hv, Iinv, C, Lo, acc, alpha, f_c,
                              M.half, M.inv_mass, M.inertia, M.inv_inertia, M.chain_of,
                              M.is_first, M.has_child, M.axisymmetric, M.baumgarte_stiffness,
                              M.baumgarte_damping, A.position, A.velocity, A.acceleration):
            return False
        weight = 1.0 if (s == 0 or s == 3) else 2.0
        c = hh if s < 2 else h            # the next stage's offset
        for i in range(n):
            qx, qy, qz, qw = qs[i, 0], qs[i, 1], qs[i, 2], qs[i, 3]
            d0, d1, d2, d3 = qmul_s(qx, qy, qz, qw, wbs[i, 0], wbs[i, 1], wbs[i, 2], 0.0)
            e0, e1, e2 = qrot_s(-qx, -qy, -qz, qw, alpha[i, 0], alpha[i, 1], alpha[i, 2])
            dx = (vs[i, 0], vs[i, 1], vs[i, 2])            # ẋ = v
            dv = (acc[i, 0], acc[i, 1], acc[i, 2])
            dwb = (e0, e1, e2)
            dq = (0.5 * d0, 0.5 * d1, 0.5 * d2, 0.5 * d3)
            for a in range(3):
                sx[i, a] = _rk4_sum(s, weight, sx[i, a], dx[a])
                sv[i, a] = _rk4_sum(s, weight, sv[i, a], dv[a])
                swb[i, a] = _rk4_sum(s, weight, swb[i, a], dwb[a])
            for a in range(4):
                sq[i, a] = _rk4_sum(s, weight, sq[i, a], dq[a])
            if s < 3:                     # the next stage's state
                for a in range(3):
                    xs[i, a] = x[i, a] + c * dx[a]
                    vs[i, a] = v[i, a] + c * dv[a]
                    wbs[i, a] = wb[i, a] + c * dwb[a]
                for a in range(4):
                    qs[i, a] = q[i, a] + c * dq[a]
                w_s[i, 0], w_s[i, 1], w_s[i, 2] = qrot_s(qs[i, 0], qs[i, 1], qs[i, 2], qs[i, 3],
                                                        wbs[i, 0], wbs[i, 1], wbs[i, 2])
    sixth = h / 6.0
    for i in range(n):
        for a in range(3):
            x[i, a] = x[i, a] + sixth * sx[i, a]
            v[i, a] = v[i, a] + sixth * sv[i, a]
            wb[i, a] = wb[i, a] + sixth * swb[i, a]
        for a in range(4):
            q[i, a] = q[i, a] + sixth * sq[i, a]
        qnormalize_at(q, i)
        w[i, 0], w[i, 1], w[i, 2] = qrot_s(q[i, 0], q[i, 1], q[i, 2], q[i, 3],
                                          wb[i, 0], wb[i, 1], wb[i, 2])
    return True
