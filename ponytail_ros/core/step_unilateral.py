"""The compiled step loop of scenes with colliders or joint limits: per step, the chains' own
step (``step``, or for a crowd the SIMD lanes of ``lanes``), then the contacts and limits at
its end, chain by chain (``contact_stage.resolve_chains_into``), all the steps of a call in
one compiled call.

Stages of a step, in order: the sub-step test (``step.substeps``: a joint turning faster than
the simulator's ``SUBSTEP_ANGLE`` per step stops the call there, and the simulator takes that
step in sub-steps), ``integrate`` (applied forces, the joint solves, RK4 or the other
integrators, projection), the colliders posed at the step's end (moving bodies), and
``contacts`` (detection, rows, the exact complementarity solve per touching chain,
friction, position passes). The cycles of ``integrate`` and ``contacts`` are counted
(``stages.PROFILE_STAGES``), and those of the contact stage's parts (``stages.CONTACT_STAGES``:
rows, positions, velocities), like Box2D's ``b2Profile``.

Frames and units: world frame (REP 103), SI; the arrays are ``step.advance``'s.
"""
import numba as nb
import numpy as np

from . import contact_model, contact_stage, lanes
from .broad_phase import collider_pose_into
from .kernel_cache import ensure_fresh
from .stages import cycles
from .step import (
    JOINT_SOLVE_FAILED,
    OK,
    SUBSTEPS,
    chain_starts,
    chains_steps,
    substeps,
    workspaces,
)

ensure_fresh()

__all__ = ['advance_unilateral', 'compile_contact_stage']


