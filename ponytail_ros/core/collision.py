"""Contacts with kinematic colliders and joint limits: one-sided constraints after each step.

Only scenes with colliders (and chains that collide) or joint limits ever reach this module:
the simulator builds a ``Unilateral`` for them alone, and otherwise steps exactly as before.

Geometry. Every segment is a capsule (radius ``ChainSpec.radius``) around its whole length,
from its proximal to its distal joint. Colliders are spheres, capsules (a core segment inflated
by a radius) and planes, each fixed in a kinematic body (it moves with it) or in the world.
Depths are computed for all colliding segments × all colliders (compiled loops,
``narrow_phase.detect``): clamped point–segment distance for spheres, clamped segment–segment closest points
(Ericson, *Real-Time Collision Detection* 5.1.9) for capsules, the distal end for planes (every
joint but the anchor is some segment's distal end). A chain's first segment whose anchor is
inside or next to a round collider (hair rooted on a scalp) is tested on its outer half: a
contact by the anchor would have no lever.

Method: post-stabilisation (Cline & Pai 2003) with the chain's own factorisation. Every row r
(a contact normal, a swing or a twist limit) has a Jacobian ``J_r`` (at most two segments) and
a separation rate ``J_r u`` that must not go negative. Its Delassus matrix
``W = J_r P M⁻¹ J_rᵀ``, ``P`` the M-orthogonal projection onto motions that keep every joint
closed (the joint impulses solve J M⁻¹ Jᵀ λ = ..., the block-tridiagonal matrix of the
acceleration solve, factorised by block Cholesky in O(n), ``chain_solve``, and solved once per
row), is
the chain's exact response: an impulse at one hair moves the whole chain, joints closed. After
the integrator step and the joint projection, at the step's end time:

1. positions: the violated rows and those within a skin form the LCP
   ``W μ - depth ≥ 0, μ ≥ 0, μ·(W μ - depth) = 0``; the displacement ``P M⁻¹ J_rᵀ μ`` (the
   smallest in the mass metric) is applied as a rotation of each segment (≤ 0.25 rad), the
   positions rebuilt from the orientations (joints exactly closed); repeated while a contact is
   deeper than ``POSITION_TOLERANCE`` (≤ ``POSITION_ITERATIONS`` passes; 0 or 1 at rest). A
   cone is curved: limits get one such pass, then ``limits.project_limits`` puts them exactly
   back. The velocities, unchanged, are then projected M-orthogonally onto the moved joints
   (never adding kinetic energy);
2. velocities: every row touching, or whose gap would close within ``SPECULATIVE_STEPS``
   steps at its current rate (speculative contacts: a thin collider cannot be jumped over
   between two steps), gets the inelastic impulse of the LCP ``W λ + sep + max(gap, 0)/dt ≥ 0``.
   On a still head with static colliders the kinetic energy changes by
   ``-½ λᵀWλ - λ·gap/dt ≤ 0``: contacts and limits never add energy;
3. Coulomb friction (the collider's μ) on contacts that push: the tangential impulse that
   would stop every sliding contact, clipped to μ λ_n, then scaled along itself so that the
   kinetic energy cannot grow (one Jacobi step with an exact line search, not an exact
   Coulomb cone: sticking is reached over a few steps).

The simulator splits a step into sub-steps when a joint turns by more than
``simulator.SUBSTEP_ANGLE`` per step (impacts crack the chain like a whip; explicit RK4 at
1/240 s cannot follow the crack), each resolved as above.

Implementation. Everything after the step is one compiled call per ``resolve``
(``contact_stage.resolve``, numba, no fastmath): broad phase, detection, rows, position
passes, the limits' projection, the velocity projection, impulses and friction. This module
is the Python layer: it compiles the model's constant arrays once (``Unilateral``) and turns
the result back into arrays and ``last``.

Cost. Rows couple only within a chain: each row's response is one O(chain length) block
solve, so a chain with k rows costs O(n_chain · k), and its k×k LCP is solved exactly
(principal pivoting on the unit-diagonal W with dense exact solves; Lawson–Hanson as the
fall-back). Per step: nothing without colliders or limits; one broad phase per chain and
collider, then detection only of the segments of the (chain, collider) pairs within reach
(``broad_phase.near_pairs``: a crowd's detection is O(n), not O(n × colliders)); with
contacts about two detections, two factorisations and one response per row. The scratch of
a call is one workspace (``contact_model.workspace``), a few allocations per call.
"""
from dataclasses import dataclass

