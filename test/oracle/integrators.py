"""Time integrators: one fixed step ``h`` of the constrained equations of motion.

Each takes a ``system`` (the chains' dynamics at one instant, built by the simulator), the time
``t`` (s), the step ``h`` (s) and the state ``(x, q, v, w)`` (centres m, orientations body to
world, m/s, ω in rad/s world frame), and returns the new state, ω world frame too.
Quaternions are renormalised. ``system`` provides:

    accel(t, x, q, v, w) -> (a, α)     accelerations with the joint forces solved (A f_c = b)
    applied(t, x, q, v, w) -> (F, T)   applied forces and torques (N, N·m; no gyroscopic term)
    anchor(t)                          the attachment points' ``AnchorKinematics``
    dynamics                           the ``solver.Dynamics`` (inertia, A = J M⁻¹ Jᵀ)
    projection                         ``SolverSpec.projection``

- ``rk4``: classical Runge–Kutta, 4th order, four solves per step (``accel`` only). Inside the
  step the angular velocity is carried in each segment's body frame (ω_b = Rᵀ ω, ω̇_b = Rᵀ α,
  q̇ = ½ q ⊗ (ω_b, 0)): body-frame rates vary more slowly along a swinging chain, so the
  error against the references is smaller than with world-frame ω. Joints are put back by
  ``stabilization`` after the step.
- ``symplectic_euler``: 1st order, a constrained symplectic Euler step (SHAKE/RATTLE type):
  kick, drift, joint impulses from the joint gaps the drift would open, velocities projected
  onto the joints at the step's end. One factorisation of A per step (reused by the next step)
  and two triangular solves. Its energy error is a bounded first-order oscillation on a still
  undamped chain, halving with the step (the unconstrained v += h a, ω += h α it replaces
  gains energy without bound), a thin segment's spin about its own axis costs it nothing (any
  rate; see ``rotation_kick``). Beyond its reach (dt·ω ≳ 2) it mostly dissipates rather than
  blowing up. Details in ``symplectic_euler``; figures in ``docs/bench``.
- ``rattle``: 2nd order, the same step as a symmetric kick–drift–kick (Störmer–Verlet with
  RATTLE's joint impulses) around each segment's exact torque-free rotation: same two solves
  and one factorisation per step, the applied forces twice. Its energy error is bounded and
  ∝ dt², axial spin of any rate is exact. Details in ``rattle``.
"""
import numpy as np

from ponytail_ros.core.rotations import (
    cross,
    quat_axis_x,
    quat_conjugate,
    quat_integrate,
    quat_multiply,
    quat_normalize,
    quat_rotate,
)

__all__ = ['symplectic_euler', 'rattle', 'rk4', 'rotation_kick', 'drift', 'torque_kick',
           'free_rotation', 'INTEGRATOR_STEPS']


