"""Compiled contacts and joint limits: the contact stage after each step (numba, nopython,
``cache=True``, no fastmath).

One call of ``resolve`` does what ``collision.Unilateral.resolve`` documents (the method is
in the ``collision`` module docstring): broad phase (``broad_phase``), detection
(``narrow_phase``), rows (``contact_rows``), the position passes, the limits' exact
projection, the joints' velocity projection (``contact_joints``), the inelastic impulses
(``contact_impulses``, ``small_solves``) and Coulomb friction (``friction``). ``resolve``
runs its stages in order: ``position_stage``, ``limit_stage``, the joints' velocity
projection, ``velocity_stage``; chain by chain (``resolve_chains_into``), each chain as if it
were alone with all the colliders. The model and the workspace: ``contact_model``.

numba's cache does not see edits of a callee in another file; ``kernel_cache.py`` drops the
cache files when any kernel source changes.
"""
import math

import numpy as np
from numba import njit

from .broad_phase import broad_phase_setup
from .contact_impulses import solve_rows_into, velocity_impulses
from .contact_joints import (
    half_vectors,
    joint_factors_ws,
    joint_projection,
    project_positions,
    project_velocities,
    touched_joint_factors_ws,
)
from .contact_model import (
    ANGLE_SKIN,
    CHAIN_END,
    CHAIN_OF,
    CHAIN_START,
    CONTACT,
    DEPTH,
    IS_FIRST,
    LENGTH,
    LIMITED,
    MAX_ROTATION,
    NO_ROOM,
    NOT_POSITIVE_DEFINITE,
    OK,
    POSITION_ITERATIONS,
    POSITION_SKIN,
    POSITION_TOLERANCE,
    R_B,
    R_BOUND,
    R_LAM,
    SEP,
    SP_SLOT,
    SPECULATIVE_STEPS,
    SWING_LIMIT,
    T_SEL,
    TWIST_LIMIT,
    V_N0,
    V_N1,
    V_N2,
    V_N3,
    V_V0,
    V_W0,
    VELOCITY_SKIN,
    WS_IDS,
    WS_KEEP,
    WS_Q,
    WS_ROWVEC,
    WS_SOLVE,
    WS_TABLES,
    chain_anchor,
    chain_det,
    chain_is_free,
    chain_model,
    grown,
    joint_factor_views,
    resolve_workspace,
    rows_of,
    vec,
    zero_pair,
)
from .contact_rows import build_rows_into, deepest, moved_rows, refresh_sep, take
from .limit_kernels import project_limits
from .stages import PROFILE_POSITIONS, PROFILE_ROWS, PROFILE_VELOCITIES, cycles
from .vec import dot, q4, qfrom_rotvec, qmul, qnormalize, scale, v3


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def rotate_segments(q, dth, length):
    """Turn every segment by its rotation vector ``dth`` (clamped in place to
    ``MAX_ROTATION``): q ← normalise(exp(dth) ⊗ q). Returns whether the pass was small: no
    clamp and max l θ² below a tenth of ``POSITION_TOLERANCE`` (its linearisation holds)."""
    unclamped = True
    small = 0.0
    for i in range(q.shape[0]):
        th = v3(dth, i)
        ang2 = dot(th, th)
        clamp = min(1.0, MAX_ROTATION / math.sqrt(max(ang2, 1e-300)))
        unclamped = unclamped and clamp == 1.0
        small = max(small, ang2 * length[i])
        th = scale(clamp, th)
        qi = qnormalize(qmul(qfrom_rotvec(th), q4(q, i)))
        for a in range(3):
            dth[i, a] = th[a]
        for a in range(4):
            q[i, a] = qi[a]
    return unclamped and small < 0.1 * POSITION_TOLERANCE


