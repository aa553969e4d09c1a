"""Constraint forces by Lagrange multipliers: Hecker's A f_c = b, for whole chains at once.

Joint i holds segment i's proximal point on its parent's distal point (or on the anchor):

    C_i = p_parent - p_child = 0                                  (Eq. 12–13)

Differentiated twice (Eq. 14), with the point accelerations of Eq. 3 and the body accelerations
of Eq. 10–11 (the unknown joint forces f_c included), this is a linear system in the joint
forces. With ``r_p = -h`` and ``r_d = +h`` the segment's joint vectors (``h`` = half the
segment, world frame) and ``G = [h]× I⁻¹ [h]×`` (I⁻¹ the world inverse inertia):

    A_ii     = (1/m_i + 1/m_{i-1}) 1 - G_i - G_{i-1}     (the second terms only if i has a parent)
    A_i,i-1  = -(1/m_{i-1} 1 + G_{i-1})
    b_i      = p̈_parent,free - p̈_child,free              (+ Baumgarte terms)

where ``p̈_free`` is a joint point's acceleration under the applied forces alone (gravity,
damping, ..., and the gyroscopic torque -ω × Iω). This ``A = J M⁻¹ Jᵀ`` is symmetric positive
definite and block-tridiagonal with 3×3 blocks: ``solve_banded`` factorises it as a banded
Cholesky (LAPACK ``pbsv``, half-bandwidth 5) in O(n); ``solve_dense`` is the O(n³) cross-check.

Inertia: for axisymmetric segments (principal moments ``(I_a, I_p, I_p)``, the default solid
cylinder) the world inverse inertia is ``I⁻¹ = 1/I_p + (1/I_a - 1/I_p) e eᵀ`` (e the segment
axis) and ``G = (h hᵀ - |h|² 1)/I_p``: no rotation matrices are formed. Other inertias use
``R diag(1/I) Rᵀ``.
``f_c[i]`` is the force joint i applies to its child (``-f_c[i]`` acts on the parent; for the
first joint that reaction is the one the kinematic head never feels).
"""
import numpy as np

from ponytail_ros.core.rotations import cross, quat_axis_x, quat_to_matrix, skew

__all__ = ['Dynamics', 'JointResponse']

def _linalg():
    """``scipy.linalg``, imported at the first NumPy-reference solve: the compiled step never
    needs it, and importing it costs every process start ~0.15 s."""
    import scipy.linalg
    return scipy.linalg


_KD = 5  # half-bandwidth of a block-tridiagonal matrix with 3×3 blocks


def _banded_indices(n):
    """Flat indices into the ``(6, 3n)`` upper banded storage for the diagonal and coupling blocks.

    LAPACK upper storage: ``ab[kd + i - j, j] = A[i, j]`` for ``j - kd <= i <= j``.
    """
    a, b = np.meshgrid(np.arange(3), np.arange(3), indexing='ij')
    upper = (a <= b)
    da, db = a[upper], b[upper]                          # 6 entries of the diagonal block
    j = np.arange(n)[:, None]
    diag_rows = _KD + da - db
    diag_cols = 3 * j + db
    diag_flat = (diag_rows * 3 * n + diag_cols).ravel()
    # Coupling block A[i-1, i] = A[i, i-1]ᵀ: all 9 entries lie inside the band.
    ca, cb = a.ravel(), b.ravel()
    off_rows = 2 + ca - cb
    off_cols = 3 * j + cb
    off_flat = (off_rows * 3 * n + off_cols).ravel()
    return (da, db, diag_flat), (ca, cb, off_flat)


