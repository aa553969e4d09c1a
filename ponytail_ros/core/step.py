"""The compiled internal step: every stage of a call's steps in one call into compiled code.

``advance(model, anchors, ...)`` takes all the fixed steps of one ``Simulator`` call and runs,
per step, the stage list (the way Box2D v3's ``b2SolverTask`` runs its stages in order):

    1. applied forces      gravity, explicit joint damping, bending stiffness, drag with wind,
                           external forces (``applied_forces``; a term switched off is skipped);
    2. integrate           RK4 (four joint solves), symplectic Euler or RATTLE (one
                           factorisation of A = J M⁻¹ Jᵀ per step, reused by the next step, two
                           solves: ``step_rk4``, ``step_constrained``); the joint solve is
                           ``chain_solve`` (block LDLᵀ, O(n));
    3. implicit damping    when joint damping is too stiff for the explicit step: implicit Euler
                           on the constrained system, a banded KKT solve (``implicit_damping``);
    4. stabilise           positions rebuilt from the orientations and the anchor (joints closed
                           to rounding), for RK4 the velocities too (``_project``).

This module drives them (chain by chain, step by step) and holds the stabilisation. The model
is constant during a call (``StepModel``, like MuJoCo's ``const mjModel*``); the
anchors at every stage time of the call come in one table (``AnchorTable``, row ``2k + j``
for step ``k`` at ``t_k + j h/2``), so no Python runs between stages. The equations are those
of the NumPy reference step in the tests, written per segment and per joint (``test/oracle``:
``solver`` for A f_c = b, ``integrators`` for the three steps, ``forces``, ``stabilization``);
their docstrings derive them. Compiled with numba: ``nopython``, ``cache=True``, no
``fastmath`` (results are reproducible bit for bit on one machine).

Frames and units: world frame (REP 103), SI. State arrays: ``x`` ``(n, 3)`` centres, ``q``
``(n, 4)`` (x, y, z, w) body to world, ``v`` ``(n, 3)``, ``w`` ``(n, 3)`` ω in the world frame.
"""
import numba as nb
import numpy as np

from .implicit_damping import implicit_damping
from .step_constrained import constrained_step
from .step_model import (
    DAMPING_SOLVE_FAILED,
    INTEGRATORS,
    JOINT_SOLVE_FAILED,
    OK,
    RATTLE,
    RK4,
    SUBSTEPS,
    SYMPLECTIC_EULER,
    AnchorTable,
    Integrator,
    StepModel,
)
from .step_rk4 import rk4
from .vec import cross_s, qaxis_x_at

__all__ = ['StepModel', 'AnchorTable', 'Integrator', 'INTEGRATORS', 'advance', 'advance_rk4',
           'RK4', 'SYMPLECTIC_EULER', 'RATTLE', 'OK', 'JOINT_SOLVE_FAILED',
           'DAMPING_SOLVE_FAILED', 'SUBSTEPS', 'substeps', 'chains_steps', 'chain_starts',
           'workspaces']

# Reference counting. numba counts references to every array a function binds, slices or is
# passed, with an atomic increment and decrement each (they were about half of a contact
# step's time). The per-step kernels borrow every array they touch: they allocate nothing and
# return no array, their callers own all of them for the call, so they are compiled without
# it (``_borrow``: ``_nrt=False``, which a callee inherits unless it sets its own). A function
# that allocates sets ``_nrt=True`` (``_jit``): a borrowing caller may call it, since it
# returns no array.
# Kernels called from compiled code only are compiled without the wrappers that make a
# function callable from Python (``_INTERNAL``): numba would generate them at every
# specialisation's compile (for a ``StepModel`` argument, code unboxing its 27 fields), and
# nothing would call them.
_INTERNAL = dict(no_cpython_wrapper=True, no_cfunc_wrapper=True)
_jit = nb.njit(cache=True, _nrt=True, **_INTERNAL)
_inline = nb.njit(cache=True, inline='always')
_borrow = nb.njit(cache=True, _nrt=False, **_INTERNAL)


# The workspaces are views of a few blocks, not an allocation each: a call of a few steps
# (a tick of a short chain) paid more for twenty allocations than for a step.
@_jit
def _workspace(n):
    """F, T, e, hv ``(n, 3)``; Iinv, C = P⁻¹, Lo = 𝓛 ``(n, 3, 3)``."""
    v, m = np.empty((4, n, 3)), np.empty((3, n, 3, 3))
    return v[0], v[1], v[2], v[3], m[0], m[1], m[2]


