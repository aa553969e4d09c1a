"""Narrow phase of the contact stage: depths and closest points of the colliding segments
(capsules) in the colliders (numba, nopython, ``cache=True``).

Spheres: clamped point–segment closest point; capsules: clamped segment–segment closest
points (Ericson, *Real-Time Collision Detection* 5.1.9); planes: the distal end. A first
segment rooted on a round collider (hair on a scalp) is tested on ``s ≥ ROOT_LEVER``. World
frame, SI units.
"""
import numpy as np
from numba import njit

from .contact_model import (
    D_FIRST_CHAIN,
    D_FIRST_OF,
    D_INNER,
    D_LENGTH,
    D_N_ROUND,
    D_N_SPHERE,
    D_RADIUS,
    D_ROOT_FIXED,
    D_ROOTED_FIXED,
    D_SEG,
    D_SUM_RADIUS,
    P_A0,
    P_D2,
    P_NORMAL,
)
from .vec import add, cross, dot, norm, scale, sub, v3

ROOT_LEVER = 0.5             # a rooted first segment is tested on s in [ROOT_LEVER, 1]


# -- detection ---------------------------------------------------------------------------------
@njit(cache=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def clip01(s):
    return 0.0 if s < 0.0 else min(s, 1.0)


@njit(cache=True)
def rooted(anchor, a0, d2, sum_radius, length):
    """Is a first segment's anchor inside, or within a quarter segment of, a round collider?"""
    e2 = max(dot(d2, d2), 1e-300)
    rel = sub(anchor, a0)
    ta = clip01(dot(rel, d2) / e2)
    return sum_radius - norm(sub(rel, scale(ta, d2))) > -0.25 * length


@njit(cache=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def closest_segment_segment(p0, d1, a0, d2):
    """Clamped closest points ``s``, ``t`` ∈ [0, 1] of segments ``p0 + s d1`` and
    ``a0 + t d2`` (``d2`` non-zero; Ericson, *Real-Time Collision Detection* 5.1.9)."""
    r = sub(p0, a0)
    a = dot(d1, d1)
    e = dot(d2, d2)
    b = dot(d1, d2)
    c = dot(d1, r)
    f = dot(d2, r)
    denom = a * e - b * b
    s = clip01((b * f - c * e) / denom) if denom > 1e-12 * a * e else 0.0
    t = (b * s + f) / e
    if t < 0.0:
        s = clip01(-c / a)
    elif t > 1.0:
        s = clip01((b - c) / a)
    return s, clip01(t)


@njit(cache=True, _nrt=False, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def detect_segments(x, h, anchor_position, pose, det, report, m0, m1, j, depth, s_out, t_out,
                    own):
    """``detect`` for colliding segments ``m0:m1`` and collider j: entries ``[m0:m1, j]`` of
    each table. The tuples' arrays are taken out once, before the segments' loop (each array
    bound inside the loop would cost a reference count per segment)."""
    seg = det[D_SEG]
    a0, d2, normal = pose[P_A0], pose[P_D2], pose[P_NORMAL]
    seg_radius, seg_length, inner = det[D_RADIUS], det[D_LENGTH], det[D_INNER]
    first_of, first_chain = det[D_FIRST_OF], det[D_FIRST_CHAIN]
    root_fixed, rooted_fixed = det[D_ROOT_FIXED], det[D_ROOTED_FIXED]
    sum_radius, n_sphere, n_round = det[D_SUM_RADIUS], det[D_N_SPHERE], det[D_N_ROUND]
    aj, dj = v3(a0, j), v3(d2, j)
    for m in range(m0, m1):
        # Segment m's core p0 + s d1, proximal to distal joint.
        g = seg[m]
        hg = v3(h, g)
        p0 = sub(v3(x, g), hg)
        d1 = scale(2.0, hg)
        f = first_of[m]
        if j >= n_round:
            nn = v3(normal, j)
            off = dot(aj, nn)
            s1 = dot(add(p0, d1), nn) - off
            if report:
                s1 = min(s1, dot(p0, nn) - off)
            depth[m, j] = seg_radius[m] - s1
            s_out[m, j] = 1.0
            t_out[m, j] = 0.0
            own[m, j] = True
            continue
        if j < n_sphere:
            s = clip01(dot(sub(aj, p0), d1) / (seg_length[m] * seg_length[m]))
            t = 0.0
        else:
            s, t = closest_segment_segment(p0, d1, aj, dj)
        if f >= 0:
            if root_fixed[f, j]:
                is_rooted = rooted_fixed[f, j]
            else:
                is_rooted = rooted(v3(anchor_position, first_chain[f]), aj, dj,
                                   sum_radius[m, j], seg_length[m])
            if is_rooted:
                e2 = max(dot(dj, dj), 1e-300)
                s = max(s, ROOT_LEVER)
                t = clip01(dot(sub(add(p0, scale(s, d1)), aj), dj) / e2)
        diff = sub(add(p0, scale(s, d1)), add(aj, scale(t, dj)))
        depth[m, j] = sum_radius[m, j] - norm(diff)
        s_out[m, j] = s
        t_out[m, j] = t
        own[m, j] = not (inner[m] and s <= 0.0)


@njit(cache=True, _nrt=False)
def detect(x, h, anchor_position, pose, det, report, depth, s_out, t_out, own):
    """Depth (m, > 0 inside) of every colliding segment (capsule) in every collider, the
    closest-point parameters ``s`` (on the segment, proximal 0 to distal 1) and ``t`` (on a
    capsule's core), and ``own`` (the pair may make a row), all ``(m, K)``.

    Spheres: clamped point–segment closest point; capsules: clamped segment–segment closest
    points (Ericson 5.1.9); planes: the distal end (``report``: the deeper end). A non-first
    segment's proximal joint is its parent's distal joint: no row there (``own`` False). A
    first segment rooted on a round collider is tested on ``s ≥ ROOT_LEVER``.
    """
    for j in range(pose[P_A0].shape[0]):
        detect_segments(x, h, anchor_position, pose, det, report, np.int64(0),
                        det[D_SEG].shape[0], j, depth, s_out, t_out, own)


# -- the contact frame --------------------------------------------------------------------------
@njit(cache=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def contact_frame(xg, hg, s, t, aj, dj, nj, radius, is_round):
    """Normal (from the collider to the segment) and touching point on the surface of the
    segment (centre ``xg``, half-vector ``hg``) for the closest points ``s`` (segment) and
    ``t`` (a round collider's core ``aj + t dj``; a plane: its normal ``nj``). Vectors as
    3-tuples: called per row, it binds no array."""
    ps = add(xg, scale(2.0 * s - 1.0, hg))
    if not is_round:
        nrm = nj
    else:
        diff = sub(ps, add(aj, scale(t, dj)))
        dist = norm(diff)
        if dist > 1e-12:
            nrm = (diff[0] / dist, diff[1] / dist, diff[2] / dist)
        else:
            # On the core: any direction perpendicular to the segment.
            ref = (1.0, 0.0, 0.0) if abs(hg[0]) < 0.9 else (0.0, 1.0, 0.0)
            p = cross(hg, ref)
            npn = norm(p)
            nrm = (p[0] / npn, p[1] / npn, p[2] / npn)
    return nrm, sub(ps, scale(radius, nrm))
