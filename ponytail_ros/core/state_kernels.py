"""Compiled per-tick queries of the chain state (numba, nopython, no fastmath): what the guard
measures after a call, and the segment poses a node publishes.

Both read the state arrays of ``ChainState`` (world frame, SI: ``x`` ``(n, 3)`` centres,
``q`` ``(n, 4)`` (x, y, z, w) body to world, ``v`` ``(n, 3)``, ``w`` ``(n, 3)`` ω) and the
chain structure of ``Model`` (``length``, ``is_first``, ``chain_of``); joint ``i``'s parent is
its chain's anchor when ``is_first[i]``, else segment ``i - 1``. One call replaces the dozen
NumPy calls on tiny arrays that each of these took per tick.
"""
import math

from numba import njit

from .vec import qaxis_x, qfrom_rotvec, qmul

__all__ = ['guard_measures', 'segment_poses', 'MEASURES']

#: ``guard_measures``' output, in order.
MEASURES = ('finite', 'max_gap', 'max_speed', 'max_joint_rate', 'max_checked_rate',
            'max_axial_precession')


@njit(cache=True)
def guard_measures(length, is_first, chain_of, inertia, x, q, v, w, anchor_position,
                   anchor_omega, swing_only, out):
    """The guard's figures of the state, into ``out`` ``(6,)`` (``MEASURES``):

    * finite: 1.0 if every entry of x, q, v, w is finite, else 0.0 (then nothing else is set);
    * the largest joint gap, m: |parent's joint point − the child's proximal end|;
    * the largest centre speed |v|, m/s;
    * the largest joint angular speed |ω_i − ω_parent|, rad/s (what sub-steps are chosen by);
    * the same, checked: with ``swing_only`` the part about the child's own axis left out (the
      constrained integrators turn a segment about its axis exactly at any rate);
    * the largest axial precession rate |ω·e| |1 − I_a/I_p| of axisymmetric segments
      (``inertia`` ``(n, 3)``, axial first), rad/s.
    """
    n = x.shape[0]
    for i in range(n):
        for a in range(3):
            if not (math.isfinite(x[i, a]) and math.isfinite(v[i, a])
                    and math.isfinite(w[i, a])):
                out[0] = 0.0
                return
        for a in range(4):
            if not math.isfinite(q[i, a]):
                out[0] = 0.0
                return
    out[0] = 1.0
    gap = speed = rate = checked = precession = 0.0
    e_prev = (0.0, 0.0, 0.0)
    for i in range(n):
        c = chain_of[i]
        e = qaxis_x((q[i, 0], q[i, 1], q[i, 2], q[i, 3]))
        if is_first[i]:
            pp = (anchor_position[c, 0], anchor_position[c, 1], anchor_position[c, 2])
            pw = (anchor_omega[c, 0], anchor_omega[c, 1], anchor_omega[c, 2])
        else:                               # the parent's distal joint, the parent's ω
            hp = 0.5 * length[i - 1]
            pp = (x[i - 1, 0] + hp * e_prev[0], x[i - 1, 1] + hp * e_prev[1],
                  x[i - 1, 2] + hp * e_prev[2])
            pw = (w[i - 1, 0], w[i - 1, 1], w[i - 1, 2])
        half = 0.5 * length[i]
        d0 = pp[0] - (x[i, 0] - half * e[0])
        d1 = pp[1] - (x[i, 1] - half * e[1])
        d2 = pp[2] - (x[i, 2] - half * e[2])
        r0, r1, r2 = w[i, 0] - pw[0], w[i, 1] - pw[1], w[i, 2] - pw[2]
        e_prev = e
        gap = max(gap, math.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
        speed = max(speed, math.sqrt(v[i, 0] ** 2 + v[i, 1] ** 2 + v[i, 2] ** 2))
        rate = max(rate, math.sqrt(r0 * r0 + r1 * r1 + r2 * r2))
        if swing_only:
            along = r0 * e[0] + r1 * e[1] + r2 * e[2]
            checked = max(checked, math.sqrt((r0 - along * e[0]) ** 2 + (r1 - along * e[1]) ** 2
                                             + (r2 - along * e[2]) ** 2))
        else:
            checked = rate
        spin = w[i, 0] * e[0] + w[i, 1] * e[1] + w[i, 2] * e[2]
        precession = max(precession, abs(spin * (1.0 - inertia[i, 0] / inertia[i, 1])))
    out[1], out[2], out[3], out[4], out[5] = gap, speed, rate, checked, precession


@njit(cache=True)
def segment_poses(length, is_first, chain_of, x, q, w, tau, anchor_position, origins, quats):
    """Every segment's origin (its proximal joint, m) and orientation, into ``origins``
    ``(n, 3)`` and ``quats`` ``(n, 4)``, for the chain ``tau`` s after its state.

    ``tau ≤ 0``: the state itself (origin = x − (l/2) e). Otherwise each orientation is carried
    forward by its ω (q ← exp(ω τ) ⊗ q, error O(α τ²)) and the origins rebuilt from the
    anchor at that time, ``anchor_position`` ``(C, 3)``, along the chain (joints closed
    exactly), as ``Simulator.state_at`` does.
    """
    n = x.shape[0]
    e_prev = (0.0, 0.0, 0.0)
    for i in range(n):
        qi = (q[i, 0], q[i, 1], q[i, 2], q[i, 3])
        if tau > 0.0:
            qi = qmul(qfrom_rotvec((w[i, 0] * tau, w[i, 1] * tau, w[i, 2] * tau)), qi)
        for a in range(4):
            quats[i, a] = qi[a]
        e = qaxis_x(qi)
        for a in range(3):
            if tau <= 0.0:
                origins[i, a] = x[i, a] - 0.5 * length[i] * e[a]
            elif is_first[i]:
                origins[i, a] = anchor_position[chain_of[i], a]
            else:
                origins[i, a] = origins[i - 1, a] + length[i - 1] * e_prev[a]
        e_prev = e
