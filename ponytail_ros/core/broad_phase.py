"""Broad phase of the contact stage: the colliders posed in the world, and which (chain,
collider) pairs can be within reach of a step's stages (numba, nopython, ``cache=True``).

A chain lies in the ball of its length (plus radius) about its anchor, and its surface moves
at most at ``surface_speed``: a pair farther than that (plus the skin and the speculative
allowance) can make no row. ``near`` answers for a whole chain; ``near_pairs`` keeps each
chain's pairs (sweeping the round colliders sorted along one axis from ``SWEEP_COLLIDERS`` of
them on: a crowd's chain is near one collider of hundreds) and hands them to the narrow phase
(``narrow_phase.detect_segments``). World frame, SI units.
"""
import math

import numpy as np
from numba import njit

from .contact_model import (
    CHAIN_OF,
    D_CHAIN_REACH,
    D_CHAINS,
    D_COL_RADIUS,
    D_MAX_HALF,
    D_N_ROUND,
    D_SEG,
    DT_DEPTH,
    DT_S,
    DT_T,
    P_A0,
    P_D2,
    P_NORMAL,
    P_SPEED,
    POSITION_SKIN,
    S_COUNT,
    S_END,
    S_FIRST,
    SPECULATIVE_STEPS,
    SW_AXIS,
    SW_BOUND,
    SW_FASTEST,
    SW_ON,
    SW_WIDEST,
    VELOCITY_SKIN,
    WS_BOX,
    WS_CHAIN_SLOT,
    WS_DET,
    WS_ORDER,
    WS_OWN,
    WS_PAIRS,
    WS_SLOTS,
    WS_STATE,
    WS_SWEEP,
)
from .narrow_phase import clip01, detect_segments
from .vec import add, dot, norm, q4, qrotate, scale, sub, v3

SWEEP_COLLIDERS = 16         # from this many round colliders on, the broad phase sweeps them
                             # sorted along one axis (``sweep_order``) instead of testing all
SWEEP_MARGIN = 1e-9          # relative: the sweep keeps colliders this much farther out
PAIR_MARGIN = 1e-3           # m: the per-pair broad phase keeps pairs this much farther out
                             # (rounding, and joints not exactly closed)


# -- the colliders in the world ------------------------------------------------------------------
@njit(cache=True)
def collider_pose(body_position, body_orientation, body_velocity, body_omega, cols):
    """The colliders at one instant: ``(a0, d2, normal, origin, velocity, omega, speed)``
    (``collision.ColliderPose``), each collider's local ``a0``, ``d2`` and ``normal`` turned
    into the world by its body's pose (``body < 0``: the world, no motion). ``speed`` bounds
    the speed of its surface: |v_origin| + |ω| × its reach from the body origin (m/s).

    ``cols``: ``(body, local_a0, local_d2, local_normal, reach)``; the body arrays are the
    kinematic bodies' origins (``AnchorKinematics`` of the origins), world frame.
    """
    K = cols[0].shape[0]
    pose = (np.empty((K, 3)), np.empty((K, 3)), np.empty((K, 3)), np.empty((K, 3)),
            np.empty((K, 3)), np.empty((K, 3)), np.empty(K))
    collider_pose_into(body_position, body_orientation, body_velocity, body_omega, cols, pose)
    return pose


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def collider_pose_into(body_position, body_orientation, body_velocity, body_omega, cols, pose):
    """``collider_pose`` into the arrays of ``pose`` (a step loop allocates them once)."""
    body, local_a0, local_d2, local_normal, reach = cols
    a0, d2, normal, origin, velocity, omega, speed = pose
    for j in range(body.shape[0]):
        b = body[j]
        la0, ld2, ln = v3(local_a0, j), v3(local_d2, j), v3(local_normal, j)
        if b < 0:
            wa0, wd2, wn = la0, ld2, ln
            for a in range(3):
                origin[j, a] = 0.0
                velocity[j, a] = 0.0
                omega[j, a] = 0.0
            speed[j] = 0.0
        else:
            qb = q4(body_orientation, b)
            o = v3(body_position, b)
            wa0 = add(o, qrotate(qb, la0))
            wd2 = qrotate(qb, ld2)
            wn = qrotate(qb, ln)
            vb, ob = v3(body_velocity, b), v3(body_omega, b)
            for a in range(3):
                origin[j, a] = o[a]
                velocity[j, a] = vb[a]
                omega[j, a] = ob[a]
            speed[j] = norm(vb) + norm(ob) * reach[j]
        for a in range(3):
            a0[j, a] = wa0[a]
            d2[j, a] = wd2[a]
            normal[j, a] = wn[a]