# -- symplectic Euler ------------------------------------------------------------------------
def rotation_kick(dynamics, q, w, T, h, e=None):
    """Angular velocities ``(n, 3)`` (rad/s, world) after a step ``h`` of the free rotation
    I ω̇ + ω × Iω = T (applied torques ``T``, N·m, world), the gyroscopic term implicit.
    ``e``: the segment axes of ``q`` if already at hand.

    Axisymmetric segments (principal moments I_a about the axis e, I_p across it), with
    ω = ω_a e + ω⊥: the Euler equation splits exactly into

        ω̇_a = T·e / I_a,        I_p ω̇⊥ = T⊥ + I_a ω_a e × ω⊥,        ė = ω⊥ × e

    in the world frame, once the axial part is carried along its axis (``drift`` puts ω_a on
    the new axis). The stiff part of ω × Iω, a rotation of ω⊥ at ~ω_a(1 - I_a/I_p) in the body
    frame (a thin segment spinning at Ω: rate ≈ Ω, the cause of explicit Euler's blow-up), is
    then exactly that transport; what is left, a precession of ω⊥ about e at
    κ = I_a ω_a⁺ / I_p, is integrated by the implicit midpoint rule (a Cayley rotation: |ω⊥|
    kept, stable for any spin). ω_a has no gyroscopic change: the axial spin is conserved
    exactly when no torque acts along the axis (ball-joint forces never do).

    Other inertias: one Newton step on the body-frame Euler equation, implicit Euler
    (Catto, "Numerical Methods", GDC 2015): (I + h([ω]× I - [Iω]×)) Δω = h (T - ω × Iω).
    Stable for any spin, but it damps a fast-spinning segment's swing.
    """
    dyn, m = dynamics, dynamics.model
    I = m.inertia
    if dyn.axisymmetric:
        e = quat_axis_x(q) if e is None else e
        w_a = np.sum(w * e, axis=1)
        T_a = np.sum(T * e, axis=1)
        w_perp = w - w_a[:, None] * e
        T_perp = T - T_a[:, None] * e
        w_a1 = w_a + h * T_a / I[:, 0]
        s = (0.5 * h * I[:, 0] / I[:, 1] * w_a1)[:, None]          # ½ h κ
        y = w_perp + s * cross(e, w_perp) + h * T_perp / I[:, 1, None]
        w_perp1 = (y + s * cross(e, y)) / (1.0 + s * s)             # (1 - s[e]×)⁻¹ y, y ⊥ e
        return w_a1[:, None] * e + w_perp1
    qc = quat_conjugate(q)
    wb, Tb = quat_rotate(qc, w), quat_rotate(qc, T)
    Lb = I * wb
    jac = np.zeros((m.n, 3, 3))
    jac[:, [0, 1, 2], [0, 1, 2]] = I
    jac += h * (_skew(wb) * I[:, None, :] - _skew(Lb))              # ∂(ω × Iω)/∂ω
    dwb = np.linalg.solve(jac, (h * (Tb - cross(wb, Lb)))[:, :, None])[:, :, 0]
    return quat_rotate(q, wb + dwb)


def _skew(v):
    S = np.zeros(v.shape + (3,))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return S


def _swing_rate(dynamics, w, e):
    """The part of ω that turns the segment axes ``e``: ω⊥ for axisymmetric segments (``drift``
    turns them about their own axis separately), else ω."""
    if not dynamics.axisymmetric:
        return w
    return w - np.sum(w * e, axis=1, keepdims=True) * e


def _turned(u, w, h):
    """Vectors ``u`` ``(n, 3)`` turned by the rotation vectors ``h w`` (Rodrigues)."""
    rate = np.sqrt(np.sum(w * w, axis=1, keepdims=True))
    angle = h * rate
    small = angle < 1e-6
    r = np.where(small, 1.0, rate)
    s = np.where(small, h * (1.0 - angle * angle / 6.0), np.sin(angle) / r)       # sin(hω)/ω
    c = np.where(small, 0.5 * h * h, (1.0 - np.cos(angle)) / (r * r))            # (1-cos)/ω²
    w_x_u = cross(w, u)
    return u + s * w_x_u + c * cross(w, w_x_u)


def drift(dynamics, x, q, v, w, h, e=None):
    """Positions, orientations and ω after moving for ``h`` s at the velocities ``v``, ``ω``.

    Axisymmetric segments turn about their own axis by h ω_a, then swing by h ω⊥
    (q⁺ = exp(h ω⊥) ⊗ q ⊗ exp(h ω_a x̂)), and their axial spin is carried onto the new axis,
    ω⁺ = ω_a e⁺ + ω⊥ (see ``rotation_kick``): a spin of any rate moves no joint. Other
    inertias: q⁺ = exp(h ω) ⊗ q, ω unchanged.
    """
    if not dynamics.axisymmetric:
        return x + h * v, quat_normalize(quat_integrate(q, w, h)), w
    e = quat_axis_x(q) if e is None else e
    w_a = np.sum(w * e, axis=1)
    w_perp = w - w_a[:, None] * e
    half = 0.5 * h * w_a
    spin = np.zeros(q.shape)
    spin[:, 0], spin[:, 3] = np.sin(half), np.cos(half)             # exp(h ω_a x̂), body frame
    q1 = quat_normalize(quat_integrate(quat_multiply(q, spin), w_perp, h))
    return x + h * v, q1, w_a[:, None] * quat_axis_x(q1) + w_perp


