"""The compiled internal step: every stage of a call's steps in one call into compiled code.

``advance(model, anchors, ...)`` takes all the fixed steps of one ``Simulator`` call and runs,
per step, the stage list (the way Box2D v3's ``b2SolverTask`` runs its stages in order):

    1. applied forces      gravity, explicit joint damping, bending stiffness, drag with wind,
                           external forces (``_applied``; a term switched off is skipped);
    2. integrate           RK4 (four joint solves), symplectic Euler or RATTLE (one
                           factorisation of A = J M⁻¹ Jᵀ per step, reused by the next step, two
                           solves); the joint solve is ``chain_solve`` (block Cholesky, O(n));
    3. implicit damping    when joint damping is too stiff for the explicit step: implicit Euler
                           on the constrained system, a banded KKT solve (``_implicit_damping``);
    4. stabilise           positions rebuilt from the orientations and the anchor (joints closed
                           to rounding), for RK4 the velocities too (``_project``).

The model is constant during a call (``StepModel``, like MuJoCo's ``const mjModel*``); the
anchors at every stage time of the call come in one table (``AnchorTable``, row ``2k + j``
for step ``k`` at ``t_k + j h/2``), so no Python runs between stages. The equations are those
of the NumPy modules they replace, written per segment and per joint (``solver`` for A f_c = b,
``integrators`` for the three steps, ``forces``, ``stabilization``); their docstrings derive
them. Compiled with numba: ``nopython``, ``cache=True``, no ``fastmath`` (results are
reproducible bit for bit on one machine).

Frames and units: world frame (REP 103), SI. State arrays: ``x`` ``(n, 3)`` centres, ``q``
``(n, 4)`` (x, y, z, w) body to world, ``v`` ``(n, 3)``, ``w`` ``(n, 3)`` ω in the world frame.
"""
from collections import namedtuple

import numba as nb
import numpy as np

from .chain_solve import invert_pivot, pivot, solve, store_factors
from .limit_kernels import qmatrix, qto_rotvec

__all__ = ['StepModel', 'AnchorTable', 'Integrator', 'INTEGRATORS', 'advance', 'RK4',
           'SYMPLECTIC_EULER', 'RATTLE',
           'OK', 'JOINT_SOLVE_FAILED', 'DAMPING_SOLVE_FAILED', 'SUBSTEPS', 'substeps']

RK4, SYMPLECTIC_EULER, RATTLE = 0, 1, 2
OK, JOINT_SOLVE_FAILED, DAMPING_SOLVE_FAILED, SUBSTEPS = 0, 1, 2, 3

Integrator = namedtuple('Integrator', ['name', 'id', 'order', 'solves_per_step',
                                       'rebuilds_velocities', 'explicit_gyroscopic',
                                       'damping_limit'])
Integrator.__doc__ = """What the simulator needs to know of an integrator, in one record.

``id``: the compiled step's switch; ``order``: of accuracy; ``solves_per_step``: joint solves
with A (RK4: one factorisation and solve per stage; the constrained steps: one factorisation,
reused by the next step, and two solves); ``rebuilds_velocities``: the stabilisation rebuilds
v from ω after the step (RK4; the constrained steps end with their own mass-weighted
projection, which a rebuild would undo); ``explicit_gyroscopic``: ω × Iω is integrated
explicitly, so the guard must watch the precession it can follow (RK4); ``damping_limit``: where
the step's stability region ends on the negative real axis (dt·λ for a decay rate λ): explicit
joint damping is stable while dt·λ_max stays below it (RK4: 2.785, taken as 2.78; the Euler
kicks of the constrained steps: 2)."""

INTEGRATORS = {
    'rk4': Integrator('rk4', RK4, 4, 4, True, True, 2.78),
    'symplectic_euler': Integrator('symplectic_euler', SYMPLECTIC_EULER, 1, 2, False, False,
                                   2.0),
    'rattle': Integrator('rattle', RATTLE, 2, 2, False, False, 2.0),
}

# The model's arrays and switches for one call (n segments, C chains; SI units).
StepModel = namedtuple('StepModel', [
    'length', 'half', 'mass', 'inv_mass', 'inertia', 'inv_inertia',   # (n,) ×4, (n, 3) ×2
    'chain_of', 'is_first', 'has_child',                    # (n,) int64, bool, bool
    'damping', 'stiffness', 'drag_linear', 'drag_quadratic', 'q_rest',   # (n,) ..., (n, 4)
    'gravity', 'wind',                                      # (3,)
    'axisymmetric', 'integrator', 'projection',             # bool, int, bool
    'gravity_on', 'explicit_damping', 'implicit_damping', 'stiffness_on', 'drag_on',
    'external_on', 'baumgarte_stiffness', 'baumgarte_damping',
])
# The anchors (attachment points and anchor bodies) at the stage times, (S, C, 3|4) each.
AnchorTable = namedtuple('AnchorTable', ['position', 'velocity', 'acceleration',
                                         'orientation', 'angular_velocity'])

# Reference counting. numba counts references to every array a function binds, slices or is
# passed, with an atomic increment and decrement each (they were about half of a contact
# step's time). The per-step kernels borrow every array they touch: they allocate nothing and
# return no array, their callers own all of them for the call, so they are compiled without
# it (``_borrow``: ``_nrt=False``, which a callee inherits unless it sets its own). A function
# that allocates sets ``_nrt=True`` (``_jit``): a borrowing caller may call it, since it
# returns no array.
_jit = nb.njit(cache=True, _nrt=True)
_inline = nb.njit(cache=True, inline='always')
_borrow = nb.njit(cache=True, _nrt=False)


# -- small vector and quaternion algebra -------------------------------------------------------
@_inline
def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@_inline
def _qmul(ax, ay, az, aw, bx, by, bz, bw):
    """Hamilton product a ⊗ b."""
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