@njit(cache=True, inline='always')
def anchor_distance(p, aj, dj, nn, is_round, radius):
    """Distance (m) from a chain's anchor ``p`` to a collider's surface: to a round
    collider's core ``aj + t dj`` minus its ``radius``, a plane's (through ``aj``, normal
    ``nn``) signed height. Vectors as 3-tuples: called per (chain, collider) pair, it binds
    no array."""
    if is_round:
        rel = sub(p, aj)
        e2 = max(dot(dj, dj), 1e-300)
        t = clip01(dot(rel, dj) / e2)
        return norm(sub(rel, scale(t, dj))) - radius
    return dot(p, nn) - dot(aj, nn)


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def outside_box(p, aj, dj, radius, reach):
    """Is the anchor ``p`` farther than ``reach`` (m) along some axis from the box around a
    round collider (its core ``aj + t dj``'s box grown by its radius)? Then it is farther
    than that from the collider (a cheap test before ``anchor_distance``: no square root)."""
    for a in range(3):
        e = aj[a] + dj[a]
        if p[a] < min(aj[a], e) - radius - reach or p[a] > max(aj[a], e) + radius + reach:
            return True
    return False


@njit(cache=True, inline='always')
def surface_speed(v, w, det, fastest):
    """A bound (m/s) on how fast any colliding segment's surface nears any collider: the
    fastest centre's speed, plus the fastest spin times the longest half segment, plus the
    fastest collider's surface speed ``fastest`` (``broad_phase_setup``)."""
    v2 = 0.0
    w2 = 0.0
    for i in range(v.shape[0]):
        v2 = max(v2, dot(v3(v, i), v3(v, i)))
        w2 = max(w2, dot(v3(w, i), v3(w, i)))
    return math.sqrt(v2) + math.sqrt(w2) * det[D_MAX_HALF] + fastest


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def near(anchor_position, pose, v, w, det, dt, fastest):
    """Broad phase: could any collider be within reach of a chain? A chain lies in the ball of
    its length (plus radius) about its anchor; its surface moves at most at
    ``surface_speed``."""
    det_chains, chain_reach = det[D_CHAINS], det[D_CHAIN_REACH]
    a0, d2, normal = pose[P_A0], pose[P_D2], pose[P_NORMAL]
    col_radius, n_round = det[D_COL_RADIUS], det[D_N_ROUND]
    speed = surface_speed(v, w, det, fastest)
    for c in range(det_chains.shape[0]):
        reach = chain_reach[c] + POSITION_SKIN + 2.0 * SPECULATIVE_STEPS * dt * speed
        p = v3(anchor_position, det_chains[c])
        for j in range(a0.shape[0]):
            if anchor_distance(p, v3(a0, j), v3(d2, j), v3(normal, j), j < n_round,
                               col_radius[j]) < reach:
                return True
    return False


@njit(cache=True, inline='always')
def test_pair(state, c, j, p, reach, box, a0, d2, normal, n_round, col_radius, pair_list,
              count):
    """``near_pairs``' test of the pair (chain slot c at anchor ``p``, collider j), unless
    decided already: kept (state 1, appended to ``pair_list[c]``, ``count[c]`` of them) when
    the collider's surface is within ``reach``, a round collider's box tested first
    (``outside_box`` with the bounds of ``box``)."""
    if state[c, j] != 0:
        return
    if j < n_round and (p[0] < box[j, 0] - reach or p[0] > box[j, 3] + reach
                        or p[1] < box[j, 1] - reach or p[1] > box[j, 4] + reach
                        or p[2] < box[j, 2] - reach or p[2] > box[j, 5] + reach):
        return
    if anchor_distance(p, v3(a0, j), v3(d2, j), v3(normal, j), j < n_round,
                       col_radius[j]) < reach:
        state[c, j] = 1
        pair_list[c, count[c]] = j
        count[c] += 1


