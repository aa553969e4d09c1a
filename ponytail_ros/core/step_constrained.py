"""Symplectic Euler and RATTLE steps of the compiled step
(``oracle.integrators.symplectic_euler``, ``oracle.integrators.rattle``): kicks, drifts and
joint impulses, one factorisation of A = J M⁻¹ Jᵀ per step (``chain_solve.factor``, reused
by the next step) and two solves.

Frames and units: world frame (REP 103), SI; the state arrays are ``step``'s.
"""
import numba as nb
import numpy as np

from .applied_forces import applied_forces
from .chain_solve import block, factor, mul9, solve
from .step_model import RATTLE
from .vec import cross_s, qaxis_x_at, qfrom_rotvec_s, qmul_s, qnormalize_at, qrot_s

__all__ = ['constrained_step']

# Kernels called from compiled code only are compiled without the wrappers that make a
# function callable from Python (``_INTERNAL``): numba would generate them at every
# specialisation's compile (for a ``StepModel`` argument, code unboxing its 27 fields), and
# nothing would call them.
_INTERNAL = dict(no_cpython_wrapper=True, no_cfunc_wrapper=True)
_jit = nb.njit(cache=True, _nrt=True, **_INTERNAL)
_inline = nb.njit(cache=True, inline='always')
_borrow = nb.njit(cache=True, _nrt=False, **_INTERNAL)


@_inline
def _axes(q, e):
    """Every segment's axis (its body +X in the world) into ``e`` ``(n, 3)``."""
    for i in range(q.shape[0]):
        e[i, 0], e[i, 1], e[i, 2] = qaxis_x_at(q, i)


@_inline
def _apply_joint_impulses(M, lam, hv, Iinv, dv, dw):
    """Δv, Δω of every segment from joint forces or impulses ``lam`` (+ on the child at its
    proximal end, - on the parent at its distal end)."""
    n = lam.shape[0]
    for i in range(n):
        f0, f1, f2 = lam[i, 0], lam[i, 1], lam[i, 2]
        g0, g1, g2 = 0.0, 0.0, 0.0
        if M.has_child[i]:
            g0, g1, g2 = lam[i + 1, 0], lam[i + 1, 1], lam[i + 1, 2]
        dv[i, 0] = (f0 - g0) * M.inv_mass[i]
        dv[i, 1] = (f1 - g1) * M.inv_mass[i]
        dv[i, 2] = (f2 - g2) * M.inv_mass[i]
        # (-h) × f_c + h × (-f_next) = (f_c + f_next) × h
        t0, t1, t2 = cross_s(f0 + g0, f1 + g1, f2 + g2, hv[i, 0], hv[i, 1], hv[i, 2])
        dw[i, 0], dw[i, 1], dw[i, 2] = mul9(block(Iinv, i), t0, t1, t2)