@_inline
def _qrot(qx, qy, qz, qw, v0, v1, v2):
    """v rotated by q (q need not be exactly unit: the formula of ``rotations.quat_rotate``)."""
    t0, t1, t2 = _cross(qx, qy, qz, v0, v1, v2)
    t0, t1, t2 = 2.0 * t0, 2.0 * t1, 2.0 * t2
    c0, c1, c2 = _cross(qx, qy, qz, t0, t1, t2)
    return v0 + qw * t0 + c0, v1 + qw * t1 + c1, v2 + qw * t2 + c2


@_inline
def _axis(q, i):
    """World direction of segment i's body +X axis (R(q)[:, 0])."""
    x, y, z, w = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
    return 1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)


@_inline
def _from_rotvec(p0, p1, p2):
    """Unit quaternion of the rotation vector p (axis × angle)."""
    angle = np.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    half = 0.5 * angle
    if angle < 1e-8:
        s = 0.5 - angle * angle / 48.0
    else:
        s = np.sin(half) / angle
    return p0 * s, p1 * s, p2 * s, np.cos(half)


@_inline
def _normalize(q, i):
    r = 1.0 / np.sqrt(q[i, 0] ** 2 + q[i, 1] ** 2 + q[i, 2] ** 2 + q[i, 3] ** 2)
    q[i, 0] *= r
    q[i, 1] *= r
    q[i, 2] *= r
    q[i, 3] *= r


# -- mass properties and the joint system ------------------------------------------------------
# The per-segment helpers below take and return scalars (tuples): an inline helper that takes
# arrays and branches pays their reference counts on every call, inside the segment loops.
_ZERO6 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
_ZERO9 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@_inline
def _rotation_matrix(x, y, z, w):
    """Rows of R(q), body to world (the arithmetic of ``limit_kernels.qmatrix``, as
    scalars: no 3×3 scratch array to allocate per call)."""
    return ((1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)),
            (2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)),
            (2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)))


@_inline
def _inv_inertia_axisymmetric(e0, e1, e2, ia, ip):
    """World I⁻¹ = I_p⁻¹ 1 + (I_a⁻¹ - I_p⁻¹) e eᵀ (row-major 9-tuple) of an axisymmetric
    segment of axis e, inverse moments ``ia`` (axial), ``ip`` (1/(kg·m²))."""
    k = ia - ip
    ke0, ke1, ke2 = k * e0, k * e1, k * e2
    return (ke0 * e0 + ip, ke0 * e1, ke0 * e2,
            ke1 * e0, ke1 * e1 + ip, ke1 * e2,
            ke2 * e0, ke2 * e1, ke2 * e2 + ip)


@_inline
def _rdr(Ra, Rb, d):
    """(R diag(d) Rᵀ)_ab from rows a and b of R."""
    s = 0.0
    s += Ra[0] * Rb[0] * d[0]
    s += Ra[1] * Rb[1] * d[1]
    s += Ra[2] * Rb[2] * d[2]
    return s


@_inline
def _inv_inertia_general(R, d):
    """World I⁻¹ = R diag(d) Rᵀ (row-major 9-tuple), d the inverse principal moments."""
    R0, R1, R2 = R
    return (_rdr(R0, R0, d), _rdr(R0, R1, d), _rdr(R0, R2, d),
            _rdr(R1, R0, d), _rdr(R1, R1, d), _rdr(R1, R2, d),
            _rdr(R2, R0, d), _rdr(R2, R1, d), _rdr(R2, R2, d))


@_inline
def _mass_properties(axisymmetric, x, y, z, w, i0, i1, i2):
    """Axis e (the body +X axis in the world, ``_axis``) and world I⁻¹ (row-major 9-tuple) of
    a segment at orientation (x, y, z, w), inverse principal moments (i0, i1, i2) (axial
    first)."""
    if axisymmetric:
        e0, e1, e2 = 1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)
        return e0, e1, e2, _inv_inertia_axisymmetric(e0, e1, e2, i0, i1)
    R = _rotation_matrix(x, y, z, w)
    return R[0][0], R[1][0], R[2][0], _inv_inertia_general(R, (i0, i1, i2))


@_inline
def _block(X, i):
    """The 3×3 block ``X[i]`` as a row-major 9-tuple."""
    return (X[i, 0, 0], X[i, 0, 1], X[i, 0, 2], X[i, 1, 0], X[i, 1, 1], X[i, 1, 2],
            X[i, 2, 0], X[i, 2, 1], X[i, 2, 2])


@_inline
def _store_block(X, i, b):
    X[i, 0, 0], X[i, 0, 1], X[i, 0, 2] = b[0], b[1], b[2]
    X[i, 1, 0], X[i, 1, 1], X[i, 1, 2] = b[3], b[4], b[5]
    X[i, 2, 0], X[i, 2, 1], X[i, 2, 2] = b[6], b[7], b[8]


@_inline
def _mul9(X, v0, v1, v2):
    """The row-major 3×3 ``X`` times v."""
    return (X[0] * v0 + X[1] * v1 + X[2] * v2,
            X[3] * v0 + X[4] * v1 + X[5] * v2,
            X[6] * v0 + X[7] * v1 + X[8] * v2)


@_inline
def _inertia_terms(M, q, e, hv, Iinv):
    """Segment axes ``e``, half-vectors ``hv`` = (l/2) e and world inverse inertias ``Iinv``
    ``(n, 3, 3)`` at orientations ``q``."""
    n = q.shape[0]
    for i in range(n):
        e0, e1, e2, X = _mass_properties(M.axisymmetric, q[i, 0], q[i, 1], q[i, 2], q[i, 3],
                                         M.inv_inertia[i, 0], M.inv_inertia[i, 1],
                                         M.inv_inertia[i, 2])
        _store_block(Iinv, i, X)
        e[i, 0], e[i, 1], e[i, 2] = e0, e1, e2
        g = M.half[i]
        hv[i, 0], hv[i, 1], hv[i, 2] = g * e0, g * e1, g * e2