class Dynamics:
    """Accelerations of all segments under applied and constraint forces, for one model."""

    def __init__(self, model, linear_solver='banded', baumgarte=(0.0, 0.0)):
        self.model = model
        self.linear_solver = linear_solver
        self.baumgarte_stiffness, self.baumgarte_damping = baumgarte
        m = model
        n = m.n
        self._diag_idx, self._off_idx = _banded_indices(n)
        # The first joint of every chain has no coupling to the previous segment.
        self._couple = (~m.is_first)[1:, None, None].astype(float)
        I = m.inertia
        self.axisymmetric = bool(np.allclose(I[:, 1], I[:, 2], rtol=1e-12, atol=0.0))
        self._inv_Ia, self._inv_Ip = 1.0 / I[:, 0], 1.0 / I[:, 1]
        self._half = 0.5 * m.length
        self.last_f_c = np.zeros((n, 3))
        self._response = None                   # the last ``joint_response``, reused while q holds

    # -- mass properties in the world frame -------------------------------------------------
    def mass_terms(self, q, w):
        """Half-vectors ``h``, ``G = [h]× I⁻¹ [h]×``, ``I⁻¹·`` and the gyroscopic ω × Iω."""
        h, G, inv_I, gyroscopic = self.inertia_terms(q)
        return h, G, inv_I, gyroscopic(w)

    def inertia_terms(self, q):
        """Half-vectors ``h``, ``G``, ``I⁻¹·`` and ``ω ↦ ω × Iω`` at orientations ``q`` (world)."""
        m = self.model
        if self.axisymmetric:
            e = quat_axis_x(q)
            h = self._half[:, None] * e
            hh = np.sum(h * h, axis=1)
            G = h[:, :, None] * h[:, None, :]
            G[:, [0, 1, 2], [0, 1, 2]] -= hh[:, None]
            G *= self._inv_Ip[:, None, None]
            k = (self._inv_Ia - self._inv_Ip)[:, None]
            inv_Ip = self._inv_Ip[:, None]

            def inv_I(v):
                return v * inv_Ip + (k * np.sum(e * v, axis=1, keepdims=True)) * e

            def gyroscopic(w):
                # L = I_p ω + (I_a - I_p)(e·ω) e, so ω × L = (I_a - I_p)(e·ω) ω × e.
                axial = (m.inertia[:, 0] - m.inertia[:, 1]) * np.sum(e * w, axis=1)
                return axial[:, None] * cross(w, e)
            return h, G, inv_I, gyroscopic
        R = quat_to_matrix(q)
        h = self._half[:, None] * R[:, :, 0]
        inv_I_world = (R * m.inv_inertia[:, None, :]) @ R.transpose(0, 2, 1)
        S = skew(h)
        G = S @ inv_I_world @ S

        def inv_I(v):
            return (inv_I_world @ v[:, :, None])[:, :, 0]

        def gyroscopic(w):
            w_body = (w[:, None, :] @ R)[:, 0, :]                  # Rᵀ ω
            L_ang = (R @ (m.inertia * w_body)[:, :, None])[:, :, 0]
            return cross(w, L_ang)
        return h, G, inv_I, gyroscopic

    def gyroscopic_rates(self, q, w):
        """Rate (rad/s) ``(n,)`` at which the gyroscopic term turns each segment's body-frame ω:
        the spectral radius of I⁻¹([ω]× I - [Iω]×), the Jacobian of I⁻¹(ω × Iω).

        Axisymmetric segments: |ω·e| |1 - I_a/I_p| (a thin segment spinning about its own axis
        at Ω: ≈ Ω). An explicit integrator must resolve it like any other rotation.
        """
        m = self.model
        I = m.inertia
        if self.axisymmetric:
            e = quat_axis_x(q)
            return np.abs(np.sum(w * e, axis=1) * (1.0 - I[:, 0] / I[:, 1]))
        R = quat_to_matrix(q)
        wb = (w[:, None, :] @ R)[:, 0, :]
        K = (skew(wb) * I[:, None, :] - skew(I * wb)) / I[:, :, None]
        return np.max(np.abs(np.linalg.eigvals(K)), axis=1)

    def world_inertia(self, q):
        """World-frame inertia tensors ``(n, 3, 3)``, kg·m²."""
        I = self.model.inertia
        if self.axisymmetric:
            e = quat_axis_x(q)
            return (I[:, 1, None, None] * np.eye(3)
                    + (I[:, 0] - I[:, 1])[:, None, None] * e[:, :, None] * e[:, None, :])
        R = quat_to_matrix(q)
        return (R * I[:, None, :]) @ R.transpose(0, 2, 1)

    # -- the system A f_c = b -------------------------------------------------------------
    def blocks(self, G):
        """Diagonal blocks ``D`` ``(n,3,3)`` and coupling blocks ``L[i] = A[i, i-1]``."""
        inv_m = self.model.inv_mass[:, None, None]
        eye = np.eye(3)
        K_pp = inv_m * eye - G          # K(r_p, r_p) = K(r_d, r_d) since r_d = -r_p
        D = K_pp.copy()
        D[1:] += K_pp[:-1] * self._couple
        L = np.zeros_like(D)
        L[1:] = -(inv_m[:-1] * eye + G[:-1]) * self._couple     # -K(r_d, r_p)
        return D, L

    def solve(self, D, L, b):
        if self.linear_solver == 'banded':
            return self.solve_banded(D, L, b)
        return self.solve_dense(D, L, b)

    def solve_banded(self, D, L, b):
        n = self.model.n
        _, x, info = _linalg().lapack.dpbsv(self.band(D, L), b.reshape(-1), lower=0,
                                            overwrite_ab=1, overwrite_b=0)
        if info != 0:
            raise np.linalg.LinAlgError(f'J M⁻¹ Jᵀ is not positive definite (pbsv info={info})')
        return x.reshape(n, 3)

    def band(self, D, L):
        """``A`` in LAPACK's upper banded storage ``(6, 3n)``."""
        n = self.model.n
        ab = np.zeros((_KD + 1, 3 * n))
        da, db, dflat = self._diag_idx
        ab.flat[dflat] = D[:, da, db].ravel()
        ca, cb, oflat = self._off_idx
        # A[i-1, i][a, b] = L[i][b, a]; the row for i = 0 falls outside and stays zero.
        ab.flat[oflat[9:]] = L[1:, cb, ca].ravel()
        return ab

    def assemble_dense(self, D, L):
        n = self.model.n
        A = np.zeros((n, 3, n, 3))
        idx = np.arange(n)
        A[idx, :, idx, :] = D
        A[idx[1:], :, idx[1:] - 1, :] = L[1:]
        A[idx[1:] - 1, :, idx[1:], :] = L[1:].transpose(0, 2, 1)
        return A.reshape(3 * n, 3 * n)

    def solve_dense(self, D, L, b):
        return np.linalg.solve(self.assemble_dense(D, L), b.reshape(-1)).reshape(-1, 3)

    def _apply_joint_forces(self, f_c, h, inv_I):
        """Δa, Δα of every segment from joint forces ``f_c`` (+ at proximal, - at distal)."""
        f_next = self.model.distal_side(f_c)
        return ((f_c - f_next) * self.model.inv_mass[:, None],
                inv_I(cross(f_c + f_next, h)))          # (-h) × f_c + h × (-f_next)

    # -- accelerations --------------------------------------------------------------------
    def accelerations(self, x, q, v, w, anchor, F, T):
        """Linear and angular accelerations ``(n, 3)`` each, the constraints enforced.

        ``anchor``: ``AnchorKinematics`` per chain (attachment point motion, world frame).
        ``F``, ``T``: applied forces and torques (without the gyroscopic term), N and N·m.
        """
        m = self.model
        h, G, inv_I, gyro = self.mass_terms(q, w)
        D, L = self.blocks(G)
        a_free = F * m.inv_mass[:, None]
        al_free = inv_I(T - gyro)                      # Eq. 11 without f_c
        # Joint-point accelerations under applied forces only (Eq. 3), r_d = h, r_p = -h.
        w_x_h = cross(w, h)
        tang = cross(al_free, h) + cross(w, w_x_h)
        b = self.model.parent_side(anchor.acceleration, a_free + tang) - (a_free - tang)
        if self.baumgarte_stiffness or self.baumgarte_damping:
            gap, gap_rate = self.constraint_error(x, v, h, w_x_h, anchor)
            b += self.baumgarte_damping * gap_rate + self.baumgarte_stiffness * gap
        f_c = self.solve(D, L, b)
        self.last_f_c = f_c
        da, dal = self._apply_joint_forces(f_c, h, inv_I)
        return a_free + da, al_free + dal

    def constraint_error(self, x, v, h, w_x_h, anchor):
        """Position and velocity error ``C``, ``Ċ`` of every joint (parent minus child)."""
        return (self.model.parent_side(anchor.position, x + h) - (x - h),
                self.model.parent_side(anchor.velocity, v + w_x_h) - (v - w_x_h))

    def implicit_damping(self, x, q, v, w, anchor, h):
        """Velocities ``(v⁺, ω⁺)`` after a step ``h`` of joint damping, implicit and constrained.

        Joint damping is stiff (rates up to ~4c/I_min: a thin segment twists easily, a short
        thick one swings fast), beyond explicit RK4 at game steps. Implicit Euler on the
        constrained system is stable for any ``h`` and never adds energy:

            (M + h C) u⁺ - Jᵀ λ = M u + h c₀ ω_anchor      (C: block Laplacian of the dampers)
            J u⁺ = anchor velocity terms                     (every joint closed, Ċ = 0)

        The joints must be in the same solve: damping the first joint's light segment and
        then projecting would hand most of its loss back to the chain it drags. Unknowns
        ordered per segment (v_i, ω_i, λ_i) make the KKT matrix banded (half-bandwidth 17):
        a banded LU in O(n).
        """
        m = self.model
        n = m.n
        c = m.damping
        c_next = m.distal_side(c[:, None])[:, 0]
        hv = self.mass_terms(q, w)[0]                 # half-vectors
        S = skew(hv)
        eye = np.eye(3)
        I_w = self.world_inertia(q)
        N = 9 * n
        kl = ku = 17
        ab = np.zeros((2 * kl + ku + 1, N))           # gbsv storage (kl extra rows for pivots)
        rhs = np.zeros((n, 3, 3))                     # per segment: v rows, ω rows, λ rows

        def put(rows, cols, blocks):
            """Scatter 3×3 ``blocks`` at block rows/cols (unknown offsets) into band storage."""
            r = rows[:, None, None] + np.arange(3)[None, :, None]
            cc = cols[:, None, None] + np.arange(3)[None, None, :]
            r, cc = np.broadcast_arrays(r, cc)
            ab[kl + ku + r - cc, cc] += blocks

        seg = np.arange(n)
        V, W, LAM = 9 * seg, 9 * seg + 3, 9 * seg + 6
        has_p = ~m.is_first
        has_c = m.has_child
        # v rows: m v⁺ - λ_i + λ_{i+1} = m v
        put(V, V, m.mass[:, None, None] * eye)
        put(V, LAM, np.broadcast_to(-eye, (n, 3, 3)))
        put(V[has_c], LAM[np.nonzero(has_c)[0] + 1], np.broadcast_to(eye, (has_c.sum(), 3, 3)))
        rhs[:, 0] = m.mass[:, None] * v
        # ω rows: (I + h(c_i + c_{i+1})) ω⁺ - h c_i ω⁺_{i-1} - h c_{i+1} ω⁺_{i+1}
        #         + [h]× λ_i + [h]× λ_{i+1} = I ω + h c_i ω_anchor (first joint)
        put(W, W, I_w + (h * (c + c_next))[:, None, None] * eye)
        ip = np.nonzero(has_p)[0]
        put(W[ip], W[ip - 1], -(h * c[ip])[:, None, None] * eye)
        put(W[ip - 1], W[ip], -(h * c[ip])[:, None, None] * eye)
        put(W, LAM, S)
        put(W[has_c], LAM[np.nonzero(has_c)[0] + 1], S[has_c])
        rhs[:, 1] = (I_w @ w[:, :, None])[:, :, 0]
        rhs[m.is_first, 1] += (h * c[m.is_first])[:, None] * anchor.angular_velocity
        # λ rows: parent point velocity - child point velocity = 0
        #   child:  v_i + [h_i]× ω_i;   parent: v_{i-1} - [h_{i-1}]× ω_{i-1}, or the anchor's.
        put(LAM, V, np.broadcast_to(-eye, (n, 3, 3)))
        put(LAM, W, -S)
        put(LAM[ip], V[ip - 1], np.broadcast_to(eye, (ip.size, 3, 3)))
        put(LAM[ip], W[ip - 1], -S[ip - 1])
        rhs[m.is_first, 2] = -anchor.velocity
        _, _, x_sol, info = _linalg().lapack.dgbsv(kl, ku, ab, rhs.reshape(-1), overwrite_ab=1)
        if info != 0:
            raise np.linalg.LinAlgError(
                f'implicit damping KKT system is singular (gbsv info={info})')
        sol = x_sol.reshape(n, 3, 3)
        return sol[:, 0], sol[:, 1]

    def velocity_correction(self, x, q, v, w, anchor):
        """Mass-weighted velocity change that closes every joint's velocity error (Ċ = 0).

        Solves J M⁻¹ Jᵀ λ = Ċ for joint impulses λ (N·s): the physical response of the chain
        to an impulse. Returns ``(Δv, Δω)``.
        """
        h, G, inv_I, _ = self.mass_terms(q, w)
        D, L = self.blocks(G)
        _, c_dot = self.constraint_error(x, v, h, cross(w, h), anchor)
        return self._apply_joint_forces(self.solve(D, L, c_dot), h, inv_I)

    # -- joint impulses on a factorised A (symplectic Euler) ------------------------------
    def joint_response(self, q):
        """``JointResponse`` of the chains at orientations ``q``: ``A = J M⁻¹ Jᵀ`` factorised once.

        ``A`` depends on the orientations only, and the projection keeps them: the velocity
        projection that ends one symplectic Euler step and the joint correction that starts the
        next see the same ``A``, so the factorisation is kept for the last ``q`` (compared by
        value: contacts and limits turn segments in between).
        """
        r = self._response
        if r is not None and np.array_equal(r.q, q):
            return r
        h, G, inv_I, _ = self.inertia_terms(q)
        D, L = self.blocks(G)
        if self.linear_solver == 'banded':
            c, info = _linalg().lapack.dpbtrf(self.band(D, L), lower=0, overwrite_ab=1)
            if info != 0:
                raise np.linalg.LinAlgError(
                    f'J M⁻¹ Jᵀ is not positive definite (pbtrf info={info})')

            def solve(b):
                x, info = _linalg().lapack.dpbtrs(c, b.reshape(-1, 1), lower=0)
                if info != 0:
                    raise np.linalg.LinAlgError(
                        f'banded triangular solve failed (pbtrs info={info})')
                return x.reshape(-1, 3)
        else:
            factor = _linalg().cho_factor(self.assemble_dense(D, L))

            def solve(b):
                return _linalg().cho_solve(factor, b.reshape(-1)).reshape(-1, 3)
        self._response = JointResponse(self, q.copy(), h, h / self._half[:, None], inv_I, solve)
        return self._response


class JointResponse:
    """The chains' response to joint impulses at one configuration (orientations ``q``).

    ``impulse(r)`` solves ``A λ = r`` (λ: an impulse per joint, N·s, on the child; minus on
    the parent) and returns ``λ`` and the velocity change ``M⁻¹ Jᵀ λ`` it causes,
    ``(Δv, Δω)`` (m/s, rad/s, world). With ``r`` the joints' velocity error (parent side minus
    child side, m/s) that change cancels it, and it is the M-orthogonal (smallest in kinetic
    energy) change that does: on a still anchor it never adds kinetic energy.
    """

    def __init__(self, dynamics, q, h, axes, inv_I, solve):
        self.dynamics, self.q, self.inv_I, self._solve = dynamics, q, inv_I, solve
        self.h, self.axes = h, axes          # half-vectors (m) and unit axes, world, ``(n, 3)``

    def impulse(self, r):
        lam = self._solve(r)
        return lam, self.dynamics._apply_joint_forces(lam, self.h, self.inv_I)
