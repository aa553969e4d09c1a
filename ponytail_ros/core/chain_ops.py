"""Operations on the chains' state outside the step: the rest pose, the joints closed from the
orientations, an impulse's response, the state carried rigidly by the anchors.

The joints are closed by the compiled kernels the contact stage uses
(``contact_joints.project_positions``, ``project_velocities``, and ``joint_factors`` with
``joint_projection`` for the mass-weighted response), so these equations exist once. They take
the model's constant tuple (``joint_args``, the layout of ``contact_model.LENGTH`` ...).
All arrays are world frame, SI (``state`` module).
"""
import numpy as np

from . import contact_joints
from .rotations import (
    cross,
    quat_conjugate,
    quat_from_two_vectors,
    quat_integrate,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    quat_to_matrix,
    skew,
)
from .state import ChainState, half_vectors

__all__ = ['joint_args', 'is_axisymmetric', 'closed_state', 'rest_state', 'state_ahead',
           'apply_impulse', 'carry_with_anchors', 'gyroscopic_rates', 'energy']

_X = np.array([1.0, 0.0, 0.0])


def _c(a):
    return np.ascontiguousarray(a, dtype=float)


def is_axisymmetric(model):
    """Whether every segment's principal moments are ``(I_a, I_p, I_p)`` (to rounding)."""
    I = model.inertia
    return bool(np.allclose(I[:, 1], I[:, 2], rtol=1e-12, atol=0.0))


def joint_args(model):
    """The model's constant tuple of the compiled joint and contact kernels
    (``contact_model.LENGTH`` ... ``TWIST_LIMIT``)."""
    i64 = np.int64
    lim = np.flatnonzero(np.isfinite(model.swing_limit)
                         | np.isfinite(model.twist_limit)).astype(i64)
    return (model.length.astype(float), model.inv_mass.astype(float), _c(model.inv_inertia),
            model.inv_inertia.max(axis=1), model.is_first.copy(), model.has_child.copy(),
            model.parent.astype(i64), model.chain_of.astype(i64),
            model.chain_start.astype(i64), model.chain_end.astype(i64),
            is_axisymmetric(model), lim, model.swing_limit.astype(float),
            model.twist_limit.astype(float))


def closed_state(model, args, anchor, q, w):
    """The state with orientations ``q`` and angular velocities ``w`` ``(n, 4|3)`` whose joints
    are exactly closed on the anchors ``anchor`` (``AnchorKinematics``): every centre placed
    from its parent's distal joint, every centre's velocity the rigid chain's."""
    n = model.n
    h = _c(half_vectors(model.length, q))
    x, v = np.empty((n, 3)), np.empty((n, 3))
    w = _c(w)
    contact_joints.project_positions(_c(anchor.position), h, args, x)
    contact_joints.project_velocities(_c(anchor.velocity), w, h, args, v)
    return ChainState(x, _c(q), v, w.copy())


def rest_state(model, args, head, anchor):
    """Every chain at rest on ``head`` (a ``KinematicState``), its anchors ``anchor``: every
    segment along its chain's rest direction (given in the anchor frame, its twist following
    the anchor; or along gravity, by the shortest arc), the chain moving rigidly with its
    anchor body."""
    g = model.gravity
    down = g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0.0, 0.0, -1.0])
    local = ~np.isnan(model.rest_direction[:, 0])
    d_local = np.where(local[:, None], model.rest_direction, 1.0)
    q_chain = np.where(
        local[:, None],
        quat_multiply(anchor.orientation,
                      quat_from_two_vectors(np.broadcast_to(_X, d_local.shape), d_local)),
        quat_from_two_vectors(_X, down)[None])
    w = head.angular_velocity[model.anchor_body][model.chain_of]
    return closed_state(model, args, anchor, q_chain[model.chain_of], w)


def state_ahead(model, args, state, anchor, tau):
    """``state`` carried ``tau`` s ahead: every orientation turned by its ω (q ← exp(ωτ) q),
    the joints closed on ``anchor`` (the anchors at that time)."""
    return closed_state(model, args, anchor, quat_integrate(state.q, state.w, tau), state.w)


def apply_impulse(model, args, state, anchor, segment, impulse, r):
    """``state``'s velocities after an impulse (N·s, world) on ``segment`` at ``r`` (m, from its
    centre), in place: the free kick, then the joint impulses that close every joint's
    velocity again (J M⁻¹ Jᵀ λ = Ċ, the M-orthogonal projection), so the chain responds as a
    whole. False if J M⁻¹ Jᵀ is not positive definite."""
    n = model.n
    q = _c(state.q)
    h, inv_I = np.empty((n, 3)), np.empty((n, 3, 3))
    C, Lo = np.empty((n, 3, 3)), np.empty((n, 3, 3))
    if not contact_joints.joint_factors(q, args, h, inv_I, C, Lo):
        return False
    v, w = _c(state.v).copy(), _c(state.w).copy()
    v[segment] += impulse * model.inv_mass[segment]
    w[segment] += inv_I[segment] @ cross(r, impulse)
    contact_joints.joint_projection(v, w, _c(anchor.velocity), h, inv_I, C, Lo, args,
                                     np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)))
    state.v[:], state.w[:] = v, w
    return True


def carry_with_anchors(model, a0, a1, x, q, v, w):
    """The chains' state ``(x, q, v, w)`` moved rigidly with their anchor bodies from the
    ``AnchorKinematics`` ``a0`` to ``a1``: positions and orientations transformed with the
    anchor, velocities so that the motion relative to the anchor body is kept. Joints that were
    closed (in position and velocity) stay closed; a static anchor moves nothing."""
    c = model.chain_of
    dq = quat_multiply(a1.orientation, quat_conjugate(a0.orientation))[c]
    p0, w0, w1 = a0.position[c], a0.angular_velocity[c], a1.angular_velocity[c]
    r = quat_rotate(dq, x - p0)
    v_rel = v - a0.velocity[c] - cross(w0, x - p0)         # relative to the anchor body
    return (a1.position[c] + r, quat_normalize(quat_multiply(dq, q)),
            a1.velocity[c] + cross(w1, r) + quat_rotate(dq, v_rel), w1 + quat_rotate(dq, w - w0))


def gyroscopic_rates(model, q, w):
    """Rate (rad/s) ``(n,)`` at which the gyroscopic term turns each segment's body-frame ω,
    for any inertia: the spectral radius of I⁻¹([ω]× I - [Iω]×), the Jacobian of
    I⁻¹(ω × Iω). (Axisymmetric segments: |ω·e| |1 - I_a/I_p|, ``state_kernels``.)"""
    I = model.inertia
    R = quat_to_matrix(q)
    wb = (w[:, None, :] @ R)[:, 0, :]
    K = (skew(wb) * I[:, None, :] - skew(I * wb)) / I[:, :, None]
    return np.max(np.abs(np.linalg.eigvals(K)), axis=1)


def energy(model, state):
    """Kinetic and gravitational potential energy of every chain, ``(C,)`` each, J."""
    R = quat_to_matrix(state.q)
    w_body = np.einsum('nji,nj->ni', R, state.w)
    ke = (0.5 * model.mass * np.sum(state.v ** 2, axis=1)
          + 0.5 * np.sum(model.inertia * w_body ** 2, axis=1))
    pe = -model.mass * (state.x @ model.gravity)
    per_chain = np.zeros((2, model.n_chains))
    np.add.at(per_chain[0], model.chain_of, ke)
    np.add.at(per_chain[1], model.chain_of, pe)
    return per_chain[0], per_chain[1]