@_inline
def _apply3(Mx, i, v0, v1, v2):
    """The 3×3 block ``Mx[i]`` times v."""
    return (Mx[i, 0, 0] * v0 + Mx[i, 0, 1] * v1 + Mx[i, 0, 2] * v2,
            Mx[i, 1, 0] * v0 + Mx[i, 1, 1] * v1 + Mx[i, 1, 2] * v2,
            Mx[i, 2, 0] * v0 + Mx[i, 2, 1] * v1 + Mx[i, 2, 2] * v2)


@_inline
def _G_axisymmetric(h0, h1, h2, ip):
    """G = [h]× I⁻¹ [h]× = (h hᵀ - |h|² 1) / I_p of an axisymmetric segment (h ∥ its axis):
    the upper triangle (00, 01, 02, 11, 12, 22)."""
    hh = h0 * h0 + h1 * h1 + h2 * h2
    return ((h0 * h0 - hh) * ip, h0 * h1 * ip, h0 * h2 * ip, (h1 * h1 - hh) * ip,
            h1 * h2 * ip, (h2 * h2 - hh) * ip)


@_inline
def _G_general(h0, h1, h2, X):
    """G = [h]× I⁻¹ [h]× for the world I⁻¹ ``X`` (row-major), with
    [h]× = ((0, -h2, h1), (h2, 0, -h0), (-h1, h0, 0)): the upper triangle."""
    a00 = -h2 * X[3] + h1 * X[6]
    a01 = -h2 * X[4] + h1 * X[7]
    a02 = -h2 * X[5] + h1 * X[8]
    a10 = h2 * X[0] - h0 * X[6]
    a11 = h2 * X[1] - h0 * X[7]
    a12 = h2 * X[2] - h0 * X[8]
    a20 = -h1 * X[0] + h0 * X[3]
    a21 = -h1 * X[1] + h0 * X[4]
    return (a01 * h2 - a02 * h1, -a00 * h2 + a02 * h0, a00 * h1 - a01 * h0,
            -a10 * h2 + a12 * h0, a10 * h1 - a11 * h0, a20 * h1 - a21 * h0)


@_inline
def _joint_row(first, pinv_prev, im, imp, g, gp):
    """Joint i's row of A = J M⁻¹ Jᵀ, factorised (``chain_solve.pivot``):
    ``(ok, 𝓛_i, P_i⁻¹)``. ``g``, ``gp``: G of the child segment and of the parent (upper
    triangles), ``im``, ``imp`` their inverse masses; ``first``: no parent segment (``imp``,
    ``gp`` unused), ``pinv_prev``: the previous row's P⁻¹.

    A_ii = (1/m_i + 1/m_{i-1}) 1 - G_i - G_{i-1},  A_i,i-1 = -(1/m_{i-1} 1 + G_{i-1})."""
    g00, g01, g02, g11, g12, g22 = g
    if first:
        ok, pinv = invert_pivot((im - g00, -g01, -g02, im - g11, -g12, im - g22))
        return ok, _ZERO9, pinv
    p00, p01, p02, p11, p12, p22 = gp
    s = im + imp
    d = (s - g00 - p00, -g01 - p01, -g02 - p02, s - g11 - p11, -g12 - p12, s - g22 - p22)
    l = (-imp - p00, -p01, -p02, -p01, -imp - p11, -p12, -p02, -p12, -imp - p22)
    return pivot(d, l, pinv_prev)


@_inline
def _factor_joints(M, hv, Iinv, C, Lo):
    """A = J M⁻¹ Jᵀ at half-vectors ``hv`` (Hecker's A of Eq. 14 per joint), factorised into
    ``C`` = P⁻¹ and ``Lo`` = 𝓛 (``chain_solve``) in one pass, row by row (``_joint_row``);
    False if A is not positive definite."""
    n = hv.shape[0]
    g = pinv = _ZERO6
    for i in range(n):
        gp = g
        h0, h1, h2 = hv[i, 0], hv[i, 1], hv[i, 2]
        if M.axisymmetric:
            g = _G_axisymmetric(h0, h1, h2, M.inv_inertia[i, 1])
        else:
            g = _G_general(h0, h1, h2, _block(Iinv, i))
        first = M.is_first[i]
        imp = 0.0 if first else M.inv_mass[i - 1]
        ok, lo, pinv = _joint_row(first, pinv, M.inv_mass[i], imp, g, gp)
        if not ok:
            return False
        store_factors(C, Lo, i, pinv, lo)
    return True


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
        t0, t1, t2 = _cross(f0 + g0, f1 + g1, f2 + g2, hv[i, 0], hv[i, 1], hv[i, 2])
        dw[i, 0], dw[i, 1], dw[i, 2] = _apply3(Iinv, i, t0, t1, t2)


# -- applied forces ----------------------------------------------------------------------------
@_inline
def _applied_forces(M, A, row, x, q, v, w, ext_F, ext_T, F, T):
    """``_applied`` of the whole model ``M`` and table ``A`` (the constrained steps)."""
    _applied(row, x, q, v, w, ext_F, ext_T, F, T, M.mass, M.length, M.chain_of, M.is_first,
             M.damping, M.stiffness, M.q_rest, M.drag_linear, M.drag_quadratic, M.gravity,
             M.wind, M.gravity_on, M.explicit_damping, M.stiffness_on, M.drag_on,
             M.external_on, A.orientation, A.angular_velocity)