import numpy as np

from . import broad_phase, contact_model as K, contact_stage, narrow_phase
from .contact_impulses import solve_rows
from .contact_joints import joint_factors
from .contact_model import (  # noqa: F401 (the tolerances, re-exported)
    ANGLE_SKIN,
    MAX_ROTATION,
    MOBILITY,
    POSITION_ITERATIONS,
    POSITION_SKIN,
    POSITION_TOLERANCE,
    SPECULATIVE_STEPS,
    VELOCITY_SKIN,
)
from .contact_rows import build_rows
from .narrow_phase import ROOT_LEVER  # noqa: F401 (re-exported)
from .rotations import cross
from .state import half_vectors

__all__ = ['Unilateral', 'segment_depths', 'POSITION_TOLERANCE', 'POSITION_ITERATIONS',
           'SPECULATIVE_STEPS']


def _c(a):
    """``a`` as a writable C-contiguous float64 array (a copy only if needed): the kernels
    are compiled for exactly that type, so a read-only or strided view would compile them
    again."""
    a = np.ascontiguousarray(a, dtype=float)
    return a if a.flags.writeable else a.copy()


@dataclass
class ColliderPose:
    """The colliders in the world at one instant, in column order (spheres, capsules, planes).

    ``a0``: sphere centre, capsule core start or plane point; ``d2``: capsule core vector
    (zero otherwise); ``normal``: plane normal; ``origin``/``velocity``/``omega``: motion of
    the body they are fixed in (zero: world); ``speed``: a bound on the speed of the
    collider's surface, m/s.
    """

    a0: np.ndarray
    d2: np.ndarray
    normal: np.ndarray
    origin: np.ndarray
    velocity: np.ndarray
    omega: np.ndarray
    speed: np.ndarray

    def arrays(self):
        """The kernels' tuple ``(a0, d2, normal, origin, velocity, omega, speed)``."""
        return tuple(_c(a) for a in (
            self.a0, self.d2, self.normal, self.origin, self.velocity, self.omega, self.speed))

    def point_velocity(self, col, p):
        """Velocity of the material of colliders ``col`` at world points ``p``."""
        return self.velocity[col] + cross(self.omega[col], p - self.origin[col])


class Colliders:
    """A model's colliders, compiled once: column order spheres, capsules, planes."""

    def __init__(self, model):
        kind = model.collider_kind
        self.sphere = np.flatnonzero(kind == 'sphere')
        self.capsule = np.flatnonzero(kind == 'capsule')
        self.plane = np.flatnonzero(kind == 'plane')
        cols = np.concatenate([self.sphere, self.capsule, self.plane]).astype(np.intp)
        self.cols = cols
        self.n_sphere, self.n_capsule = self.sphere.size, self.capsule.size
        self.n_round = self.n_sphere + self.n_capsule
        self.radius = model.collider_radius[cols]
        self.friction = model.collider_friction[cols]
        self.body = model.collider_body[cols]
        hl = model.collider_half_length[cols]
        axis = model.collider_axis[cols]
        self.local_a0 = model.collider_center[cols] - hl[:, None] * axis
        self.local_d2 = 2.0 * hl[:, None] * axis
        self.local_normal = axis
        self.moving = np.flatnonzero(self.body >= 0)
        k = cols.size
        zeros = np.zeros((k, 3))
        self._static = ColliderPose(self.local_a0, self.local_d2, self.local_normal, zeros,
                                    zeros, zeros, np.zeros(k))
        # Distance from the body origin that bounds the collider's reach (for its speed).
        reach = (np.linalg.norm(self.local_a0, axis=1) + np.linalg.norm(self.local_d2, axis=1)
                 + self.radius)
        self.args = (self.body.astype(np.int64), _c(self.local_a0), _c(self.local_d2),
                     _c(self.local_normal), reach)

    def pose(self, bodies):
        """``ColliderPose`` given the kinematic bodies' origins (``AnchorKinematics``)."""
        if self.moving.size == 0:
            return self._static
        return ColliderPose(*broad_phase.collider_pose(_c(bodies.position), _c(bodies.orientation),
                                             _c(bodies.velocity), _c(bodies.angular_velocity),
                                             self.args))