@_jit
def _rotation_kick(M, q, e, Iinv, w, T, h, out):
    """ω after ``h`` of I ω̇ + ω × Iω = T, the gyroscopic term implicit
    (``oracle.integrators.rotation_kick``: exact axial transport + implicit midpoint precession for
    axisymmetric segments, Catto's implicit Euler Newton step otherwise)."""
    n = w.shape[0]
    J = np.empty((3, 3)) if not M.axisymmetric else np.empty((0, 0))
    r = np.empty(3) if not M.axisymmetric else np.empty(0)
    for i in range(n):
        Ia, Ip = M.inertia[i, 0], M.inertia[i, 1]
        if M.axisymmetric:
            e0, e1, e2 = e[i, 0], e[i, 1], e[i, 2]
            wa = w[i, 0] * e0 + w[i, 1] * e1 + w[i, 2] * e2
            Ta = T[i, 0] * e0 + T[i, 1] * e1 + T[i, 2] * e2
            p0, p1, p2 = w[i, 0] - wa * e0, w[i, 1] - wa * e1, w[i, 2] - wa * e2
            t0, t1, t2 = T[i, 0] - Ta * e0, T[i, 1] - Ta * e1, T[i, 2] - Ta * e2
            wa1 = wa + h * Ta / Ia
            s = 0.5 * h * Ia / Ip * wa1
            c0, c1, c2 = cross_s(e0, e1, e2, p0, p1, p2)
            y0 = p0 + s * c0 + h * t0 / Ip
            y1 = p1 + s * c1 + h * t1 / Ip
            y2 = p2 + s * c2 + h * t2 / Ip
            c0, c1, c2 = cross_s(e0, e1, e2, y0, y1, y2)
            den = 1.0 + s * s
            out[i, 0] = wa1 * e0 + (y0 + s * c0) / den
            out[i, 1] = wa1 * e1 + (y1 + s * c1) / den
            out[i, 2] = wa1 * e2 + (y2 + s * c2) / den
        else:
            qx, qy, qz, qw = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
            b0, b1, b2 = qrot_s(-qx, -qy, -qz, qw, w[i, 0], w[i, 1], w[i, 2])
            T0, T1, T2 = qrot_s(-qx, -qy, -qz, qw, T[i, 0], T[i, 1], T[i, 2])
            I0, I1, I2 = M.inertia[i, 0], M.inertia[i, 1], M.inertia[i, 2]
            L0, L1, L2 = I0 * b0, I1 * b1, I2 * b2
            # J = I + h([ω]× I - [Iω]×)
            Sw = ((0.0, -b2, b1), (b2, 0.0, -b0), (-b1, b0, 0.0))
            SL = ((0.0, -L2, L1), (L2, 0.0, -L0), (-L1, L0, 0.0))
            Id = (I0, I1, I2)
            for a in range(3):
                for b in range(3):
                    J[a, b] = (Id[a] if a == b else 0.0) + h * (Sw[a][b] * Id[b] - SL[a][b])
            g0, g1, g2 = cross_s(b0, b1, b2, L0, L1, L2)
            r[0], r[1], r[2] = h * (T0 - g0), h * (T1 - g1), h * (T2 - g2)
            d0, d1, d2 = _solve3(J, r[0], r[1], r[2])
            out[i, 0], out[i, 1], out[i, 2] = qrot_s(qx, qy, qz, qw, b0 + d0, b1 + d1, b2 + d2)


@_inline
def _solve3(J, r0, r1, r2):
    """J⁻¹ r for a 3×3 ``J`` (Cramer's rule: no LAPACK call inside the step)."""
    c00 = J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1]
    c01 = J[1, 2] * J[2, 0] - J[1, 0] * J[2, 2]
    c02 = J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0]
    det = J[0, 0] * c00 + J[0, 1] * c01 + J[0, 2] * c02
    c10 = J[0, 2] * J[2, 1] - J[0, 1] * J[2, 2]
    c11 = J[0, 0] * J[2, 2] - J[0, 2] * J[2, 0]
    c12 = J[0, 1] * J[2, 0] - J[0, 0] * J[2, 1]
    c20 = J[0, 1] * J[1, 2] - J[0, 2] * J[1, 1]
    c21 = J[0, 2] * J[1, 0] - J[0, 0] * J[1, 2]
    c22 = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
    return ((c00 * r0 + c10 * r1 + c20 * r2) / det, (c01 * r0 + c11 * r1 + c21 * r2) / det,
            (c02 * r0 + c12 * r1 + c22 * r2) / det)


@_borrow
def _torque_kick(M, q, e, Iinv, w, T, h, out):
    """ω + h I⁻¹ T at fixed orientations, no gyroscopic term
    (``oracle.integrators.torque_kick``)."""
    n = w.shape[0]
    for i in range(n):
        if M.axisymmetric:
            e0, e1, e2 = e[i, 0], e[i, 1], e[i, 2]
            Ta = T[i, 0] * e0 + T[i, 1] * e1 + T[i, 2] * e2
            ka = Ta / M.inertia[i, 0]
            ip = M.inertia[i, 1]
            out[i, 0] = w[i, 0] + h * (ka * e0 + (T[i, 0] - Ta * e0) / ip)
            out[i, 1] = w[i, 1] + h * (ka * e1 + (T[i, 1] - Ta * e1) / ip)
            out[i, 2] = w[i, 2] + h * (ka * e2 + (T[i, 2] - Ta * e2) / ip)
        else:
            qx, qy, qz, qw = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
            b0, b1, b2 = qrot_s(-qx, -qy, -qz, qw, T[i, 0], T[i, 1], T[i, 2])
            r0, r1, r2 = qrot_s(qx, qy, qz, qw, b0 / M.inertia[i, 0], b1 / M.inertia[i, 1],
                               b2 / M.inertia[i, 2])
            out[i, 0] = w[i, 0] + h * r0
            out[i, 1] = w[i, 1] + h * r1
            out[i, 2] = w[i, 2] + h * r2


