"""Compiled numbers of the display markers (numba, nopython, no fastmath): where each segment's
capsule, each joint and each collider is drawn, from a tick's poses.

The node publishes them as ``visualization_msgs`` markers (``app/messages.py`` lays out the
messages and owns the conventions); here are only the numbers, per segment and per collider
in one call each, instead of some fifty NumPy calls on arrays of a few rows. Each number is
computed by the same floating-point operations in the same order as ``core.rotations``'s
functions (``quat_axis_x``, ``quat_rotate``, ``quat_multiply`` by a constant,
``quat_from_two_vectors``), so the bytes a recording holds do not depend on which computed
them.

Frames and units: world frame (REP 103), m; quaternions scalar-last ``(x, y, z, w)``, body to
world. A segment's pose has its origin at its proximal joint and its local +X along it.
"""
import math

from numba import njit

from .vec import qaxis_x_s, qrot_s

__all__ = ['chain_numbers', 'collider_numbers']


@njit(cache=True)
def chain_numbers(origins, quats, lengths, last, origin_rows, tip_rows, capsule_rows,
                  identity_rows, capsules, k0, k1, k2, k3, poses, joints):
    """Every chain's joints and (``capsules``) its segments' capsule poses.

    ``origins`` ``(n, 3)``, ``quats`` ``(n, 4)``: the segments' poses, chains laid end to
    end; ``lengths`` ``(n,)`` m; ``last`` ``(C,)``: each chain's tip segment. Into ``joints``:
    row ``origin_rows[i]`` segment i's origin, row ``tip_rows[c]`` chain c's tip
    (``origin + length · axis_x(q)`` of its last segment). With ``capsules``, into ``poses``
    ``(·, 7)`` (x, y, z, qx, qy, qz, qw): row ``capsule_rows[i]`` the capsule of segment i
    (centre ``origin + ½ length · axis_x(q)``, orientation ``q ⊗ b`` with ``b`` the constant
    whose product terms are ``k0 … k3`` ``(4,)``: ``((q_w k0 + q_x k1) + q_y k2) + q_z k3``),
    rows ``identity_rows`` the identity pose."""
    n = origins.shape[0]
    for i in range(n):
        x, y, z, w = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        L = lengths[i]
        e0, e1, e2 = qaxis_x_s(x, y, z, w)
        a0, a1, a2 = e0 * L, e1 * L, e2 * L
        r = origin_rows[i]
        joints[r, 0], joints[r, 1], joints[r, 2] = origins[i, 0], origins[i, 1], origins[i, 2]
        if capsules:
            r = capsule_rows[i]
            poses[r, 0] = origins[i, 0] + 0.5 * a0
            poses[r, 1] = origins[i, 1] + 0.5 * a1
            poses[r, 2] = origins[i, 2] + 0.5 * a2
            for j in range(4):
                poses[r, 3 + j] = ((w * k0[j] + x * k1[j]) + y * k2[j]) + z * k3[j]
    for c in range(last.shape[0]):
        i = last[c]
        x, y, z, w = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        L = lengths[i]
        r = tip_rows[c]
        e0, e1, e2 = qaxis_x_s(x, y, z, w)
        joints[r, 0] = origins[i, 0] + e0 * L
        joints[r, 1] = origins[i, 1] + e1 * L
        joints[r, 2] = origins[i, 2] + e2 * L
    if capsules:
        for r in identity_rows:
            for j in range(6):
                poses[r, j] = 0.0
            poses[r, 6] = 1.0


@njit(cache=True)
def collider_numbers(centres, axes, moving, bodies, body_position, body_orientation,
                     pose_rows, identity_rows, capsules, half_lengths, poses, points,
                     degenerate):
    """The colliders' poses and capsule end points.

    ``centres`` and ``axes`` ``(K, 3)``: each collider's centre and unit axis (a plane's
    normal, a sphere's +Z) in its body, overwritten with their world values: the colliders
    ``moving`` ``(M,)`` are fixed in kinematic bodies ``bodies`` ``(M,)`` (rows of
    ``body_position`` ``(B, 3)``, ``body_orientation`` ``(B, 4)``), the others are in the
    world already. Into ``poses`` ``(·, 7)``: row ``pose_rows[k]`` collider k's centre and
    the shortest-arc rotation of +Z onto its axis; rows ``identity_rows`` the identity pose.
    Into ``points`` ``(2 len(capsules), 3)``: each capsule's two end points, centre ∓
    ``half_lengths`` · axis. ``degenerate[k]`` is set where that rotation is not defined here
    (a zero axis, or one opposite +Z): the caller computes those rows itself. Returns how many
    there are."""
    for j in range(moving.shape[0]):
        k, b = moving[j], bodies[j]
        u0, u1, u2, w = (body_orientation[b, 0], body_orientation[b, 1],
                         body_orientation[b, 2], body_orientation[b, 3])
        r0, r1, r2 = qrot_s(u0, u1, u2, w, centres[k, 0], centres[k, 1], centres[k, 2])
        centres[k, 0] = body_position[b, 0] + r0
        centres[k, 1] = body_position[b, 1] + r1
        centres[k, 2] = body_position[b, 2] + r2
        axes[k, 0], axes[k, 1], axes[k, 2] = qrot_s(u0, u1, u2, w, axes[k, 0], axes[k, 1],
                                                     axes[k, 2])
    a0, a1, a2 = 0.0, 0.0, 1.0          # +Z (normalised: unchanged)
    n_degenerate = 0
    for k in range(centres.shape[0]):
        r = pose_rows[k]
        poses[r, 0], poses[r, 1], poses[r, 2] = centres[k, 0], centres[k, 1], centres[k, 2]
        nb = math.sqrt((axes[k, 0] * axes[k, 0] + axes[k, 1] * axes[k, 1])
                       + axes[k, 2] * axes[k, 2])
        qw = qx = qy = qz = 0.0
        if nb != 0.0:
            b0, b1, b2 = axes[k, 0] / nb, axes[k, 1] / nb, axes[k, 2] / nb
            qw = 1.0 + ((a0 * b0 + a1 * b1) + a2 * b2)
            qx, qy, qz = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        degenerate[k] = not qw >= 1e-12
        if degenerate[k]:
            n_degenerate += 1
            continue
        norm = math.sqrt(((qx * qx + qy * qy) + qz * qz) + qw * qw)
        poses[r, 3], poses[r, 4], poses[r, 5], poses[r, 6] = (qx / norm, qy / norm, qz / norm,
                                                              qw / norm)
    for r in identity_rows:
        for j in range(6):
            poses[r, j] = 0.0
        poses[r, 6] = 1.0
    for j in range(capsules.shape[0]):
        k, h = capsules[j], half_lengths[j]
        for a in range(3):
            points[2 * j, a] = centres[k, a] - h * axes[k, a]
            points[2 * j + 1, a] = centres[k, a] + h * axes[k, a]
    return n_degenerate