# The stage-level helpers of RK4 below take only the arrays they use, not the ``StepModel`` and
# ``AnchorTable`` tuples: an inline helper increfs and decrefs every array of a tuple argument at
# every call, and the stages run four times per step.
@_inline
def _applied(row, x, q, v, w, ext_F, ext_T, F, T, mass, length, chain_of, is_first, damping,
             stiffness, q_rest, drag_linear, drag_quadratic, gravity, wind, gravity_on,
             explicit_damping, stiffness_on, drag_on, external_on, anchor_orientation,
             anchor_angular_velocity):
    """Applied forces ``F`` and torques ``T`` (N, N·m, world) on every segment (``forces``);
    the model's arrays and switches are ``StepModel``'s, the anchors' ``AnchorTable``'s."""
    n = x.shape[0]
    for i in range(n):
        for a in range(3):
            F[i, a] = mass[i] * gravity[a] if gravity_on else 0.0
            T[i, a] = 0.0
    if explicit_damping or stiffness_on:
        for i in range(n):
            c = chain_of[i]
            tau0, tau1, tau2 = 0.0, 0.0, 0.0
            if explicit_damping:
                if is_first[i]:
                    pw0 = anchor_angular_velocity[row, c, 0]
                    pw1 = anchor_angular_velocity[row, c, 1]
                    pw2 = anchor_angular_velocity[row, c, 2]
                else:
                    pw0, pw1, pw2 = w[i - 1, 0], w[i - 1, 1], w[i - 1, 2]
                k = damping[i]
                tau0 -= k * (w[i, 0] - pw0)
                tau1 -= k * (w[i, 1] - pw1)
                tau2 -= k * (w[i, 2] - pw2)
            if stiffness_on:
                # q = q_parent ⊗ q_rest ⊗ q_err: q_err is the deviation in the child frame.
                if is_first[i]:
                    px = anchor_orientation[row, c, 0]
                    py = anchor_orientation[row, c, 1]
                    pz = anchor_orientation[row, c, 2]
                    pw = anchor_orientation[row, c, 3]
                else:
                    px, py, pz, pw = q[i - 1, 0], q[i - 1, 1], q[i - 1, 2], q[i - 1, 3]
                rx, ry, rz, rw = _qmul(px, py, pz, pw, q_rest[i, 0], q_rest[i, 1],
                                       q_rest[i, 2], q_rest[i, 3])
                ex, ey, ez, ew = _qmul(-rx, -ry, -rz, rw, q[i, 0], q[i, 1], q[i, 2], q[i, 3])
                p0, p1, p2 = qto_rotvec((ex, ey, ez, ew))
                s0, s1, s2 = _qrot(q[i, 0], q[i, 1], q[i, 2], q[i, 3], p0, p1, p2)
                k = stiffness[i]
                tau0 -= k * s0
                tau1 -= k * s1
                tau2 -= k * s2
            T[i, 0] += tau0
            T[i, 1] += tau1
            T[i, 2] += tau2
            if not is_first[i]:
                T[i - 1, 0] -= tau0
                T[i - 1, 1] -= tau1
                T[i - 1, 2] -= tau2
    if drag_on:
        for i in range(n):
            u0 = v[i, 0] - wind[0]
            u1 = v[i, 1] - wind[1]
            u2 = v[i, 2] - wind[2]
            speed = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
            c1 = drag_linear[i]
            k = (c1 + drag_quadratic[i] * speed) * length[i]
            F[i, 0] -= k * u0
            F[i, 1] -= k * u1
            F[i, 2] -= k * u2
            e0, e1, e2 = _axis(q, i)
            wa = w[i, 0] * e0 + w[i, 1] * e1 + w[i, 2] * e2
            kt = c1 * (length[i] ** 3 / 12.0)
            T[i, 0] -= kt * (w[i, 0] - wa * e0)
            T[i, 1] -= kt * (w[i, 1] - wa * e1)
            T[i, 2] -= kt * (w[i, 2] - wa * e2)
    if external_on:
        for i in range(n):
            for a in range(3):
                F[i, a] += ext_F[i, a]
                T[i, a] += ext_T[i, a]


@_inline
def _gyroscopic(axisymmetric, I0, I1, I2, e0, e1, e2, qx, qy, qz, qw, w0, w1, w2):
    """ω × Iω (world) of a segment of principal moments (I0, I1, I2), axis e, orientation q.
    Scalars only: an inline helper taking arrays would pay their reference counts per call."""
    if axisymmetric:
        s = (I0 - I1) * (e0 * w0 + e1 * w1 + e2 * w2)
        c0, c1, c2 = _cross(w0, w1, w2, e0, e1, e2)
        return s * c0, s * c1, s * c2
    b0, b1, b2 = _qrot(-qx, -qy, -qz, qw, w0, w1, w2)
    l0, l1, l2 = _qrot(qx, qy, qz, qw, I0 * b0, I1 * b1, I2 * b2)
    return _cross(w0, w1, w2, l0, l1, l2)