@_inline
def _turned(u0, u1, u2, w0, w1, w2, h):
    """u turned by the rotation vector h w (Rodrigues)."""
    rate = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    angle = h * rate
    if angle < 1e-6:
        s = h * (1.0 - angle * angle / 6.0)
        c = 0.5 * h * h
    else:
        s = np.sin(angle) / rate
        c = (1.0 - np.cos(angle)) / (rate * rate)
    a0, a1, a2 = cross_s(w0, w1, w2, u0, u1, u2)
    b0, b1, b2 = cross_s(w0, w1, w2, a0, a1, a2)
    return u0 + s * a0 + c * b0, u1 + s * a1 + c * b1, u2 + s * a2 + c * b2


@_inline
def _axial_part(M, i, e, w0, w1, w2, ratio):
    """The part of ω that does not turn segment i's axis: ``ratio`` (ω·e) e (axisymmetric)."""
    if not M.axisymmetric:
        return 0.0, 0.0, 0.0
    s = ratio * (w0 * e[i, 0] + w1 * e[i, 1] + w2 * e[i, 2])
    return s * e[i, 0], s * e[i, 1], s * e[i, 2]


@_borrow
def _gap_rhs(M, A, row, x, v, w, hv, e, h, precession, end, out):
    """Where the free motion (v, ω) held for ``h`` would open every joint, divided by ``h``
    (the joint impulses' right-hand side; the segment axes turned by their swing rate,
    or the precession rate Ω for RATTLE)."""
    n = x.shape[0]
    for i in range(n):
        ratio = 1.0
        if precession and M.axisymmetric:
            ratio = 1.0 - M.inertia[i, 0] / M.inertia[i, 1]
        a0, a1, a2 = _axial_part(M, i, e, w[i, 0], w[i, 1], w[i, 2], ratio)
        t0, t1, t2 = _turned(hv[i, 0], hv[i, 1], hv[i, 2], w[i, 0] - a0, w[i, 1] - a1,
                             w[i, 2] - a2, h)
        end[i, 0], end[i, 1], end[i, 2] = t0, t1, t2
    for i in range(n):
        c = M.chain_of[i]
        for a in range(3):
            xi = x[i, a] + h * v[i, a]
            if M.is_first[i]:
                parent = A.position[row, c, a]
            else:
                parent = x[i - 1, a] + h * v[i - 1, a] + end[i - 1, a]
            out[i, a] = (parent - (xi - end[i, a])) / h


@_borrow
def _velocity_errors(M, A, row, v, w, hv, out):
    """Parent side minus child side of every joint's velocity (m/s)."""
    n = v.shape[0]
    for i in range(n):
        c = M.chain_of[i]
        u0, u1, u2 = cross_s(w[i, 0], w[i, 1], w[i, 2], hv[i, 0], hv[i, 1], hv[i, 2])
        child = (v[i, 0] - u0, v[i, 1] - u1, v[i, 2] - u2)
        if M.is_first[i]:
            for a in range(3):
                out[i, a] = A.velocity[row, c, a] - child[a]
        else:
            p0, p1, p2 = cross_s(w[i - 1, 0], w[i - 1, 1], w[i - 1, 2],
                                hv[i - 1, 0], hv[i - 1, 1], hv[i - 1, 2])
            par = (v[i - 1, 0] + p0, v[i - 1, 1] + p1, v[i - 1, 2] + p2)
            for a in range(3):
                out[i, a] = par[a] - child[a]