# error_model='numpy': the lanes' loops inlined here divide as plain ``fdiv`` (see ``lanes``).
@nb.njit(cache=True, nogil=True, error_model='numpy')
def advance_unilateral(M, A, n_steps, h, x, q, v, w, ext_F, ext_T, f_c, B, moving, cols,
                       static_pose, umodel, det, split, q_rest, has_colliders, stats,
                       substep_angle, max_substeps, profile, in_lanes, cws, constrained):
    """``step.advance`` for scenes with colliders or joint limits: each step is integrated,
    chain by chain (``in_lanes`` None), or if ``in_lanes`` is True (``lanes.crowd_layout``
    and ``lanes.supports`` allow it) in the SIMD lanes of ``lanes.step_blocks``, the same bits
    (None, not False: numba prunes the lanes' branches from a version compiled for None, so a
    scene without a crowd does not compile them); then its contacts and
    limits are resolved chain by chain (``contact_stage.resolve_chains_into``; ``split``:
    ``collision.Unilateral.split_args``) at the step's end, the colliders
    posed from the kinematic bodies' table ``B`` (rows as ``A``) if ``moving``, else
    ``static_pose``. ``cws``: the contact stage's workspace
    (``contact_model.resolve_workspace`` of this model, detector and colliders), kept by the
    caller across calls like MuJoCo's ``mjData`` arena: a crowd's is megabytes (detection
    tables of every colliding segment by every collider), which allocated per call were
    mapped and page-faulted in at every tick. Returns ``(status, steps taken, row tables,
    row ids)``: the workspace's ``WS_TABLES`` and ``WS_IDS``, the only arrays
    ``contact_model.grown`` replaces when a step's rows overflow them (the caller keeps
    them in its workspace; handing back the whole workspace cost a boxed array each of its
    twenty at every call): status ``SUBSTEPS`` when the next step needs sub-steps
    (``step.substeps`` > 1; it is not taken: the simulator takes it), else as
    ``step.advance``. Adds the cycles spent in each of ``stages.PROFILE_STAGES``, then in the
    whole call, then in each of ``stages.CONTACT_STAGES``, to ``profile``
    ``(step.PROFILE_SIZE,)`` int64. ``constrained``: None for RK4 (the other integrators
    pruned, as in ``step.advance_rk4``), True for the model's integrator."""
    t_call = cycles()
    starts, ends = chain_starts(M, x.shape[0])
    W, R = workspaces(starts, ends)
    if in_lanes is not None:
        # The lanes' record, allocated here, where their loops are inlined (``lanes``).
        RL, EL, SL, ML = lanes.crowd_records(M, x.shape[0], in_lanes)
    # The step's positions before the contact stage, for all the steps.
    x0, q0 = np.empty_like(x), np.empty_like(q)
    # The moving colliders' pose, posed into these arrays at every step.
    mpose = (np.empty_like(static_pose[0]), np.empty_like(static_pose[1]),
             np.empty_like(static_pose[2]), np.empty_like(static_pose[3]),
             np.empty_like(static_pose[4]), np.empty_like(static_pose[5]),
             np.empty_like(static_pose[6]))
    own = np.empty(3, dtype=np.int64)   # (the contact stage's scratch)
    status, done = OK, n_steps
    for k in range(n_steps):
        if substeps(M, A, 2 * k, w, h, substep_angle, max_substeps) > 1:
            status, done = SUBSTEPS, k
            break
        t0 = cycles()
        if in_lanes is None:
            status = chains_steps(M, A, k, np.int64(1), h, x, q, v, w, ext_F, ext_T, f_c, W, R,
                                  starts, ends, constrained)
        else:
            status = lanes.step_blocks(M, A, k, h, x, q, v, w, ext_F, ext_T, f_c, RL, EL, SL,
                                       ML)
        t1 = cycles()
        profile[0] += t1 - t0
        if status != OK:
            done = k
            break
        r = 2 * k + 2
        anchor = (A.position[r], A.velocity[r], A.orientation[r], A.angular_velocity[r])
        if moving:
            collider_pose_into(B.position[r], B.orientation[r], B.velocity[r],
                               B.angular_velocity[r], cols, mpose)
            pose = mpose
        else:
            pose = static_pose
        _copy_positions(x, q, x0, q0)
        resolved, c = contact_stage.resolve_chains_into(
            x0, q0, x, q, v, w, anchor, pose, umodel, det, split, q_rest, has_colliders,
            M.projection, h, stats, own, cws, np.int64(0), profile)
        while resolved == contact_model.NO_ROOM:
            # (a workspace grown for one step's rows is kept for the rest of the call)
            cws = contact_model.grown(cws)
            resolved, c = contact_stage.resolve_chains_into(
                x0, q0, x, q, v, w, anchor, pose, umodel, det, split, q_rest, has_colliders,
                M.projection, h, stats, own, cws, c, profile)
        profile[1] += cycles() - t1
        if resolved != contact_model.OK:
            status, done = JOINT_SOLVE_FAILED, k
            break
    profile[2] += cycles() - t_call
    return status, done, cws[contact_model.WS_TABLES], cws[contact_model.WS_IDS]


def compile_contact_stage(args):
    """Compile (or load) the contact stage (``contact_stage.resolve_chains_into``) for the
    types ``advance_unilateral`` calls it with, given ``advance_unilateral``'s arguments
    ``args``, without compiling ``advance_unilateral``: a cold compile does this in a second
    process while the first compiles the chains' step (``compile``). The arguments are
    those of the loop below, built alike (C-contiguous arrays: ``np.empty_like`` of C arrays,
    a C table's rows)."""
    (M, A, _, h, x, q, v, w, _, _, _, _, _, _, static_pose, umodel, det, split, q_rest,
     has_colliders, stats, _, _, profile, _, cws, _) = args
    anchor = (A.position[2], A.velocity[2], A.orientation[2], A.angular_velocity[2])
    like = (np.empty_like(x), np.empty_like(q), x, q, v, w, anchor, static_pose, umodel, det,
            split, q_rest, has_colliders, M.projection, h, stats,
            np.empty(3, dtype=np.int64), cws, np.int64(0), profile)
    contact_stage.resolve_chains_into.compile(tuple(nb.typeof(a) for a in like))


@nb.njit(cache=True, _nrt=False, inline='always')
def _copy_positions(x, q, x0, q0):
    """``x0[:] = x; q0[:] = q`` as plain loops (slice assignment makes and counts views)."""
    for i in range(x.shape[0]):
        for a in range(3):
            x0[i, a] = x[i, a]
        for a in range(4):
            q0[i, a] = q[i, a]