class _Detector:
    """Depths of the colliding segments (capsules) in every collider, ``(m, K)`` at once
    (``narrow_phase.detect``), and the constant arrays it needs, built once.

    Spheres: closest point of the segment to the centre (clamped); capsules: clamped
    segment–segment closest points; planes: the segment's distal end (every joint but the
    anchor is some segment's distal end; ``report``: the deeper end). A pair makes no row when
    its point is a non-first segment's proximal joint: that is its parent's distal joint, the
    parent's row already (a duplicate row would make the Delassus matrix singular).

    A chain's first segment whose anchor lies inside a round collider or within a quarter
    segment of it (hair rooted on a scalp) is tested on its outer half only (closest point
    clamped to ``s ≥ ROOT_LEVER``): a contact next to an anchor that cannot move has almost no
    lever (an ill-conditioned row, huge impulses). Its inner half may then dip below the
    surface by up to the sag of a chord of half its length, (l/2)²/(8ρ) for a collider (plus
    segment) radius ρ: 0.45 mm for a 4 cm segment on a 0.11 m head.

    ``args``, the tuple the kernels take: the colliding segments, their radii and lengths,
    ``inner`` (not a chain's first), ``first_of`` (index among the first segments, or -1),
    each first segment's chain, ``root_fixed``/``rooted_fixed`` ``(f, K)`` (rooting decided
    once, and its answer), segment plus collider radius ``(m, K)``, the colliding chains and
    their reach (m), the longest half segment (m), the numbers of spheres and of round
    colliders, the collider radii (m) and friction coefficients, in column order.
    """

    def __init__(self, model, colliders):
        self.c = colliders
        self.seg = np.flatnonzero(model.collide).astype(np.int64)
        self.radius = model.radius[self.seg]
        first = model.is_first[self.seg]
        first_rows = np.flatnonzero(first)
        first_chain = model.chain_of[self.seg[first]].astype(np.int64)
        first_of = np.full(self.seg.size, -1, dtype=np.int64)
        first_of[first_rows] = np.arange(first_rows.size)
        self.length = model.length[self.seg]
        nr, k = colliders.n_round, colliders.cols.size
        # Segment radius plus collider radius (planes: the segment's alone, unused).
        sum_radius = colliders.radius[None, :] + self.radius[:, None]
        # Broad phase: the colliding chains, each within its length (+ radius) of its anchor.
        chains = np.unique(model.chain_of[self.seg]).astype(np.int64)
        ends = [model.chain_slice(c) for c in chains]
        chain_reach = np.array([model.length[e].sum() + model.radius[e].max() for e in ends])
        # Which first segments are rooted on which round colliders. Where the anchor and the
        # collider are fixed in the same body this never changes: decided once, here.
        chain_body = model.anchor_body[first_chain]
        root_fixed = np.zeros((first_rows.size, k), dtype=bool)
        root_fixed[:, :nr] = chain_body[:, None] == colliders.body[None, :nr]
        rooted_fixed = np.zeros_like(root_fixed)
        for f, c in enumerate(first_chain):
            for j in np.flatnonzero(root_fixed[f]):
                rooted_fixed[f, j] = narrow_phase.rooted(
                    tuple(model.attach[c]), tuple(colliders.local_a0[j]),
                    tuple(colliders.local_d2[j]), float(sum_radius[first_rows[f], j]),
                    float(self.length[first_rows[f]]))
        self.args = (self.seg, self.radius, self.length, ~first, first_of, first_chain,
                     root_fixed, rooted_fixed, sum_radius, chains, chain_reach,
                     0.5 * float(self.length.max()), int(colliders.n_sphere), int(nr),
                     colliders.radius.astype(float), colliders.friction.astype(float))

    @staticmethod
    def empty_args():
        """The kernels' detector tuple of a model without colliders (same types)."""
        i0, f0, b0 = np.zeros(0, np.int64), np.zeros(0), np.zeros(0, bool)
        return (i0, f0, f0, b0, i0, i0, np.zeros((0, 0), bool), np.zeros((0, 0), bool),
                np.zeros((0, 0)), i0, f0, 0.0, 0, 0, f0, f0)

    def detect(self, x, h, anchor_position, pose, report=False):
        """``depth`` (m, > 0 inside), the closest-point parameters ``s`` (on the segment) and
        ``t`` (on a capsule's core), and ``own`` (the pair may make a row), each ``(m, K)``."""
        shape = (self.seg.size, self.c.cols.size)
        depth, s, t = np.empty(shape), np.empty(shape), np.empty(shape)
        own = np.empty(shape, dtype=bool)
        narrow_phase.detect(_c(x), _c(h), _c(anchor_position), pose.arrays(), self.args,
                 bool(report), depth, s, t, own)
        return depth, s, t, own