@_borrow
def _drift(M, x, q, v, w, e, h, precession):
    """Move for ``h`` at (v, ω), in place: symplectic Euler's ``drift`` (``precession``
    False: spin about the axis by h ω_a, swing by h ω⊥) or RATTLE's exact torque-free
    ``free_rotation`` (True: precess about Ω, spin at ν = ω_a (1 - I_a/I_p))."""
    n = x.shape[0]
    for i in range(n):
        for a in range(3):
            x[i, a] = x[i, a] + h * v[i, a]
        w0, w1, w2 = w[i, 0], w[i, 1], w[i, 2]
        qx, qy, qz, qw = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
        if not M.axisymmetric:
            rx, ry, rz, rw = qfrom_rotvec_s(w0 * h, w1 * h, w2 * h)
            q[i, 0], q[i, 1], q[i, 2], q[i, 3] = qmul_s(rx, ry, rz, rw, qx, qy, qz, qw)
            qnormalize_at(q, i)
            continue
        e0, e1, e2 = e[i, 0], e[i, 1], e[i, 2]
        wa = w0 * e0 + w1 * e1 + w2 * e2
        if precession:
            r = 1.0 - M.inertia[i, 0] / M.inertia[i, 1]
            o0, o1, o2 = w0 - r * wa * e0, w1 - r * wa * e1, w2 - r * wa * e2     # Ω
            spin = (w0 - o0) * e0 + (w1 - o1) * e1 + (w2 - o2) * e2             # ν
        else:
            o0, o1, o2 = w0 - wa * e0, w1 - wa * e1, w2 - wa * e2                # ω⊥
            spin = wa
        half = 0.5 * h * spin
        sx, sw = np.sin(half), np.cos(half)
        bx, by, bz, bw = qmul_s(qx, qy, qz, qw, sx, 0.0, 0.0, sw)     # q ⊗ exp(h·spin x̂)
        rx, ry, rz, rw = qfrom_rotvec_s(o0 * h, o1 * h, o2 * h)
        q[i, 0], q[i, 1], q[i, 2], q[i, 3] = qmul_s(rx, ry, rz, rw, bx, by, bz, bw)
        qnormalize_at(q, i)
        n0, n1, n2 = qaxis_x_at(q, i)
        w[i, 0] = o0 + spin * n0
        w[i, 1] = o1 + spin * n1
        w[i, 2] = o2 + spin * n2