def _joint_gaps(model, anchor_position, x, hv):
    """Parent side minus child side of every joint (m), half-vectors ``hv`` (m, world)."""
    return model.parent_side(anchor_position, x + hv) - (x - hv)


def _joint_velocity_errors(model, anchor_velocity, v, w, hv):
    """Parent side minus child side of every joint's velocity (m/s), half-vectors ``hv``."""
    w_x_h = cross(w, hv)
    return model.parent_side(anchor_velocity, v + w_x_h) - (v - w_x_h)


def symplectic_euler(system, t, h, x, q, v, w):
    """One constrained symplectic Euler step; state in and out as in the module docstring.

    With u = (v, ω), M the masses and inertias, J the joints' Jacobian at the step's start
    (orientations q) and A = J M⁻¹ Jᵀ (block-tridiagonal, factorised once, ``joint_response``):

    1. kick: v* = v + h F/m, ω* = ``rotation_kick`` (gyroscopic term implicit);
    2. joint impulses: the drift at u* would open the joints by g* (m) at t + h (the anchor
       there); A λ = g*/h gives the impulses λ (N·s) that close them to first order, and
       u⁺ = u* + M⁻¹ Jᵀ λ. This is one simplified-Newton step of SHAKE (the constraint forces
       along J at the start, the positions constrained at the end): the left-rectangle
       variational integrator of the constrained system, whose energy error stays bounded,
       where the acceleration-level form (C̈ = 0, then v += h a) gained energy steadily on
       multi-segment chains. The gaps left are O(h³) (the simulator's projection closes them);
    3. drift at u⁺ (``drift``);
    4. RATTLE-type projection: A(q⁺) μ = Ċ(u⁺) at t + h, u⁺ ← u⁺ + M⁻¹ J(q⁺)ᵀ μ, so the
       velocities leave the step tangent to the joints. M-orthogonal: it never adds kinetic
       energy (a rigid rebuild of v from ω after this step is not, and it blows up).
       The projection keeps q, so the next step's A is this one (not factorised again).

    The simulator then rebuilds the positions from the orientations (closing the O(h³) gaps
    exactly), and leaves the velocities as they are.

    With ``system.projection`` off there is neither the position correction nor step 4: step
    2 solves the velocity form of C̈ = 0 instead (the joint points' curvature ω⊥ × (ω⊥ × r)
    predicted at the step's start, the velocity errors kept, optional Baumgarte terms), and
    the joints drift by O(h²) per step (what Baumgarte stabilisation is for).

    ``system.dynamics.last_f_c`` is set to λ/h, the joint forces on the children (N).
    """
    dyn = system.dynamics
    m = dyn.model
    K = dyn.joint_response(q)              # A at the start: the previous step's end, cached
    e, hv = K.axes, K.h
    F, T = system.applied(t, x, q, v, w)
    v_free = v + h * F * m.inv_mass[:, None]
    w_free = rotation_kick(dyn, q, w, T, h, e)
    a1 = system.anchor(t + h)
    if system.projection:
        # Where the free velocities would take the joints: only the segment axes matter.
        hv_free = _turned(hv, _swing_rate(dyn, w_free, e), h)
        gaps = _joint_gaps(m, a1.position, x + h * v_free, hv_free)
        lam, (dv, dw) = K.impulse(gaps / h)
    else:
        w_swing = _swing_rate(dyn, w, e)
        curvature = cross(w_swing, cross(w_swing, hv))
        a0 = system.anchor(t)
        c_dot0 = _joint_velocity_errors(m, a0.velocity, v, w, hv)
        target = c_dot0
        if dyn.baumgarte_stiffness or dyn.baumgarte_damping:
            gaps0 = _joint_gaps(m, a0.position, x, hv)
            target = c_dot0 - h * (dyn.baumgarte_damping * c_dot0
                                   + dyn.baumgarte_stiffness * gaps0)
        c_dot = _joint_velocity_errors(m, a1.velocity, v_free, w_free, hv)
        r = c_dot + h * (m.parent_side(np.zeros_like(a1.velocity), curvature) + curvature) - target
        lam, (dv, dw) = K.impulse(r)
    dyn.last_f_c = lam / h
    v1 = v_free + dv
    x1, q1, w1 = drift(dyn, x, q, v1, w_free + dw, h, e)
    if system.projection:
        K1 = dyn.joint_response(q1)
        _, (dv, dw) = K1.impulse(_joint_velocity_errors(m, a1.velocity, v1, w1, K1.h))
        v1, w1 = v1 + dv, w1 + dw
    return x1, q1, v1, w1