@njit(cache=True, inline='always')
def position_stage(x, q, v, w, anchor, q_rest, pose, model, det, has_colliders, dt, ws, stats,  # noqa: C901, E501
                   profile):
    """Positions: passes of the linearised LCP ``W μ - depth ≥ 0, μ ≥ 0`` over the violated
    rows and those within the skin (plus 4× the deepest violation), each displacement
    ``P M⁻¹ J_rᵀ μ`` applied as segment rotations, positions rebuilt from the anchor, while a
    contact is deeper than ``POSITION_TOLERANCE`` (limits: the first pass). ``x``, ``q`` in
    place. Returns ``(status, moved, k)``: the k rows at the final pose are the workspace's
    (``rows_of``). The cycles of its row builds are added to ``profile``'s rows."""
    length = model[LENGTH]
    h, inv_I, C, Lo = joint_factor_views(ws, q.shape[0])
    t0 = cycles()
    k = build_rows_into(x, q, v, w, anchor, q_rest, pose, model, det, has_colliders, dt, ws)
    profile[PROFILE_ROWS] += cycles() - t0
    if k < 0:
        return NO_ROOM, False, 0
    R, I = rows_of(ws, k)
    moved = False
    for passes in range(POSITION_ITERATIONS):
        if R.shape[0] == 0:
            break
        worst = deepest(R, I, passes == 0)
        if worst <= POSITION_TOLERANCE:
            break
        active = ws[WS_KEEP][:R.shape[0]]
        for r in range(R.shape[0]):
            skin = POSITION_SKIN if I[r, CONTACT] else ANGLE_SKIN
            active[r] = R[r, DEPTH] > -skin - 4.0 * worst
        ks = take(R, I, active, ws[WS_TABLES][T_SEL], ws[WS_IDS][T_SEL])
        Rs, Is = ws[WS_TABLES][T_SEL][:ks], ws[WS_IDS][T_SEL][:ks]
        # Only the selected rows' chains are solved for: their factors alone.
        if not touched_joint_factors_ws(q, model, Is, ws):
            return NOT_POSITIVE_DEFINITE, moved, R.shape[0]
        b = ws[WS_ROWVEC][R_B][:ks]
        for r in range(ks):
            b[r] = -Rs[r, DEPTH]
        # The displacements (centres unused: positions are rebuilt from the rotations).
        dx, dth = vec(ws, V_N2, x.shape[0]), vec(ws, V_N3, x.shape[0])
        zero_pair(dx, dth)
        solve_rows_into(Rs, Is, b, ws[WS_ROWVEC][R_BOUND][:0], h, inv_I, C, Lo, model, dx, dth,
                        ws[WS_ROWVEC][R_LAM][:ks], ws[WS_SOLVE])
        small = rotate_segments(q, dth, length)
        stats[2] = passes + 1
        moved = True
        x_old = vec(ws, V_N0, x.shape[0])
        for i in range(x.shape[0]):
            for a in range(3):
                x_old[i, a] = x[i, a]
        half_vectors(length, q, h)
        project_positions(anchor[0], h, model, x)
        if small:
            # The predicted depths stand (error ~ l θ²), no second detection.
            for i in range(x.shape[0]):
                for a in range(3):
                    dx[i, a] = x[i, a] - x_old[i, a]
            moved_rows(R, I, dx, dth)
            break
        t0 = cycles()
        k = build_rows_into(x, q, v, w, anchor, q_rest, pose, model, det, has_colliders, dt,
                            ws)
        profile[PROFILE_ROWS] += cycles() - t0
        if k < 0:
            return NO_ROOM, moved, 0
        R, I = rows_of(ws, k)
    return OK, moved, R.shape[0]


@njit(cache=True, inline='always')
def limit_stage(x, q, anchor, q_rest, model, ws):
    """The limits' exact projection (``project_limits``) for what the linearisation of their
    cones left; ``x``, ``q`` in place. Returns whether anything moved."""
    q_lim = ws[WS_Q][:q.shape[0]]
    if not project_limits(q, anchor[2], q_rest, model[IS_FIRST], model[CHAIN_OF],
                          model[CHAIN_START], model[CHAIN_END], model[LIMITED],
                          model[SWING_LIMIT], model[TWIST_LIMIT], POSITION_TOLERANCE, q_lim):
        return False
    for i in range(q.shape[0]):
        for a in range(4):
            q[i, a] = q_lim[i, a]
    h = vec(ws, V_N1, q.shape[0])
    half_vectors(model[LENGTH], q, h)
    project_positions(anchor[0], h, model, x)
    return True


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def unprojected_positions(x0, q0, q, anchor, model, x, h, p0, p1):
    """Without projection the centres move by the rotations about the joints only:
    x = x0 + (joint-closed centres at q) - (joint-closed centres at q0). ``h``, ``p0``,
    ``p1`` ``(n, 3)``: scratch."""
    half_vectors(model[LENGTH], q0, h)
    project_positions(anchor[0], h, model, p0)
    half_vectors(model[LENGTH], q, h)
    project_positions(anchor[0], h, model, p1)
    for i in range(x.shape[0]):
        for a in range(3):
            x[i, a] = x0[i, a] + (p1[i, a] - p0[i, a])