def segment_depths(model, x, q, anchor_position, bodies):
    """Deepest penetration of every segment into any collider, ``(n,)``, m (≤ 0: clear; -inf
    for segments that do not collide), as the solver measures it (``_Detector``)."""
    out = np.full(model.n, -np.inf)
    if not model.has_colliders:
        return out
    colliders = Colliders(model)
    det = _Detector(model, colliders)
    depth = det.detect(x, half_vectors(model.length, q), anchor_position,
                       colliders.pose(bodies), report=True)[0]
    out[det.seg] = depth.max(axis=1)
    return out


def _split_args(model, detector):
    """``Unilateral.split_args``: what each chain's own model and detector tuples take besides
    views of the whole model's (``contact_model.chain_model``, ``chain_det``)."""
    i64 = np.int64
    start, end = model.chain_start.astype(i64), model.chain_end.astype(i64)
    seg_start = start[model.chain_of]                    # each segment's chain's first
    parent = np.where(model.is_first, -1, model.parent - seg_start).astype(i64)
    lim = np.flatnonzero(np.isfinite(model.swing_limit) | np.isfinite(model.twist_limit))
    lim_range = np.stack([np.searchsorted(lim, start), np.searchsorted(lim, end)]).astype(i64)
    C = model.n_chains
    slot, first, max_half = np.full(C, -1, i64), np.full(C, -1, i64), np.zeros(C)
    if detector is None:
        seg = np.zeros(0, i64)
        det_seg, first_of = seg, seg
    else:
        seg = detector.seg
        det_seg = (seg - seg_start[seg]).astype(i64)
        first_of = np.where(detector.args[K.D_FIRST_OF] >= 0, 0, -1).astype(i64)
        for k, c in enumerate(detector.args[K.D_CHAINS]):       # colliding chains, in order
            slot[c] = k
        for f, c in enumerate(detector.args[K.D_FIRST_CHAIN]):  # each first segment's chain
            first[c] = f
    det_range = np.stack([np.searchsorted(seg, start), np.searchsorted(seg, end)]).astype(i64)
    for c in range(C):
        if det_range[1, c] > det_range[0, c]:
            max_half[c] = 0.5 * float(model.length[seg[det_range[0, c]:det_range[1, c]]].max())
    return (parent, np.zeros(model.n, i64), (end - start).astype(i64),
            (lim - seg_start[lim]).astype(i64), lim_range, det_range, det_seg, first_of, slot,
            first, max_half)


def _anchor_arrays(anchor):
    return (_c(anchor.position), _c(anchor.velocity), _c(anchor.orientation),
            _c(anchor.angular_velocity))