# -- RK4: accelerations with the joint forces solved (A f_c = b) --------------------------------
@_inline
def _accelerations(row, x, q, v, w, F, T, hv, Iinv, C, Lo, acc, alpha, f_c, half, inv_mass,
                   inertia, inv_inertia, chain_of, is_first, has_child, axisymmetric,
                   baumgarte_stiffness, baumgarte_damping, anchor_position, anchor_velocity,
                   anchor_acceleration):
    """Linear and angular accelerations (m/s², rad/s²) with every joint enforced
    (``solver.Dynamics.accelerations``) under the applied forces ``F``, ``T``, ``f_c`` the
    joint forces (N); False if A is not positive definite.

    Two sweeps, the factorisation's own (``chain_solve``):
      root to tip, per segment i: its mass properties and free accelerations (Eq. 11 without
        f_c), joint i's right-hand side (Eq. 3), joint i's row of A factorised and the
        right-hand side forward-substituted. The factorisation is a chain of dependent
        divisions from joint to joint; the segment's own work beside it fills the wait.
      tip to root: the back substitution, and each segment's joint forces applied.
    The arithmetic of every value is that of ``_inertia_terms``, ``_factor_joints``,
    ``chain_solve.solve`` and ``_apply_joint_impulses`` in turn."""
    n = x.shape[0]
    baumgarte = baumgarte_stiffness != 0.0 or baumgarte_damping != 0.0
    g = pinv = _ZERO6                   # G and P⁻¹ of the previous segment / joint
    z0 = z1 = z2 = 0.0                  # the previous joint's forward-substituted rhs
    pa0 = pa1 = pa2 = 0.0               # the previous segment's distal-point acceleration
    for i in range(n):
        first = is_first[i]
        e0, e1, e2, X = _mass_properties(axisymmetric, q[i, 0], q[i, 1], q[i, 2], q[i, 3],
                                         inv_inertia[i, 0], inv_inertia[i, 1],
                                         inv_inertia[i, 2])
        _store_block(Iinv, i, X)
        hl = half[i]
        h0, h1, h2 = hl * e0, hl * e1, hl * e2
        hv[i, 0], hv[i, 1], hv[i, 2] = h0, h1, h2
        # Free accelerations (Eq. 11 without f_c) and the joint points' under them (Eq. 3):
        # r_d = h, r_p = -h.
        w0, w1, w2 = w[i, 0], w[i, 1], w[i, 2]
        y0, y1, y2 = _gyroscopic(axisymmetric, inertia[i, 0], inertia[i, 1],
                                 inertia[i, 2], e0, e1, e2, q[i, 0], q[i, 1], q[i, 2],
                                 q[i, 3], w0, w1, w2)
        a0, a1, a2 = _mul9(X, T[i, 0] - y0, T[i, 1] - y1, T[i, 2] - y2)
        alpha[i, 0], alpha[i, 1], alpha[i, 2] = a0, a1, a2
        im = inv_mass[i]
        ac0, ac1, ac2 = F[i, 0] * im, F[i, 1] * im, F[i, 2] * im
        acc[i, 0], acc[i, 1], acc[i, 2] = ac0, ac1, ac2
        c0, c1, c2 = _cross(a0, a1, a2, h0, h1, h2)
        u0, u1, u2 = _cross(w0, w1, w2, h0, h1, h2)              # ω × h
        d0, d1, d2 = _cross(w0, w1, w2, u0, u1, u2)
        t0, t1, t2 = c0 + d0, c1 + d1, c2 + d2                   # tangential + centripetal
        # Joint i's right-hand side: parent point minus child point acceleration.
        if first:
            c = chain_of[i]
            pa0 = anchor_acceleration[row, c, 0]
            pa1 = anchor_acceleration[row, c, 1]
            pa2 = anchor_acceleration[row, c, 2]
        r0, r1, r2 = pa0 - (ac0 - t0), pa1 - (ac1 - t1), pa2 - (ac2 - t2)
        if baumgarte:
            r0 += _baumgarte(row, x, v, w, hv, i, 0, u0, chain_of, is_first, anchor_position,
                             anchor_velocity, baumgarte_stiffness, baumgarte_damping)
            r1 += _baumgarte(row, x, v, w, hv, i, 1, u1, chain_of, is_first, anchor_position,
                             anchor_velocity, baumgarte_stiffness, baumgarte_damping)
            r2 += _baumgarte(row, x, v, w, hv, i, 2, u2, chain_of, is_first, anchor_position,
                             anchor_velocity, baumgarte_stiffness, baumgarte_damping)
        pa0, pa1, pa2 = ac0 + t0, ac1 + t1, ac2 + t2
        # Joint i's row of A, factorised; forward substitution (1 + 𝓛) z = b.
        if axisymmetric:
            gi = _G_axisymmetric(h0, h1, h2, inv_inertia[i, 1])
        else:
            gi = _G_general(h0, h1, h2, X)
        imp = 0.0 if first else inv_mass[i - 1]
        ok, lo, pinv = _joint_row(first, pinv, im, imp, gi, g)
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
    # proximal end, - λ_{i+1} at its distal end (``_apply_joint_impulses``).
    l0 = l1 = l2 = 0.0                  # λ_{i+1}
    for i in range(n - 1, -1, -1):
        z0, z1, z2 = f_c[i, 0], f_c[i, 1], f_c[i, 2]
        P = _block(C, i)
        f0, f1, f2 = _mul9(P, z0, z1, z2)
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
        t0, t1, t2 = _cross(f0 + g0, f1 + g1, f2 + g2, hv[i, 0], hv[i, 1], hv[i, 2])
        b0, b1, b2 = _apply3(Iinv, i, t0, t1, t2)
        alpha[i, 0] += b0
        alpha[i, 1] += b1
        alpha[i, 2] += b2
        l0, l1, l2 = f0, f1, f2
    return True


@_borrow
def _baumgarte(row, x, v, w, hv, i, a, wxh, chain_of, is_first, anchor_position,
               anchor_velocity, baumgarte_stiffness, baumgarte_damping):
    """Joint i's Baumgarte term 2ζ Ċ + κ C along axis ``a`` (``wxh`` = (ω × h)_a of segment
    i; segment i-1's ``hv`` already set)."""
    if is_first[i]:
        c = chain_of[i]
        pp = anchor_position[row, c, a]
        pv = anchor_velocity[row, c, a]
    else:
        pp = x[i - 1, a] + hv[i - 1, a]
        pu0, pu1, pu2 = _cross(w[i - 1, 0], w[i - 1, 1], w[i - 1, 2],
                               hv[i - 1, 0], hv[i - 1, 1], hv[i - 1, 2])
        pv = v[i - 1, a] + (pu0, pu1, pu2)[a]
    gap = pp - (x[i, a] - hv[i, a])
    rate = pv - (v[i, a] - wxh)
    return baumgarte_damping * rate + baumgarte_stiffness * gap


@_jit
def _workspace(n):
    """F, T, e, hv ``(n, 3)``; Iinv, C = P⁻¹, Lo = 𝓛 ``(n, 3, 3)``."""
    return (np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)),
            np.empty((n, 3, 3)), np.empty((n, 3, 3)), np.empty((n, 3, 3)))


@_jit
def _rk4_workspace(n):
    """The integrators' scratch: RK4's wb, w_s, xs, qs, vs, wbs, acc, (7: the constrained
    steps' only), sx, sv, sq, swb, α; ``(n, 3)``, the quaternions ``(n, 4)``."""
    return (np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 4)),
            np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)),
            np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 4)), np.empty((n, 3)),
            np.empty((n, 3)))