@njit(cache=True, inline='always')
def velocity_stage(R, I, q, v, w, anchor, model, project, dt, have_factor, ws, stats):
    """Velocities: every row touching, or whose gap would close within ``SPECULATIVE_STEPS``
    steps at its current rate, gets the inelastic impulse of the LCP
    ``W λ + sep + max(gap, 0)/dt ≥ 0``, then friction; ``v``, ``w`` in place. Returns the
    status (the chain is factorised here if it was not yet)."""
    h, inv_I, C, Lo = joint_factor_views(ws, q.shape[0])
    k = R.shape[0]
    keep = ws[WS_KEEP][:k]
    for r in range(k):
        gap = -R[r, DEPTH]
        sep = R[r, SEP]
        skin = VELOCITY_SKIN if I[r, CONTACT] else ANGLE_SKIN
        keep[r] = gap < skin or (sep < 0.0 and gap < -SPECULATIVE_STEPS * dt * sep)
    kv = take(R, I, keep, ws[WS_TABLES][T_SEL], ws[WS_IDS][T_SEL])
    Rv, Iv = ws[WS_TABLES][T_SEL][:kv], ws[WS_IDS][T_SEL][:kv]
    b = ws[WS_ROWVEC][R_B][:kv]
    closing = False
    for r in range(kv):
        stats[0 if Iv[r, CONTACT] else 1] += 1
        b[r] = Rv[r, SEP] + max(-Rv[r, DEPTH], 0.0) / dt
        closing = closing or b[r] < 0.0
    if not closing:
        return OK
    if not have_factor and not touched_joint_factors_ws(q, model, Iv, ws):
        return NOT_POSITIVE_DEFINITE
    velocity_impulses(Rv, Iv, b, h, inv_I, C, Lo, model, v, w, ws)
    if project:
        project_velocities(anchor[1], w, h, model, v)
    return OK


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def resolve_chains_into(x0, q0, x, q, v, w, anchor, pose, model, det, split, q_rest,  # noqa: C901
                        has_colliders, project, dt, stats, own, ws, first, profile):
    """``resolve`` on ``x``, ``q``, ``v``, ``w`` in place (on entry: the step's state), chain
    by chain (``chain_model``, ``chain_det``, ``chain_anchor``): each chain is resolved as if
    it were alone with all the colliders, so that what one chain touches never changes
    another's step. Chains with nothing to resolve (no colliding segment, no limit) are
    skipped; the broad phase's per-step setup (``broad_phase_setup``) is done once, for all.
    ``x0``, ``q0``: a copy of the step's positions (not ``x``, ``q`` themselves). ``ws``: the
    workspace (``resolve_workspace`` of this model, detector and colliders: a step loop
    allocates it once for all its steps; every stage writes what it reads there first, as it
    must of ``np.empty``'s contents). ``stats``: the contacts and limits summed over the
    chains, the most position passes any took. ``own`` ``(3,)`` int64: scratch.

    Returns ``(status, chain)``: a chain that fails stops the call; ``NO_ROOM``: chain
    ``chain``'s candidate rows overflowed the row tables (a segment near more than
    ``ROW_COLLIDERS`` colliders), that chain is restored to its entry state and the caller
    resolves again from it (``first``) with ``grown(ws)``, kept for the next steps.
    ``first`` 0 starts a step (the stats and the broad phase's setup). ``profile``: the
    step's profile (``stages.PROFILE_SIZE`` int64), whose contact stages
    (``stages.CONTACT_STAGES``) get the cycles of each chain's rows, positions and velocities.

    It allocates nothing and borrows every array (``_nrt=False``): entering a function
    that counts references costs an atomic increment of each of its arrays (the model's, the
    detector's, the workspace's) and a decrement on the way out, at every step."""
    if first == 0:
        stats[:] = 0
        if has_colliders:
            broad_phase_setup(pose, det, ws)
    chain_start, chain_end = model[CHAIN_START], model[CHAIN_END]
    for c in range(first, chain_start.shape[0]):
        if chain_is_free(split, has_colliders, c):
            continue
        s, e = chain_start[c], chain_end[c]
        n = e - s
        v0, w0 = vec(ws, V_V0, n), vec(ws, V_W0, n)
        for i in range(n):
            for a in range(3):
                v0[i, a] = v[s + i, a]
                w0[i, a] = w[s + i, a]
        collides = has_colliders and split[SP_SLOT][c] >= 0
        status = _resolve_stages(x0[s:e], q0[s:e], x[s:e], q[s:e], v[s:e], w[s:e],
                                 chain_anchor(anchor, c), pose, chain_model(model, split, c),
                                 chain_det(det, split, c), q_rest[s:e], collides, project,
                                 dt, own, ws, profile)
        if status == NO_ROOM:
            for i in range(n):
                for a in range(3):
                    x[s + i, a] = x0[s + i, a]
                    v[s + i, a] = v0[i, a]
                    w[s + i, a] = w0[i, a]
                for a in range(4):
                    q[s + i, a] = q0[s + i, a]
            return status, c
        stats[0] += own[0]
        stats[1] += own[1]
        stats[2] = max(stats[2], own[2])
        if status != OK:
            return status, c
    return OK, chain_start.shape[0]


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def _resolve_stages(x0, q0, x, q, v, w, anchor, pose, model, det, q_rest, has_colliders,
                    project, dt, stats, ws, profile):
    """One chain's stages (``resolve``), in order, borrowing every array (no reference
    counting); ``NO_ROOM`` if the row tables overflow. Their cycles go to ``profile``'s
    contact stages (``stages.CONTACT_STAGES``)."""
    stats[:] = 0
    h, inv_I, C, Lo = joint_factor_views(ws, q.shape[0])
    t0 = cycles()
    rows0 = profile[PROFILE_ROWS]
    status, moved, k = position_stage(x, q, v, w, anchor, q_rest, pose, model, det,
                                      has_colliders, dt, ws, stats, profile)
    if status != OK:
        return status
    R, I = rows_of(ws, k)
    stale = model[LIMITED].shape[0] > 0 and limit_stage(x, q, anchor, q_rest, model, ws)
    moved = moved or stale
    if moved:
        if not project:
            n = x.shape[0]
            unprojected_positions(x0, q0, q, anchor, model, x, vec(ws, V_N1, n),
                                  vec(ws, V_N0, n), vec(ws, V_N2, n))
        if not joint_factors_ws(q, model, ws):
            return NOT_POSITIVE_DEFINITE
        n = x.shape[0]
        joint_projection(v, w, anchor[1], h, inv_I, C, Lo, model, vec(ws, V_N0, n),
                         vec(ws, V_N2, n), vec(ws, V_N3, n))
        if stale:
            t = cycles()
            k = build_rows_into(x, q, v, w, anchor, q_rest, pose, model, det, has_colliders,
                                dt, ws)
            profile[PROFILE_ROWS] += cycles() - t
            if k < 0:
                return NO_ROOM
            R, I = rows_of(ws, k)
        else:
            refresh_sep(R, I, v, w, anchor[3], model[CHAIN_OF])
    t1 = cycles()
    profile[PROFILE_POSITIONS] += (t1 - t0) - (profile[PROFILE_ROWS] - rows0)
    if R.shape[0]:
        status = velocity_stage(R, I, q, v, w, anchor, model, project, dt, moved, ws, stats)
        if status != OK:
            return status
    if moved and project:
        half_vectors(model[LENGTH], q, h)
        project_velocities(anchor[1], w, h, model, v)
    profile[PROFILE_VELOCITIES] += cycles() - t1
    return OK