_NO_POSE = ColliderPose(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)),
                        np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))


class Unilateral:
    """Contacts and joint limits of one model, resolved after every internal step.

    For a compiled step loop: ``model_args`` and ``detector_args`` are the constant tuples
    that ``contact_stage.resolve`` takes (``model_args``: length, 1/m, principal 1/I
    ``(n, 3)``, the largest 1/I, is_first, has_child, parent, chain_of, chain_start,
    chain_end, axisymmetric, the limited joints, swing and twist limits; ``detector_args``:
    see ``_Detector``), ``colliders.args`` the one of ``broad_phase.collider_pose``;
    ``resolve`` is callable from other njit code with them. ``split_args``: their split by
    chain (``contact_model.SP_*``): the kernels resolve each chain on its own, as if it
    were alone with all the colliders (``contact_stage.resolve_chains_into``).
    """

    def __init__(self, model, dt):
        self.model = model
        self.step = self.dt = dt
        self.colliders = Colliders(model) if model.has_colliders else None
        self.detector = _Detector(model, self.colliders) if model.has_colliders else None
        I = model.inertia
        axisymmetric = bool(np.allclose(I[:, 1], I[:, 2], rtol=1e-12, atol=0.0))
        lim = np.flatnonzero(np.isfinite(model.swing_limit)
                             | np.isfinite(model.twist_limit)).astype(np.int64)
        i64 = np.int64
        self.model_args = (model.length.astype(float), model.inv_mass.astype(float),
                       _c(model.inv_inertia),
                       model.inv_inertia.max(axis=1), model.is_first.copy(),
                       model.has_child.copy(), model.parent.astype(i64),
                       model.chain_of.astype(i64), model.chain_start.astype(i64),
                       model.chain_end.astype(i64), axisymmetric, lim,
                       model.swing_limit.astype(float), model.twist_limit.astype(float))
        self.detector_args = (self.detector.args if self.detector is not None else
                     _Detector.empty_args())
        self.split_args = _split_args(model, self.detector)
        self._stats = np.zeros(3, dtype=np.int64)
        self.last = {'contacts': 0, 'limits': 0, 'position_passes': 0}
        # The compiled step loop's contact workspace, built at its first call and kept (see
        # ``step_unilateral.advance_unilateral``): it belongs to this structure.
        self.workspace = None
        # The colliders' pose arrays in their bodies (the compiled loop poses moving ones
        # from them): constant for this structure, built once.
        self.static_pose = self._pose_arrays(None if self.colliders is None
                                             else self.colliders._static)

    def pose(self, bodies):
        """``ColliderPose`` of the colliders for the kinematic bodies' origins (or ``None``)."""
        return None if self.colliders is None else self.colliders.pose(bodies)

    def _pose_arrays(self, pose):
        return (_NO_POSE if pose is None else pose).arrays()

    # -- rows (for inspection and tests; ``resolve`` builds its own inside the kernel) -------
    def rows(self, x, q, v, w, anchor, pose):
        """Contact and limit rows within reach of this step's stages (dict of arrays), or
        ``None``: contacts first (segment-major), then swing, then twist rows.

        A pair is a candidate if it is inside, within the position skin, or could close within
        ``SPECULATIVE_STEPS`` steps at a bound of the two surfaces' speeds.
        """
        R, I = build_rows(*self._state(x, q, v, w), _anchor_arrays(anchor),
                            _c(self.model.q_rest),
                            self._pose_arrays(pose), self.model_args, self.detector_args,
                            self.split_args, self.detector is not None, float(self.dt))
        if R.shape[0] == 0:
            return None
        return _rows_dict(R, I)

    def _solve(self, rows, q, b, friction_bound=None):
        """Impulses ``λ`` of ``rows`` (a ``rows`` dict) at orientations ``q``: the exact LCP
        ``Wλ + b ≥ 0, λ ≥ 0, λ·(Wλ + b) = 0``, or with ``friction_bound`` the energy-safe
        friction step; and the velocity change ``(Δv, Δω)`` of every segment."""
        n = self.model.n
        h, inv_I = np.empty((n, 3)), np.empty((n, 3, 3))
        C, Lo = np.empty((n, 3, 3)), np.empty((n, 3, 3))
        if not joint_factors(_c(q), self.model_args, h, inv_I, C, Lo):
            raise np.linalg.LinAlgError('J M⁻¹ Jᵀ is not positive definite')
        R, I = _rows_arrays(rows)
        b = _c(b)
        bound = np.zeros(0) if friction_bound is None else _c(friction_bound)
        dv, dw = np.zeros((n, 3)), np.zeros((n, 3))
        lam = solve_rows(R, I, b, bound, h, inv_I, C, Lo, self.model_args, dv, dw)
        return lam, dv, dw

    def _state(self, x, q, v, w):
        return tuple(_c(a) for a in (x, q, v, w))

    # -- the pass after a step ---------------------------------------------------------------
    def resolve(self, x, q, v, w, anchor, pose, project=True, dt=None):
        """Contacts and limits at the end of a step (of length ``dt``): positions, then
        velocities (inelastic impulses, then friction). ``anchor``: ``AnchorKinematics`` at
        that time; ``pose``: ``ColliderPose`` (``None`` without colliders). Returns
        ``(x, q, v, w)`` (new arrays).

        Positions: mass-weighted passes of the linearised LCP over contacts and limits, while
        a contact is deeper than ``POSITION_TOLERANCE`` (limits: one pass), then the limits'
        exact projection (``limits.project_limits``) for what the linearisation of their
        cones left (second order). Then the unchanged velocities are projected onto the moved
        joints (M-orthogonally: no kinetic energy is added) before the velocity stage. One
        compiled call (``contact_stage.resolve``).
        """
        self.dt = self.step if dt is None else dt
        stats = self._stats
        status, x, q, v, w = contact_stage.resolve(
            *self._state(x, q, v, w), _anchor_arrays(anchor), self._pose_arrays(pose),
            self.model_args, self.detector_args, self.split_args, _c(self.model.q_rest),
            self.detector is not None, bool(project), float(self.dt), stats)
        self.last = {'contacts': int(stats[0]), 'limits': int(stats[1]),
                     'position_passes': int(stats[2])}
        if status != K.OK:
            raise np.linalg.LinAlgError('J M⁻¹ Jᵀ is not positive definite')
        return x, q, v, w