@njit(cache=True, _nrt=False)
def sweep_order(box, nr, order):
    """The broad phase's sweep over many round colliders (``near_pairs``): ``(sweep, axis,
    widest, bound)``; sweep False (test every pair) for fewer than ``SWEEP_COLLIDERS`` or a
    box that is not finite. Else ``order`` ``(nr,)`` receives the colliders sorted by their
    box's lower bound along the axis of the largest spread (column 6 of ``box``: that bound),
    ``widest`` is the widest box along it, ``bound`` the largest magnitude of a bound."""
    if nr < SWEEP_COLLIDERS:
        return False, 0, 0.0, 0.0
    bound = 0.0
    ax, spread = 0, -1.0
    for a in range(3):
        lo, hi = np.inf, -np.inf
        for j in range(nr):
            if not (np.isfinite(box[j, a]) and np.isfinite(box[j, 3 + a])):
                return False, 0, 0.0, 0.0
            lo = min(lo, box[j, a])
            hi = max(hi, box[j, a])
            bound = max(bound, max(abs(box[j, a]), abs(box[j, 3 + a])))
        if hi - lo > spread:
            ax, spread = a, hi - lo
    wmax = 0.0
    for j in range(nr):
        order[j] = j
        box[j, 6] = box[j, ax]
        wmax = max(wmax, box[j, 3 + ax] - box[j, ax])
    # Shell sort of the order by the lower bounds (Ciura's gaps; few colliders).
    for gap in (701, 301, 132, 57, 23, 10, 4, 1):
        for i in range(gap, nr):
            t = order[i]
            key = box[t, 6]
            k = i
            while k >= gap and box[order[k - gap], 6] > key:
                order[k] = order[k - gap]
                k -= gap
            order[k] = t
    return True, ax, wmax, bound


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def broad_phase_setup(pose, det, ws):
    """What the broad phase of every chain shares in a step (``WS_BOX``, ``WS_ORDER``,
    ``WS_SWEEP``): the round colliders' boxes (``outside_box``'s bounds before the reach), their
    sweep order (``sweep_order``) and the fastest collider's surface speed; once per step, not
    once per chain and detection."""
    a0, d2, col_radius, n_round = pose[P_A0], pose[P_D2], det[D_COL_RADIUS], det[D_N_ROUND]
    box, sweep = ws[WS_BOX], ws[WS_SWEEP]
    K = a0.shape[0]
    nr = min(K, n_round)
    for j in range(nr):
        for a in range(3):
            e = a0[j, a] + d2[j, a]
            box[j, a] = min(a0[j, a], e) - col_radius[j]
            box[j, 3 + a] = max(a0[j, a], e) + col_radius[j]
    on, ax, wmax, bound = sweep_order(box, nr, ws[WS_ORDER][:nr])
    col_speed = pose[P_SPEED]
    fastest = 0.0
    for j in range(col_speed.shape[0]):
        fastest = max(fastest, col_speed[j])
    sweep[SW_ON] = 1.0 if on else 0.0
    sweep[SW_AXIS] = ax
    sweep[SW_WIDEST] = wmax
    sweep[SW_BOUND] = bound
    sweep[SW_FASTEST] = fastest