@_jit
def constrained_step(M, A, k, h, x, q, v, w, ext_F, ext_T, ws, rws, f_c, fresh):  # noqa: C901 (the stages of the two integrators)
    """One symplectic Euler or RATTLE step (``oracle.integrators.symplectic_euler`` /
    ``oracle.integrators.rattle``). ``fresh``: A must be factorised at q first (else the factors in
    ``ws`` are those of q, left by the previous step's projection). False if a solve fails."""
    F, T, e, hv, Iinv, C, Lo = ws
    n = x.shape[0]
    r0, r1 = 2 * k, 2 * k + 2
    rattle = M.integrator == RATTLE
    s0 = np.int64(0)        # (a literal 0 would specialise ``factor`` on it)
    if fresh:
        _axes(q, e)
        if not factor(M, q, s0, n, hv, Iinv, C, Lo):
            return False
    applied_forces(M, A, r0, x, q, v, w, ext_F, ext_T, F, T)
    kick = 0.5 * h if rattle else h
    v1, w1, dv, dw, lam, w_change, v0, mu, end = (rws[0], rws[1], rws[2], rws[4], rws[5],
                                                  rws[6], rws[7], rws[8], rws[9])
    for i in range(n):
        for a in range(3):
            v1[i, a] = v[i, a] + kick * F[i, a] * M.inv_mass[i]
    if rattle:
        _torque_kick(M, q, e, Iinv, w, T, kick, w1)
    else:
        _rotation_kick(M, q, e, Iinv, w, T, h, w1)
    if M.projection:
        _gap_rhs(M, A, r1, x, v1, w1, hv, e, h, rattle, end, lam)
    else:
        _unprojected_rhs(M, A, r0, r1, x, v, w, v1, w1, hv, e, h, lam)
    solve(C, Lo, M.is_first, lam)
    _apply_joint_impulses(M, lam, hv, Iinv, dv, dw)
    for i in range(n):
        for a in range(3):
            v1[i, a] += dv[i, a]
            w1[i, a] += dw[i, a]
            w_change[i, a] = w1[i, a] - w[i, a]
            f_c[i, a] = lam[i, a] / h
    for i in range(n):
        for a in range(3):
            v0[i, a] = v[i, a]
    _drift(M, x, q, v1, w1, e, h, rattle)       # x, q in place; w1 gets the carried spin
    for i in range(n):
        for a in range(3):
            v[i, a] = v1[i, a]
            w[i, a] = w1[i, a]
    if not M.projection:
        return True
    # A at the step's end (kept for the next step: the projection does not turn segments).
    _axes(q, e)
    if not factor(M, q, s0, n, hv, Iinv, C, Lo):
        return False
    if rattle:
        # Second half kick with the forces at the end; velocity-dependent terms at u½
        # extrapolated by its change over the first half.
        for i in range(n):
            for a in range(3):
                dv[i, a] = 2.0 * v1[i, a] - v0[i, a]
                dw[i, a] = w1[i, a] + w_change[i, a]
        applied_forces(M, A, r1, x, q, dv, dw, ext_F, ext_T, F, T)
        for i in range(n):
            for a in range(3):
                v[i, a] = v1[i, a] + kick * F[i, a] * M.inv_mass[i]
        _torque_kick(M, q, e, Iinv, w1, T, kick, w)
    _velocity_errors(M, A, r1, v, w, hv, mu)
    solve(C, Lo, M.is_first, mu)
    _apply_joint_impulses(M, mu, hv, Iinv, dv, dw)
    for i in range(n):
        for a in range(3):
            v[i, a] += dv[i, a]
            w[i, a] += dw[i, a]
            if rattle:
                f_c[i, a] += mu[i, a] / h
    return True


@_jit
def _unprojected_rhs(M, A, r0, r1, x, v, w, v1, w1, hv, e, h, out):
    """Symplectic Euler without projection: the velocity form of C̈ = 0 (the joint points'
    curvature predicted at the step's start, velocity errors kept, optional Baumgarte)."""
    n = x.shape[0]
    curv = np.empty((n, 3))
    c_dot0 = np.empty((n, 3))
    c_dot1 = np.empty((n, 3))
    for i in range(n):
        a0, a1, a2 = _axial_part(M, i, e, w[i, 0], w[i, 1], w[i, 2], 1.0)
        s0, s1, s2 = w[i, 0] - a0, w[i, 1] - a1, w[i, 2] - a2
        u0, u1, u2 = cross_s(s0, s1, s2, hv[i, 0], hv[i, 1], hv[i, 2])
        curv[i, 0], curv[i, 1], curv[i, 2] = cross_s(s0, s1, s2, u0, u1, u2)
    _velocity_errors(M, A, r0, v, w, hv, c_dot0)
    _velocity_errors(M, A, r1, v1, w1, hv, c_dot1)
    baumgarte = M.baumgarte_stiffness != 0.0 or M.baumgarte_damping != 0.0
    for i in range(n):
        c = M.chain_of[i]
        for a in range(3):
            target = c_dot0[i, a]
            if baumgarte:
                if M.is_first[i]:
                    pp = A.position[r0, c, a]
                else:
                    pp = x[i - 1, a] + hv[i - 1, a]
                gap = pp - (x[i, a] - hv[i, a])
                target = c_dot0[i, a] - h * (M.baumgarte_damping * c_dot0[i, a]
                                             + M.baumgarte_stiffness * gap)
            parent = 0.0 if M.is_first[i] else curv[i - 1, a]
            out[i, a] = c_dot1[i, a] + h * (parent + curv[i, a]) - target