@_inline
def _rk4_sum(s, weight, total, d):
    """RK4's d₁ + 2 d₂ + 2 d₃ + d₄, summed as the stage derivatives ``d`` come (``s`` =
    0..3)."""
    return d if s == 0 else total + weight * d


@_inline
def _rk4(M, A, k, h, x, q, v, w, ext_F, ext_T, ws, rws, f_c):
    """One classical RK4 step (``integrators.rk4``), ω carried in the body frame inside.

    The right-hand side is (ẋ = v, q̇ = ½ q ⊗ ω_b, v̇ = a, ω̇_b = Rᵀ α), with a, α from
    ``_accelerations`` at the stage's world ω = R ω_b (``w_s``). The stage derivatives are
    summed as they come (d1 + 2 d2 + 2 d3 + d4, in that order), so no stage is stored; each
    segment's derivative, sums and next stage are done in one pass."""
    n = x.shape[0]
    F, T, _, hv, Iinv, C, Lo = ws
    wb, w_s, xs, qs, vs, wbs, acc, _, sx, sv, sq, swb, alpha = rws
    for i in range(n):
        qx, qy, qz, qw = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
        b0, b1, b2 = _qrot(-qx, -qy, -qz, qw, w[i, 0], w[i, 1], w[i, 2])
        wb[i, 0], wb[i, 1], wb[i, 2] = b0, b1, b2
        for a in range(3):
            xs[i, a] = x[i, a]
            vs[i, a] = v[i, a]
        wbs[i, 0], wbs[i, 1], wbs[i, 2] = b0, b1, b2
        qs[i, 0], qs[i, 1], qs[i, 2], qs[i, 3] = qx, qy, qz, qw
        w_s[i, 0], w_s[i, 1], w_s[i, 2] = _qrot(qx, qy, qz, qw, b0, b1, b2)
    hh = 0.5 * h
    for s in range(4):
        row = 2 * k + (0 if s == 0 else (1 if s < 3 else 2))
        _applied(row, xs, qs, vs, w_s, ext_F, ext_T, F, T, M.mass, M.length, M.chain_of,
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
            d0, d1, d2, d3 = _qmul(qx, qy, qz, qw, wbs[i, 0], wbs[i, 1], wbs[i, 2], 0.0)
            e0, e1, e2 = _qrot(-qx, -qy, -qz, qw, alpha[i, 0], alpha[i, 1], alpha[i, 2])
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
                w_s[i, 0], w_s[i, 1], w_s[i, 2] = _qrot(qs[i, 0], qs[i, 1], qs[i, 2], qs[i, 3],
                                                        wbs[i, 0], wbs[i, 1], wbs[i, 2])
    sixth = h / 6.0
    for i in range(n):
        for a in range(3):
            x[i, a] = x[i, a] + sixth * sx[i, a]
            v[i, a] = v[i, a] + sixth * sv[i, a]
            wb[i, a] = wb[i, a] + sixth * swb[i, a]
        for a in range(4):
            q[i, a] = q[i, a] + sixth * sq[i, a]
        _normalize(q, i)
        w[i, 0], w[i, 1], w[i, 2] = _qrot(q[i, 0], q[i, 1], q[i, 2], q[i, 3],
                                          wb[i, 0], wb[i, 1], wb[i, 2])
    return True


# -- symplectic Euler and RATTLE: kicks, drifts and joint impulses -----------------------------
@_jit
def _rotation_kick(M, q, e, Iinv, w, T, h, out):
    """ω after ``h`` of I ω̇ + ω × Iω = T, the gyroscopic term implicit
    (``integrators.rotation_kick``: exact axial transport + implicit midpoint precession for
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
            c0, c1, c2 = _cross(e0, e1, e2, p0, p1, p2)
            y0 = p0 + s * c0 + h * t0 / Ip
            y1 = p1 + s * c1 + h * t1 / Ip
            y2 = p2 + s * c2 + h * t2 / Ip
            c0, c1, c2 = _cross(e0, e1, e2, y0, y1, y2)
            den = 1.0 + s * s
            out[i, 0] = wa1 * e0 + (y0 + s * c0) / den
            out[i, 1] = wa1 * e1 + (y1 + s * c1) / den
            out[i, 2] = wa1 * e2 + (y2 + s * c2) / den
        else:
            qx, qy, qz, qw = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
            b0, b1, b2 = _qrot(-qx, -qy, -qz, qw, w[i, 0], w[i, 1], w[i, 2])
            T0, T1, T2 = _qrot(-qx, -qy, -qz, qw, T[i, 0], T[i, 1], T[i, 2])
            I0, I1, I2 = M.inertia[i, 0], M.inertia[i, 1], M.inertia[i, 2]
            L0, L1, L2 = I0 * b0, I1 * b1, I2 * b2
            # J = I + h([ω]× I - [Iω]×)
            Sw = ((0.0, -b2, b1), (b2, 0.0, -b0), (-b1, b0, 0.0))
            SL = ((0.0, -L2, L1), (L2, 0.0, -L0), (-L1, L0, 0.0))
            Id = (I0, I1, I2)
            for a in range(3):
                for b in range(3):
                    J[a, b] = (Id[a] if a == b else 0.0) + h * (Sw[a][b] * Id[b] - SL[a][b])
            g0, g1, g2 = _cross(b0, b1, b2, L0, L1, L2)
            r[0], r[1], r[2] = h * (T0 - g0), h * (T1 - g1), h * (T2 - g2)
            d0, d1, d2 = _solve3(J, r[0], r[1], r[2])
            out[i, 0], out[i, 1], out[i, 2] = _qrot(qx, qy, qz, qw, b0 + d0, b1 + d1, b2 + d2)


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
    """ω + h I⁻¹ T at fixed orientations, no gyroscopic term (``integrators.torque_kick``)."""
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
            b0, b1, b2 = _qrot(-qx, -qy, -qz, qw, T[i, 0], T[i, 1], T[i, 2])
            r0, r1, r2 = _qrot(qx, qy, qz, qw, b0 / M.inertia[i, 0], b1 / M.inertia[i, 1],
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
    a0, a1, a2 = _cross(w0, w1, w2, u0, u1, u2)
    b0, b1, b2 = _cross(w0, w1, w2, a0, a1, a2)
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
        u0, u1, u2 = _cross(w[i, 0], w[i, 1], w[i, 2], hv[i, 0], hv[i, 1], hv[i, 2])
        child = (v[i, 0] - u0, v[i, 1] - u1, v[i, 2] - u2)
        if M.is_first[i]:
            for a in range(3):
                out[i, a] = A.velocity[row, c, a] - child[a]
        else:
            p0, p1, p2 = _cross(w[i - 1, 0], w[i - 1, 1], w[i - 1, 2],
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
            rx, ry, rz, rw = _from_rotvec(w0 * h, w1 * h, w2 * h)
            q[i, 0], q[i, 1], q[i, 2], q[i, 3] = _qmul(rx, ry, rz, rw, qx, qy, qz, qw)
            _normalize(q, i)
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
        bx, by, bz, bw = _qmul(qx, qy, qz, qw, sx, 0.0, 0.0, sw)     # q ⊗ exp(h·spin x̂)
        rx, ry, rz, rw = _from_rotvec(o0 * h, o1 * h, o2 * h)
        q[i, 0], q[i, 1], q[i, 2], q[i, 3] = _qmul(rx, ry, rz, rw, bx, by, bz, bw)
        _normalize(q, i)
        n0, n1, n2 = _axis(q, i)
        w[i, 0] = o0 + spin * n0
        w[i, 1] = o1 + spin * n1
        w[i, 2] = o2 + spin * n2


@_jit
def _constrained_step(M, A, k, h, x, q, v, w, ext_F, ext_T, ws, rws, f_c, fresh):
    """One symplectic Euler or RATTLE step (``integrators.symplectic_euler`` /
    ``integrators.rattle``). ``fresh``: A must be factorised at q first (else the factors in
    ``ws`` are those of q, left by the previous step's projection). False if a solve fails."""
    F, T, e, hv, Iinv, C, Lo = ws
    n = x.shape[0]
    r0, r1 = 2 * k, 2 * k + 2
    rattle = M.integrator == RATTLE
    if fresh:
        _inertia_terms(M, q, e, hv, Iinv)
        if not _factor_joints(M, hv, Iinv, C, Lo):
            return False
    _applied_forces(M, A, r0, x, q, v, w, ext_F, ext_T, F, T)
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
    _inertia_terms(M, q, e, hv, Iinv)
    if not _factor_joints(M, hv, Iinv, C, Lo):
        return False
    if rattle:
        # Second half kick with the forces at the end; velocity-dependent terms at u½
        # extrapolated by its change over the first half.
        for i in range(n):
            for a in range(3):
                dv[i, a] = 2.0 * v1[i, a] - v0[i, a]
                dw[i, a] = w1[i, a] + w_change[i, a]
        _applied_forces(M, A, r1, x, q, dv, dw, ext_F, ext_T, F, T)
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
        u0, u1, u2 = _cross(s0, s1, s2, hv[i, 0], hv[i, 1], hv[i, 2])
        curv[i, 0], curv[i, 1], curv[i, 2] = _cross(s0, s1, s2, u0, u1, u2)
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


# -- implicit joint damping: the constrained KKT system, banded ---------------------------------
_KL = 8         # half-bandwidth of the reduced KKT matrix, unknowns (λ_i, ω_i) per segment


@_inline
def _band_add(ab, r, c, val):
    ab[r, c - r + 2 * _KL] += val


@_jit
def _implicit_damping(M, A, row, q, v, w, h):
    """Velocities after ``h`` of joint damping, implicit Euler on the constrained system
    (``solver.Dynamics.implicit_damping``), in place; False if singular:

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
        e0, e1, e2 = _axis(q, i)
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
            p0, p1, p2 = _axis(q, i - 1)
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
def _band_solve(ab, b, kl):
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


# -- stabilisation -----------------------------------------------------------------------------
@_inline
def _project(M, A, row, x, q, v, w, velocities):
    """Centres rebuilt so every joint closes exactly from the anchor outward, and for RK4
    (``velocities``) the centre velocities from the anchor point's velocity and the ω above
    (``stabilization``)."""
    n = x.shape[0]
    p0 = p1 = p2 = u0 = u1 = u2 = 0.0
    for i in range(n):
        c = M.chain_of[i]
        if M.is_first[i]:
            p0, p1, p2 = A.position[row, c, 0], A.position[row, c, 1], A.position[row, c, 2]
            u0, u1, u2 = A.velocity[row, c, 0], A.velocity[row, c, 1], A.velocity[row, c, 2]
        e0, e1, e2 = _axis(q, i)
        h0, h1, h2 = M.half[i] * e0, M.half[i] * e1, M.half[i] * e2
        x[i, 0], x[i, 1], x[i, 2] = p0 + h0, p1 + h1, p2 + h2
        p0, p1, p2 = x[i, 0] + h0, x[i, 1] + h1, x[i, 2] + h2
        if velocities:
            c0, c1, c2 = _cross(w[i, 0], w[i, 1], w[i, 2], h0, h1, h2)
            v[i, 0], v[i, 1], v[i, 2] = u0 + c0, u1 + c1, u2 + c2
            u0, u1, u2 = v[i, 0] + c0, v[i, 1] + c1, v[i, 2] + c2


# -- the call ----------------------------------------------------------------------------------
@_inline
def _chain_model(M, s, e):
    """The ``StepModel`` of segments ``s:e`` (one chain): views, no copies."""
    return StepModel(
        M.length[s:e], M.half[s:e], M.mass[s:e], M.inv_mass[s:e], M.inertia[s:e],
        M.inv_inertia[s:e], M.chain_of[s:e], M.is_first[s:e], M.has_child[s:e],
        M.damping[s:e], M.stiffness[s:e], M.drag_linear[s:e], M.drag_quadratic[s:e],
        M.q_rest[s:e], M.gravity, M.wind, M.axisymmetric, M.integrator, M.projection,
        M.gravity_on, M.explicit_damping, M.implicit_damping, M.stiffness_on, M.drag_on,
        M.external_on, M.baumgarte_stiffness, M.baumgarte_damping)


@_borrow
def _chain_steps(M, A, k0, n_steps, h, x, q, v, w, ext_F, ext_T, f_c, ws, rws, constrained):
    """Steps ``k0 .. k0 + n_steps - 1`` of the table of one chain (or any set of whole
    chains). ``constrained`` None: RK4 only (numba prunes the other integrators from that
    version: an RK4 scene does not compile them); True: the model's integrator."""
    for k in range(k0, k0 + n_steps):
        if constrained is None or M.integrator == RK4:
            ok = _rk4(M, A, k, h, x, q, v, w, ext_F, ext_T, ws, rws, f_c)
        else:
            ok = _constrained_step(M, A, k, h, x, q, v, w, ext_F, ext_T, ws, rws, f_c,
                                   k == k0 or not M.projection)
        if not ok:
            return JOINT_SOLVE_FAILED
        if M.implicit_damping:
            if not _implicit_damping(M, A, 2 * k + 2, q, v, w, h):
                return DAMPING_SOLVE_FAILED
        if M.projection:
            _project(M, A, 2 * k + 2, x, q, v, w, M.integrator == RK4)
    return OK


@nb.njit(cache=True, nogil=True)
def advance(M, A, n_steps, h, x, q, v, w, ext_F, ext_T, f_c):
    """``n_steps`` fixed steps of ``h`` s with the anchors of table ``A`` (rows ``2k + j`` at
    ``t_k + j h/2``), the state ``(x, q, v, w)`` updated in place, ``f_c`` ``(n, 3)`` set to
    the joint forces on the children at the last step (N). Returns ``OK`` or the failing
    stage's code (``JOINT_SOLVE_FAILED``, ``DAMPING_SOLVE_FAILED``); the state is then
    unusable.

    Chains do not interact within a step, so the call runs chain by chain, each through all
    its steps: a chain's working set stays in the cache however many chains the scene has.
    """
    starts, ends = _chain_starts(M, x.shape[0])
    W, R = _workspaces(starts, ends)
    return _chains_steps(M, A, 0, n_steps, h, x, q, v, w, ext_F, ext_T, f_c, W, R, starts,
                         ends, True)


@nb.njit(cache=True, nogil=True)
def advance_rk4(M, A, n_steps, h, x, q, v, w, ext_F, ext_T, f_c):
    """``advance`` for a model whose integrator is RK4 (the same results bit for bit),
    compiled without the other integrators."""
    starts, ends = _chain_starts(M, x.shape[0])
    W, R = _workspaces(starts, ends)
    return _chains_steps(M, A, 0, n_steps, h, x, q, v, w, ext_F, ext_T, f_c, W, R, starts,
                         ends, None)


@_borrow
def _chains_steps(M, A, k0, n_steps, h, x, q, v, w, ext_F, ext_T, f_c, W, R, starts, ends,
                  constrained):
    """Steps ``k0 .. k0 + n_steps - 1`` of the table, chain by chain, each chain through all
    of them (its working set stays in the cache; its views borrowed: no reference counts
    however many chains there are). ``constrained``: as ``_chain_steps``."""
    for c in range(starts.shape[0]):
        s, e = starts[c], ends[c]
        ws, rws = _chain_views(W, R, e - s)
        status = _chain_steps(_chain_model(M, s, e), A, k0, n_steps, h, x[s:e], q[s:e],
                              v[s:e], w[s:e], ext_F[s:e], ext_T[s:e], f_c[s:e], ws, rws,
                              constrained)
        if status != OK:
            return status
    return OK


@_jit
def _chain_starts(M, n):
    """Each chain's first segment and one past its last, ``(C,)`` each."""
    starts = np.nonzero(M.is_first)[0]
    ends = np.empty_like(starts)
    for c in range(starts.shape[0]):
        ends[c] = starts[c + 1] if c + 1 < starts.shape[0] else n
    return starts, ends


@_jit
def _workspaces(starts, ends):
    """The joint system's and the integrators' workspaces, sized for the longest chain."""
    longest = 0
    for c in range(starts.shape[0]):
        longest = max(longest, ends[c] - starts[c])
    return _workspace(longest), _rk4_workspace(longest)


@_inline
def _chain_views(W, R, m):
    """The workspaces' first ``m`` rows: one chain's (views, no copies)."""
    return ((W[0][:m], W[1][:m], W[2][:m], W[3][:m], W[4][:m], W[5][:m], W[6][:m]),
            (R[0][:m], R[1][:m], R[2][:m], R[3][:m], R[4][:m], R[5][:m], R[6][:m],
             R[7][:m], R[8][:m], R[9][:m], R[10][:m], R[11][:m], R[12][:m]))


@_borrow
def substeps(M, A, row, w, h, substep_angle, max_substeps):
    """Sub-steps of a step of a scene with contacts or limits: ⌈h |ω_rel|max / angle⌉ (at
    least 1, at most ``max_substeps``), ω_rel every joint's relative angular velocity at the
    step's start (``simulator.SUBSTEP_ANGLE``: an impact cracks the chain like a whip)."""
    rate2 = 0.0
    for i in range(w.shape[0]):
        c = M.chain_of[i]
        d2 = 0.0
        for a in range(3):
            p = A.angular_velocity[row, c, a] if M.is_first[i] else w[i - 1, a]
            d2 += (w[i, a] - p) ** 2
        rate2 = max(rate2, d2)
    return min(max_substeps, max(1, int(np.ceil(np.sqrt(rate2) * h / substep_angle))))
