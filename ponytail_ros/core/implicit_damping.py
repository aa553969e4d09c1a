"""Implicit joint damping of the compiled step, for damping too stiff for the explicit step:
implicit Euler on the constrained system, a banded KKT solve in O(n)
(``oracle.solver.Dynamics.implicit_damping``).

Frames and units: world frame (REP 103), SI; the state arrays are ``step``'s.
"""
import numba as nb
import numpy as np

from .vec import qaxis_x_at, qmatrix

__all__ = ['implicit_damping']

# Kernels called from compiled code only are compiled without the wrappers that make a
# function callable from Python (``_INTERNAL``): numba would generate them at every
# specialisation's compile (for a ``StepModel`` argument, code unboxing its 27 fields), and
# nothing would call them.
_INTERNAL = dict(no_cpython_wrapper=True, no_cfunc_wrapper=True)
_jit = nb.njit(cache=True, _nrt=True, **_INTERNAL)
_inline = nb.njit(cache=True, inline='always')

_KL = 8         # half-bandwidth of the reduced KKT matrix, unknowns (λ_i, ω_i) per segment


@_inline
def _band_add(ab, r, c, val):
    ab[r, c - r + 2 * _KL] += val


@_jit
def implicit_damping(M, A, row, q, v, w, h):  # noqa: C901 (the banded KKT rows, per segment)
    """Velocities after ``h`` of joint damping, implicit Euler on the constrained system
    (``oracle.solver.Dynamics.implicit_damping``), in place; False if singular:

        (M + h C) u⁺ - Jᵀ λ = M u + h c₀ ω_anchor,     J u⁺ = anchor terms.

    The linear rows give v⁺_i = v_i + (λ_i - λ_{i+1}) / m_i, substituted into the joint rows:
    what is left has unknowns (λ_i, ω_i) per segment, half-bandwidth 8 (against 17 with v
    kept), solved by banded Gaussian elimination with partial pivoting in O(n)."""
    n = v.shape[0]
    N = 6 * n
    ab = np.zeros((N, 3 * _KL + 1))          # columns r - KL .. r + 2 KL (fill-in by pivoting)
    rhs = np.zeros(N)
    R = np.empty((3, 3)) if not M.axisymmetric else np.empty((0, 0))
    for i in range(n):
        c = M.chain_of[i]
        LAM, W = 6 * i, 6 * i + 3
        e0, e1, e2 = qaxis_x_at(q, i)
        g = M.half[i]
        S = ((0.0, -g * e2, g * e1), (g * e2, 0.0, -g * e0), (-g * e1, g * e0, 0.0))
        Ia, Ip = M.inertia[i, 0], M.inertia[i, 1]
        if M.axisymmetric:
            k = Ia - Ip
            Iw = ((Ip + k * e0 * e0, k * e0 * e1, k * e0 * e2),
                  (k * e1 * e0, Ip + k * e1 * e1, k * e1 * e2),
                  (k * e2 * e0, k * e2 * e1, Ip + k * e2 * e2))
        else:
            qmatrix((q[i, 0], q[i, 1], q[i, 2], q[i, 3]), R)
            r0 = (R[0, 0] * M.inertia[i, 0], R[0, 1] * M.inertia[i, 1], R[0, 2] * M.inertia[i, 2])
            r1 = (R[1, 0] * M.inertia[i, 0], R[1, 1] * M.inertia[i, 1], R[1, 2] * M.inertia[i, 2])
            r2 = (R[2, 0] * M.inertia[i, 0], R[2, 1] * M.inertia[i, 1], R[2, 2] * M.inertia[i, 2])
            Iw = ((r0[0] * R[0, 0] + r0[1] * R[0, 1] + r0[2] * R[0, 2],
                   r0[0] * R[1, 0] + r0[1] * R[1, 1] + r0[2] * R[1, 2],
                   r0[0] * R[2, 0] + r0[1] * R[2, 1] + r0[2] * R[2, 2]),
                  (r1[0] * R[0, 0] + r1[1] * R[0, 1] + r1[2] * R[0, 2],
                   r1[0] * R[1, 0] + r1[1] * R[1, 1] + r1[2] * R[1, 2],
                   r1[0] * R[2, 0] + r1[1] * R[2, 1] + r1[2] * R[2, 2]),
                  (r2[0] * R[0, 0] + r2[1] * R[0, 1] + r2[2] * R[0, 2],
                   r2[0] * R[1, 0] + r2[1] * R[1, 1] + r2[2] * R[1, 2],
                   r2[0] * R[2, 0] + r2[1] * R[2, 1] + r2[2] * R[2, 2]))
        ci = M.damping[i]
        cn = M.damping[i + 1] if M.has_child[i] else 0.0
        im = M.inv_mass[i]
        first = M.is_first[i]
        if not first:
            p0, p1, p2 = qaxis_x_at(q, i - 1)
            gp = M.half[i - 1]
            Sp = ((0.0, -gp * p2, gp * p1), (gp * p2, 0.0, -gp * p0), (-gp * p1, gp * p0, 0.0))
            imp = M.inv_mass[i - 1]
        for a in range(3):
            # Joint i: parent point velocity = child point velocity, with v⁺ substituted:
            #   -v⁺_i - [h_i]× ω⁺_i + v⁺_{i-1} - [h_{i-1}]× ω⁺_{i-1} = 0 (or the anchor's).
            _band_add(ab, LAM + a, LAM + a, -im)
            if M.has_child[i]:
                _band_add(ab, LAM + a, LAM + 6 + a, im)
            for b in range(3):
                _band_add(ab, LAM + a, W + b, -S[a][b])
            if first:
                rhs[LAM + a] = v[i, a] - A.velocity[row, c, a]
            else:
                _band_add(ab, LAM + a, LAM - 6 + a, imp)
                _band_add(ab, LAM + a, LAM + a, -imp)
                for b in range(3):
                    _band_add(ab, LAM + a, W - 6 + b, -Sp[a][b])
                rhs[LAM + a] = v[i, a] - v[i - 1, a]
            # ω rows: (I + h(c_i + c_{i+1})) ω⁺ - h c_i ω⁺_{i-1} - h c_{i+1} ω⁺_{i+1}
            #         + [h]× λ_i + [h]× λ_{i+1} = I ω + h c_i ω_anchor (first joint)
            s = 0.0
            for b in range(3):
                _band_add(ab, W + a, W + b, Iw[a][b])
                _band_add(ab, W + a, LAM + b, S[a][b])
                if M.has_child[i]:
                    _band_add(ab, W + a, LAM + 6 + b, S[a][b])
                s += Iw[a][b] * w[i, b]
            _band_add(ab, W + a, W + a, h * (ci + cn))
            if first:
                s += h * ci * A.angular_velocity[row, c, a]
            else:
                _band_add(ab, W + a, W - 6 + a, -h * ci)
                _band_add(ab, W - 6 + a, W + a, -h * ci)
            rhs[W + a] = s
    if not _band_solve(ab, rhs, _KL):
        return False
    for i in range(n):
        for a in range(3):
            lam_next = rhs[6 * i + 6 + a] if M.has_child[i] else 0.0
            v[i, a] += (rhs[6 * i + a] - lam_next) * M.inv_mass[i]
            w[i, a] = rhs[6 * i + 3 + a]
    return True