@_jit
def _rk4_workspace(n):
    """The integrators' scratch: RK4's wb, w_s, xs, qs, vs, wbs, acc, (7: the constrained
    steps' only), sx, sv, sq, swb, α; ``(n, 3)``, the quaternions ``(n, 4)``."""
    v, q = np.empty((11, n, 3)), np.empty((2, n, 4))
    return (v[0], v[1], v[2], q[0], v[3], v[4], v[5], v[6], v[7], v[8], q[1], v[9], v[10])


@_inline
def _project(M, A, row, x, q, v, w, velocities):
    """Centres rebuilt so every joint closes exactly from the anchor outward, and for RK4
    (``velocities``) the centre velocities from the anchor point's velocity and the ω above
    (``oracle.stabilization``)."""
    n = x.shape[0]
    p0 = p1 = p2 = u0 = u1 = u2 = 0.0
    for i in range(n):
        c = M.chain_of[i]
        if M.is_first[i]:
            p0, p1, p2 = A.position[row, c, 0], A.position[row, c, 1], A.position[row, c, 2]
            u0, u1, u2 = A.velocity[row, c, 0], A.velocity[row, c, 1], A.velocity[row, c, 2]
        e0, e1, e2 = qaxis_x_at(q, i)
        h0, h1, h2 = M.half[i] * e0, M.half[i] * e1, M.half[i] * e2
        x[i, 0], x[i, 1], x[i, 2] = p0 + h0, p1 + h1, p2 + h2
        p0, p1, p2 = x[i, 0] + h0, x[i, 1] + h1, x[i, 2] + h2
        if velocities:
            c0, c1, c2 = cross_s(w[i, 0], w[i, 1], w[i, 2], h0, h1, h2)
            v[i, 0], v[i, 1], v[i, 2] = u0 + c0, u1 + c1, u2 + c2
            u0, u1, u2 = v[i, 0] + c0, v[i, 1] + c1, v[i, 2] + c2


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
            ok = rk4(M, A, k, h, x, q, v, w, ext_F, ext_T, ws, rws, f_c)
        else:
            ok = constrained_step(M, A, k, h, x, q, v, w, ext_F, ext_T, ws, rws, f_c,
                                   k == k0 or not M.projection)
        if not ok:
            return JOINT_SOLVE_FAILED
        if M.implicit_damping:
            if not implicit_damping(M, A, 2 * k + 2, q, v, w, h):
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
    starts, ends = chain_starts(M, x.shape[0])
    W, R = workspaces(starts, ends)
    # k0 an int64 value, not the literal 0: numba would compile the whole step once more,
    # specialised on the constant (``step_unilateral`` passes a variable).
    return chains_steps(M, A, np.int64(0), n_steps, h, x, q, v, w, ext_F, ext_T, f_c, W, R,
                        starts, ends, True)


@nb.njit(cache=True, nogil=True)
def advance_rk4(M, A, n_steps, h, x, q, v, w, ext_F, ext_T, f_c):
    """``advance`` for a model whose integrator is RK4 (the same results bit for bit),
    compiled without the other integrators."""
    starts, ends = chain_starts(M, x.shape[0])
    W, R = workspaces(starts, ends)
    # k0 an int64 value, not the literal 0: numba would compile the whole step once more,
    # specialised on the constant (``step_unilateral`` passes a variable).
    return chains_steps(M, A, np.int64(0), n_steps, h, x, q, v, w, ext_F, ext_T, f_c, W, R,
                        starts, ends, None)


@_borrow
def chains_steps(M, A, k0, n_steps, h, x, q, v, w, ext_F, ext_T, f_c, W, R, starts, ends,
                 constrained):
    """Steps ``k0 .. k0 + n_steps - 1`` of the table, chain by chain, each chain through all
    of them (its working set stays in the cache; its views borrowed: no reference counts
    however many chains there are). ``constrained``: as ``chain_steps``."""
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
def chain_starts(M, n):
    """Each chain's first segment and one past its last, ``(C,)`` each."""
    starts = np.nonzero(M.is_first)[0]
    ends = np.empty_like(starts)
    for c in range(starts.shape[0]):
        ends[c] = starts[c + 1] if c + 1 < starts.shape[0] else n
    return starts, ends


@_jit
def workspaces(starts, ends):
    """The joint system's and the integrators' workspaces, sized for the longest chain."""
    longest = np.int64(0)       # (a literal 0 would compile the allocators once more)
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