@njit(cache=True)
def resolve(x, q, v, w, anchor, pose, model, det, split, q_rest, has_colliders, project, dt,
            stats):
    """Contacts and limits at the end of a step of length ``dt`` (s): positions, then
    velocities (inelastic impulses, then friction). Returns ``(status, x, q, v, w)`` (new
    arrays; the inputs are not changed); ``stats`` ``(3,)`` receives the contacts and limits
    of the velocity stage and the position passes taken.

    ``anchor``: ``(position, velocity, orientation, angular_velocity)`` of every chain's
    attachment (C rows); ``pose``: ``(a0, d2, normal, origin, velocity, omega, speed)`` of the
    colliders (``collision.ColliderPose``); ``model`` and ``det``: the constant tuples built by
    ``collision.Unilateral`` and ``split`` their split by chain (``SP_*``); ``q_rest``: the
    joints' rest rotations (``Model.q_rest``). Chains are resolved one at a time
    (``resolve_chains_into``).

    Stages, in order: ``position_stage``, ``limit_stage``, then (if anything moved) the
    unchanged velocities projected M-orthogonally onto the moved joints (never adding kinetic
    energy), ``velocity_stage``, and the centre velocities rebuilt from ω. All scratch is one
    workspace (``workspace``), a few allocations per call (``resolve_chains_into``: the same
    in place, on a workspace kept across steps).
    """
    x1, q1, v1, w1 = x.copy(), q.copy(), v.copy(), w.copy()
    ws = resolve_workspace(model, det, split, pose, has_colliders)
    own = np.empty(3, dtype=np.int64)
    profile = np.zeros(PROFILE_VELOCITIES + 1, dtype=np.int64)     # (not reported)
    status, c = resolve_chains_into(x, q, x1, q1, v1, w1, anchor, pose, model, det, split,
                                    q_rest, has_colliders, project, dt, stats, own, ws,
                                    np.int64(0), profile)
    while status == NO_ROOM:
        ws = grown(ws)
        status, c = resolve_chains_into(x, q, x1, q1, v1, w1, anchor, pose, model, det,
                                        split, q_rest, has_colliders, project, dt, stats, own,
                                        ws, c, profile)
    return status, x1, q1, v1, w1