@njit(cache=True, inline='always')
def near_pairs(x, h, anchor_position, pose, v, w, model, det, dt, ws):  # noqa: C901 (kernel loops)
    """Broad phase per (colliding chain, collider) pair, then detection (``detect_segments``) of
    every segment of the pairs kept; returns the position skin (``POSITION_SKIN`` plus 4×
    the deepest violation, at least ``VELOCITY_SKIN``), as if every pair had been detected.

    A pair is kept when the collider's surface is within the chain's reach (its length plus
    radius about its anchor, ``near``) plus the skin, ``2 SPECULATIVE_STEPS dt`` times
    ``surface_speed`` and ``PAIR_MARGIN``: a pair left out is then deeper outside than any
    row could reach (its depth ≤ -(distance - reach)), so it would make no row and no depth
    of it could raise the skin. Kept pairs can raise the skin, which can keep more pairs:
    repeated until the skin stands. Pairs kept, per chain slot c (``det[D_CHAINS][c]``):
    colliders ``ws[WS_PAIRS][c, :ws[WS_SLOTS][S_COUNT][c]]``, in column order."""
    seg, det_chains, chain_reach = det[D_SEG], det[D_CHAINS], det[D_CHAIN_REACH]
    a0, d2, normal = pose[P_A0], pose[P_D2], pose[P_NORMAL]
    col_radius, n_round = det[D_COL_RADIUS], det[D_N_ROUND]
    chain_of = model[CHAIN_OF]
    depth, s, t, own = ws[WS_DET][DT_DEPTH], ws[WS_DET][DT_S], ws[WS_DET][DT_T], ws[WS_OWN]
    state, pair_list, count = ws[WS_STATE], ws[WS_PAIRS], ws[WS_SLOTS][S_COUNT]
    first_seg, end_seg, slot = ws[WS_SLOTS][S_FIRST], ws[WS_SLOTS][S_END], ws[WS_CHAIN_SLOT]
    box, sw = ws[WS_BOX], ws[WS_SWEEP]
    nd, K = det_chains.shape[0], a0.shape[0]
    # Each chain's colliding segments are consecutive in det[D_SEG].
    for c in range(nd):
        slot[det_chains[c]] = c
        first_seg[c] = seg.shape[0]
        end_seg[c] = 0
    for i in range(seg.shape[0]):
        c = slot[chain_of[seg[i]]]
        first_seg[c] = min(first_seg[c], i)
        end_seg[c] = i + 1
    state[:] = 0            # 0: left out, 1: kept in this pass, 2: detected
    count[:nd] = 0
    speed = surface_speed(v, w, det, sw[SW_FASTEST])
    deepest = 0.0
    skin = max(POSITION_SKIN + 4.0 * deepest, VELOCITY_SKIN)
    tested = -1.0
    # (the boxes and their order: ``broad_phase_setup``, once per step)
    order = ws[WS_ORDER][:min(K, n_round)]
    sweep, ax, wmax, bound = sw[SW_ON] != 0.0, int(sw[SW_AXIS]), sw[SW_WIDEST], sw[SW_BOUND]
    while skin > tested:
        tested = skin
        for c in range(nd):
            # The pairs kept in this pass are appended to the chain's list (not marked in a
            # table scanned over every collider: a crowd's chain is near one collider of
            # hundreds), then detected in collider order, as a scan would.
            kept = count[c]
            reach = (chain_reach[c] + skin + 2.0 * SPECULATIVE_STEPS * dt * speed
                     + PAIR_MARGIN)
            p = v3(anchor_position, det_chains[c])
            if not sweep:
                for j in range(K):
                    test_pair(state, c, j, p, reach, box, a0, d2, normal, n_round, col_radius,
                              pair_list, count)
            else:
                # Only the round colliders whose box can be within reach along the axis
                # ``ax`` (boxes sorted by their lower bound there, none wider than ``wmax``),
                # with a margin far above rounding: every pair left out fails the box test.
                margin = SWEEP_MARGIN * (1.0 + abs(p[ax]) + reach + wmax + bound)
                left = p[ax] - reach - wmax - margin
                right = p[ax] + reach + margin
                lo, hi = 0, order.shape[0]
                while lo < hi:
                    mid = (lo + hi) // 2
                    if box[order[mid], 6] < left:
                        lo = mid + 1
                    else:
                        hi = mid
                while lo < order.shape[0] and box[order[lo], 6] <= right:
                    test_pair(state, c, order[lo], p, reach, box, a0, d2, normal, n_round,
                              col_radius, pair_list, count)
                    lo += 1
                for j in range(order.shape[0], K):
                    test_pair(state, c, j, p, reach, box, a0, d2, normal, n_round, col_radius,
                              pair_list, count)
            sort_ints(pair_list[c, kept:count[c]])
            for jj in range(kept, count[c]):
                j = pair_list[c, jj]
                state[c, j] = 2
                detect_segments(x, h, anchor_position, pose, det, np.bool_(False), first_seg[c],
                                end_seg[c], j, depth, s, t, own)
                for i in range(first_seg[c], end_seg[c]):
                    deepest = max(deepest, depth[i, j])
        skin = max(POSITION_SKIN + 4.0 * deepest, VELOCITY_SKIN)
    for c in range(nd):
        sort_ints(pair_list[c, :count[c]])
    return skin


@njit(cache=True, inline='always')
def sort_ints(a):
    """``a`` sorted in place, ascending (insertion sort: a chain keeps a few pairs)."""
    for i in range(1, a.shape[0]):
        key = a[i]
        k = i
        while k > 0 and a[k - 1] > key:
            a[k] = a[k - 1]
            k -= 1
        a[k] = key