@_jit
def _band_solve(ab, b, kl):  # noqa: C901 (LAPACK gbsv's elimination)
    """Solve a banded system (half-bandwidths kl, stored ``ab[r, c - r + 2 kl]``) by Gaussian
    elimination with partial pivoting, like LAPACK's gbsv; ``b`` overwritten. False if
    singular."""
    N = b.shape[0]
    off = 2 * kl
    for k in range(N):
        last = min(k + kl, N - 1)
        p = k
        big = abs(ab[k, off])
        for r in range(k + 1, last + 1):
            val = abs(ab[r, k - r + off])
            if val > big:
                big, p = val, r
        if big == 0.0:
            return False
        top = min(k + 2 * kl, N - 1)
        if p != k:
            for c in range(k, top + 1):
                t = ab[k, c - k + off]
                ab[k, c - k + off] = ab[p, c - p + off]
                ab[p, c - p + off] = t
            t = b[k]
            b[k] = b[p]
            b[p] = t
        piv = ab[k, off]
        for r in range(k + 1, last + 1):
            f = ab[r, k - r + off] / piv
            if f != 0.0:
                for c in range(k + 1, top + 1):
                    ab[r, c - r + off] -= f * ab[k, c - k + off]
                b[r] -= f * b[k]
            ab[r, k - r + off] = 0.0
    for k in range(N - 1, -1, -1):
        s = b[k]
        for c in range(k + 1, min(k + 2 * kl, N - 1) + 1):
            s -= ab[k, c - k + off] * b[c]
        b[k] = s / ab[k, off]
    return True
