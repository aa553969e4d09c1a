"""Applied forces and torques of the compiled step (the terms of ``test/oracle/forces.py``,
per segment): gravity, explicit joint damping, bending stiffness, drag with wind, external
forces.

Frames and units: world frame (REP 103), SI: forces N, torques N·m; the state arrays are
``step``'s.
"""
import numba as nb
import numpy as np

from .vec import qaxis_x_at, qmul_s, qrot_s, qto_rotvec

__all__ = ['applied_forces', 'applied_terms']

_inline = nb.njit(cache=True, inline='always')


@_inline
def applied_forces(M, A, row, x, q, v, w, ext_F, ext_T, F, T):
    """``applied_terms`` of the whole model ``M`` and table ``A`` (the constrained steps)."""
    applied_terms(row, x, q, v, w, ext_F, ext_T, F, T, M.mass, M.length, M.chain_of, M.is_first,
             M.damping, M.stiffness, M.q_rest, M.drag_linear, M.drag_quadratic, M.gravity,
             M.wind, M.gravity_on, M.explicit_damping, M.stiffness_on, M.drag_on,
             M.external_on, A.orientation, A.angular_velocity)


# The stage-level helpers of RK4 take only the arrays they use, not the ``StepModel`` and
# ``AnchorTable`` tuples: an inline helper increfs and decrefs every array of a tuple argument at
# every call, and the stages run four times per step.
@_inline
def applied_terms(  # noqa: C901 (one switch per term, per-segment loops)
        row, x, q, v, w, ext_F, ext_T, F, T, mass, length, chain_of, is_first, damping,
        stiffness, q_rest, drag_linear, drag_quadratic, gravity, wind, gravity_on,
        explicit_damping, stiffness_on, drag_on, external_on, anchor_orientation,
        anchor_angular_velocity):
    """Applied forces ``F`` and torques ``T`` (N, N·m, world) on every segment (``oracle.forces``);
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
                rx, ry, rz, rw = qmul_s(px, py, pz, pw, q_rest[i, 0], q_rest[i, 1],
                                       q_rest[i, 2], q_rest[i, 3])
                ex, ey, ez, ew = qmul_s(-rx, -ry, -rz, rw, q[i, 0], q[i, 1], q[i, 2], q[i, 3])
                p0, p1, p2 = qto_rotvec((ex, ey, ez, ew))
                s0, s1, s2 = qrot_s(q[i, 0], q[i, 1], q[i, 2], q[i, 3], p0, p1, p2)
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
            e0, e1, e2 = qaxis_x_at(q, i)
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