# -- RATTLE ----------------------------------------------------------------------------------
def torque_kick(dynamics, q, w, T, h, e=None):
    """Angular velocities ``(n, 3)`` (rad/s, world) after the applied torques ``T`` (N·m,
    world) act for ``h`` s at fixed orientations ``q``: ω + h I⁻¹ T, no gyroscopic term (for
    RATTLE it is in ``free_rotation``). Axisymmetric segments: T·e / I_a along the axis e,
    the rest / I_p; other inertias: in the body frame."""
    I = dynamics.model.inertia
    if dynamics.axisymmetric:
        e = quat_axis_x(q) if e is None else e
        T_a = np.sum(T * e, axis=1)
        return w + h * ((T_a / I[:, 0])[:, None] * e + (T - T_a[:, None] * e) / I[:, 1, None])
    return w + h * quat_rotate(q, quat_rotate(quat_conjugate(q), T) / I)


def free_rotation(dynamics, x, q, v, w, h, e=None):
    """Positions, orientations and ω after ``h`` s of free motion: translation at ``v`` and
    the torque-free rotation of each segment, exact for axisymmetric segments.

    With ω = ω_a e + ω⊥ and I_a, I_p the axial and transverse moments, the angular momentum
    L = I_p Ω, Ω = ω⊥ + (I_a / I_p) ω_a e, is fixed in the world: the segment precesses about
    Ω at |Ω| and spins about its own axis at ν = ω_a (1 - I_a / I_p) in the precessing frame,

        q⁺ = exp(h Ω) ⊗ q ⊗ exp(h ν x̂),      ω⁺ = Ω + ν e⁺.

    (ω_a and |ω⊥| are kept; a spin of any rate is exact.) Other inertias: exp(h ω) ⊗ q with ω
    held, first order in the gyroscopic term.
    """
    if not dynamics.axisymmetric:
        return x + h * v, quat_normalize(quat_integrate(q, w, h)), w
    e = quat_axis_x(q) if e is None else e
    Omega = _precession_rate(dynamics, w, e)
    nu = np.sum((w - Omega) * e, axis=1)                         # ω_a (1 - I_a / I_p)
    spin = np.zeros(q.shape)
    spin[:, 0], spin[:, 3] = np.sin(0.5 * h * nu), np.cos(0.5 * h * nu)   # exp(h ν x̂), body
    q1 = quat_normalize(quat_integrate(quat_multiply(q, spin), Omega, h))
    return x + h * v, q1, Omega + nu[:, None] * quat_axis_x(q1)