_ROW_VECTORS = (('lin', K.LIN), ('ang', K.ANG), ('ang_par', K.APAR), ('arm', K.ARM),
                ('v_other', K.VOTH))
_ROW_SCALARS = (('depth', K.DEPTH), ('sep', K.SEP), ('mu', K.MU))


def _rows_dict(R, I):
    """Rows as a dict of arrays: ``seg``, ``par``, ``lin``, ``ang``, ``ang_par``, ``depth``,
    ``sep``, ``mu``, ``arm``, ``v_other``, ``contact``."""
    out = dict(seg=I[:, K.SEG].copy(), par=I[:, K.PAR].copy(),
               contact=I[:, K.CONTACT].astype(bool))
    out.update({name: R[:, c:c + 3].copy() for name, c in _ROW_VECTORS})
    out.update({name: R[:, c].copy() for name, c in _ROW_SCALARS})
    return out


def _rows_arrays(rows):
    """The kernel's ``(R, I)`` of a rows dict (missing entries: zero)."""
    k = len(rows['seg'])
    R = np.zeros((k, K.NCOL))
    I = np.zeros((k, 3), dtype=np.int64)
    I[:, K.SEG] = rows['seg']
    I[:, K.PAR] = rows.get('par', np.full(k, -1))
    I[:, K.CONTACT] = rows.get('contact', np.ones(k, bool))
    for name, c in _ROW_VECTORS:
        if name in rows:
            R[:, c:c + 3] = rows[name]
    for name, c in _ROW_SCALARS:
        if name in rows:
            R[:, c] = rows[name]
    return R, I
