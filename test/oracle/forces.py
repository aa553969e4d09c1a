"""Applied (non-constraint) forces and torques: the F_E and τ_E of Hecker's Eq. 8–9.

Each term is optional; ``applied_forces`` evaluates only the terms the model has switched on,
so a scene that leaves a term out pays nothing for it. Everything is world frame, SI.

Terms:
    gravity      F = m g at the centre of mass.
    damping      at joint i, τ = -c (ω_i - ω_parent) on the child, the opposite on the parent.
                 For the first joint the parent is the kinematic anchor: its share goes nowhere.
                 Evaluated here only when ``solver.implicit_damping`` is off; otherwise the
                 simulator applies it implicitly after each step (``Dynamics.implicit_damping``).
    stiffness    at joint i, τ = -k R_i φ on the child (the opposite on the parent), φ the
                 rotation vector of the child's deviation from its rest orientation relative
                 to the parent, expressed in the child frame.
    drag         per metre of segment, f = -(c₁ + c₂ |u|) u with u = v - wind, applied at the
                 centre (F = f l), plus the torque of the linear part distributed along the
                 segment, τ = -c₁ l³/12 ω⊥ (the quadratic part's torque is neglected).
    external     a user force and torque per segment (e.g. a hit), held until cleared.
"""
import numpy as np

from ponytail_ros.core.rotations import (
    quat_axis_x,
    quat_conjugate,
    quat_multiply,
    quat_rotate,
    quat_to_rotvec,
)

__all__ = ['applied_forces']


def _add_joint_torques(model, tau_child, T):
    """Add joint torques ``tau_child`` on each child and their reaction on the parent segment."""
    T += tau_child
    T -= model.distal_side(tau_child)


def applied_forces(model, x, q, v, w, anchor_q, anchor_w, external=None):
    """Applied force ``F`` and torque ``T`` on every segment, ``(n, 3)`` each (N, N·m).

    ``anchor_q``/``anchor_w``: the anchor body's orientation and ω per chain, ``(C, 4|3)``.
    """
    terms = model.active_terms
    n = model.n
    F = np.zeros((n, 3))
    T = np.zeros((n, 3))
    if terms['gravity']:
        F += model.mass[:, None] * model.gravity
    if terms['damping'] and not model.implicit_damping:
        w_rel = w - model.parent_side(anchor_w, w)
        _add_joint_torques(model, -model.damping[:, None] * w_rel, T)
    if terms['stiffness']:
        # q = q_parent ⊗ q_rest ⊗ q_err: q_err is the deviation in the child frame.
        q_parent = model.parent_side(anchor_q, q)
        q_err = quat_multiply(quat_conjugate(quat_multiply(q_parent, model.q_rest)), q)
        phi = quat_rotate(q, quat_to_rotvec(q_err))
        _add_joint_torques(model, -model.stiffness[:, None] * phi, T)
    if terms['drag']:
        u = v - model.wind
        speed = np.sqrt(np.sum(u * u, axis=1, keepdims=True))
        c1 = model.drag_linear[:, None]
        F -= (c1 + model.drag_quadratic[:, None] * speed) * u * model.length[:, None]
        e = quat_axis_x(q)
        w_perp = w - np.sum(w * e, axis=1, keepdims=True) * e
        T -= c1 * (model.length ** 3 / 12.0)[:, None] * w_perp
    if external is not None:
        F += external[0]
        T += external[1]
    return F, T