def rattle(system, t, h, x, q, v, w):
    """One constrained Störmer–Verlet step (RATTLE; Andersen 1983, Hairer–Lubich–Wanner VII.1):
    2nd order, with the same two solves and one factorisation per step as ``symplectic_euler``;
    state in and out as in the module docstring.

    Kick–drift–kick around the exact free motion, each half kick with its joint impulses:

    1. half kick: v½ = v + ½h F/m, ω½ = ω + ½h I⁻¹ T (``torque_kick``), forces at the start;
       joint impulses λ with A(q) from the gaps the drift would open at t + h (as
       ``symplectic_euler`` step 2), added to u½;
    2. drift for h at u½: translation, and each segment's torque-free rotation
       (``free_rotation``: exact for axisymmetric segments, so the gyroscopic term is
       integrated exactly and a spin of any rate about a segment's own axis costs nothing);
    3. half kick with the forces at the step's end (q⁺; the velocity-dependent terms at u½
       extrapolated to the end), then the velocities projected onto the joints with A(q⁺):
       the multipliers μ of RATTLE's second half.

    The kicks are linear in u, so kick and impulses commute and the step is symmetric: 2nd
    order (with axial spin and a turning head too; ``test_core_integrators`` measures it). On
    a still undamped chain its energy error is bounded and ∝ h². Extra cost over
    ``symplectic_euler``: the applied forces once more. Needs ``projection`` (step 3 is
    RATTLE's own). Segments with a custom non-axisymmetric inertia drift with ω held: first
    order in their gyroscopic term.

    ``system.dynamics.last_f_c`` is set to (λ + μ)/h, the mean joint forces on the children
    over the step (N).
    """
    dyn = system.dynamics
    m = dyn.model
    half = 0.5 * h
    K = dyn.joint_response(q)              # A at the start: the previous step's end, cached
    e, hv = K.axes, K.h
    F, T = system.applied(t, x, q, v, w)
    v_half = v + half * F * m.inv_mass[:, None]
    w_half = torque_kick(dyn, q, w, T, half, e)
    a1 = system.anchor(t + h)
    hv_free = _turned(hv, _precession_rate(dyn, w_half, e), h)
    gaps = _joint_gaps(m, a1.position, x + h * v_half, hv_free)
    lam, (dv, dw) = K.impulse(gaps / h)
    v_half, w_half = v_half + dv, w_half + dw
    w_change = w_half - w
    x1, q1, w_half = free_rotation(dyn, x, q, v_half, w_half, h, e)
    # Velocity-dependent forces at the end need u⁺, not known yet: extrapolate u½ by its
    # change over the first half (O(h²) off, so the step stays 2nd order in drag and damping;
    # for a damping rate λ it is stable for h λ ≤ 2, the same as symplectic Euler's bound that
    # ``damping_method='auto'`` keeps). The change is taken before the drift, which only
    # carries the axial spin onto the turned axis.
    F1, T1 = system.applied(t + h, x1, q1, 2.0 * v_half - v, w_half + w_change)
    K1 = dyn.joint_response(q1)
    v1 = v_half + half * F1 * m.inv_mass[:, None]
    w1 = torque_kick(dyn, q1, w_half, T1, half, K1.axes)
    mu, (dv, dw) = K1.impulse(_joint_velocity_errors(m, a1.velocity, v1, w1, K1.h))
    dyn.last_f_c = (lam + mu) / h
    return x1, q1, v1 + dv, w1 + dw


def _precession_rate(dynamics, w, e):
    """The rate Ω at which ``free_rotation`` turns the segment axes ``e``."""
    if not dynamics.axisymmetric:
        return w
    ratio = dynamics.model.inertia[:, 0] / dynamics.model.inertia[:, 1]
    return w - ((1.0 - ratio) * np.sum(w * e, axis=1))[:, None] * e


# -- RK4 -------------------------------------------------------------------------------------
def _q_dot_body(q, wb):
    """q̇ = ½ q ⊗ (ω_b, 0) for body-frame angular velocities ω_b."""
    return 0.5 * quat_multiply(q, np.concatenate([wb, np.zeros((wb.shape[0], 1))], axis=1))


def rk4(system, t, h, x, q, v, w):
    accel = system.accel

    def f(t, x, q, v, wb):
        a, alpha = accel(t, x, q, v, quat_rotate(q, wb))
        return v, _q_dot_body(q, wb), a, quat_rotate(quat_conjugate(q), alpha)

    wb = quat_rotate(quat_conjugate(q), w)
    hh = 0.5 * h
    k1 = f(t, x, q, v, wb)
    k2 = f(t + hh, x + hh * k1[0], q + hh * k1[1], v + hh * k1[2], wb + hh * k1[3])
    k3 = f(t + hh, x + hh * k2[0], q + hh * k2[1], v + hh * k2[2], wb + hh * k2[3])
    k4 = f(t + h, x + h * k3[0], q + h * k3[1], v + h * k3[2], wb + h * k3[3])
    s = h / 6.0
    x1, q1, v1, wb1 = (y + s * (d1 + 2.0 * d2 + 2.0 * d3 + d4)
                       for y, d1, d2, d3, d4 in zip((x, q, v, wb), k1, k2, k3, k4, strict=True))
    q1 = quat_normalize(q1)
    return x1, q1, v1, quat_rotate(q1, wb1)


# The NumPy reference steps by integrator name (what each is: ``step.INTEGRATORS``).
INTEGRATOR_STEPS = {'symplectic_euler': symplectic_euler, 'rattle': rattle, 'rk4': rk4}
