"""Oracle (test only): the NumPy + SciPy implementation of ``ponytail_ros.core.collision``
before it was compiled (``contact_stage``), kept to check the compiled resolve against. The
chain's mass terms and banded storage are copied here (from ``solver``) so that it does not
depend on the dynamics being rewritten.

Contacts with kinematic colliders and joint limits: one-sided constraints after each step.

Only scenes with colliders (and chains that collide) or joint limits ever reach this module:
the simulator builds a ``Unilateral`` for them alone, and otherwise steps exactly as before.

Geometry. Every segment is a capsule (radius ``ChainSpec.radius``) around its whole length,
from its proximal to its distal joint. Colliders are spheres, capsules (a core segment inflated
by a radius) and planes, each fixed in a kinematic body (it moves with it) or in the world.
Depths are computed for all colliding segments × all colliders at once (numpy, no per-segment
loop): clamped point–segment distance for spheres, clamped segment–segment closest points
(Ericson, *Real-Time Collision Detection* 5.1.9) for capsules, the distal end for planes (every
joint but the anchor is some segment's distal end). A chain's first segment whose anchor is
inside or next to a round collider (hair rooted on a scalp) is tested on its outer half: a
contact by the anchor would have no lever.

Method: post-stabilisation (Cline & Pai 2003) with the chain's own factorisation. Every row r
(a contact normal, a swing or a twist limit) has a Jacobian ``J_r`` (at most two segments) and
a separation rate ``J_r u`` that must not go negative. Its Delassus matrix
``W = J_r P M⁻¹ J_rᵀ``, ``P`` the M-orthogonal projection onto motions that keep every joint
closed (the joint impulses solve J M⁻¹ Jᵀ λ = ..., the block-tridiagonal matrix of the
acceleration solve, factorised by banded Cholesky in O(n) and solved for all rows at once), is
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

Cost. Rows couple only within a chain, so the j-th rows of all chains share the j-th
right-hand side of the banded solve: O(n · k_max), k_max the most rows of one chain; each
touching chain's k×k LCP is solved exactly by NNLS on the Cholesky factor of its (unit-
diagonal) W. Per step: nothing without colliders or limits; one vectorised detection
(O(n × colliders)) when nothing is near; with contacts about two detections, two
factorisations, two or three banded solves with k_max right-hand sides and one small NNLS.
"""
from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack
from scipy.optimize import nnls

from ponytail_ros.core.head import AnchorKinematics
from ponytail_ros.core.model import Model
from ponytail_ros.core.rotations import (
    cross,
    quat_axis_x,
    quat_integrate,
    quat_normalize,
    quat_rotate,
    quat_to_matrix,
    skew,
)
from ponytail_ros.core.state import half_vectors

import _oracle_limits as limits
from oracle.stabilization import project_positions, project_velocities

__all__ = ['Unilateral', 'segment_depths', 'POSITION_TOLERANCE', 'POSITION_ITERATIONS',
           'SPECULATIVE_STEPS']

POSITION_ITERATIONS = 4      # passes of the position LCP per step, at most
POSITION_TOLERANCE = 1e-5    # m (contacts), rad (limits): stop once no violation exceeds this
POSITION_SKIN = 1e-3         # m: contacts this close (plus 4× the deepest violation) join the
                             # position LCP as inequalities (a correction must not push a
                             # neighbouring segment in)
ANGLE_SKIN = 1e-3            # rad: the same for limits
VELOCITY_SKIN = 1e-4         # m: a contact this close is touching for the velocity stage
SPECULATIVE_STEPS = 2.0      # a gap closing within this many steps joins the velocity stage
ROOT_LEVER = 0.5             # a rooted first segment is tested on s in [ROOT_LEVER, 1]
MAX_ROTATION = 0.25          # rad: largest rotation of one segment per position pass
MOBILITY = 1e-8              # a row the jointed chain moves less than this fraction of its
                             # free segment's mobility (a contact at the anchor) is left out
_REG = 1e-9                  # relative regularisation of the (unit-diagonal) Delassus matrix


_KD = 5  # half-bandwidth of a block-tridiagonal matrix with 3×3 blocks


def _banded_indices(n):
    """Flat indices into the ``(6, 3n)`` upper banded storage (copied from ``solver``)."""
    a, b = np.meshgrid(np.arange(3), np.arange(3), indexing='ij')
    upper = (a <= b)
    da, db = a[upper], b[upper]
    j = np.arange(n)[:, None]
    diag_flat = ((_KD + da - db) * 3 * n + 3 * j + db).ravel()
    ca, cb = a.ravel(), b.ravel()
    off_flat = ((2 + ca - cb) * 3 * n + 3 * j + cb).ravel()
    return (da, db, diag_flat), (ca, cb, off_flat)


def _mass_terms(m, axisymmetric, q):
    """Half-vectors ``h`` and ``G = [h]× I⁻¹ [h]×`` (copied from ``solver.Dynamics``)."""
    half = 0.5 * m.length
    if axisymmetric:
        e = quat_axis_x(q)
        h = half[:, None] * e
        hh = np.sum(h * h, axis=1)
        G = h[:, :, None] * h[:, None, :]
        G[:, [0, 1, 2], [0, 1, 2]] -= hh[:, None]
        G *= (1.0 / m.inertia[:, 1])[:, None, None]
        return h, G
    R = quat_to_matrix(q)
    h = half[:, None] * R[:, :, 0]
    inv_I_world = (R * m.inv_inertia[:, None, :]) @ R.transpose(0, 2, 1)
    S = skew(h)
    return h, S @ inv_I_world @ S


def _blocks(m, G):
    """Diagonal blocks ``D`` and coupling blocks ``L[i] = A[i, i-1]`` of J M⁻¹ Jᵀ."""
    couple = (~m.is_first)[1:, None, None].astype(float)
    inv_m = m.inv_mass[:, None, None]
    eye = np.eye(3)
    K_pp = inv_m * eye - G
    D = K_pp.copy()
    D[1:] += K_pp[:-1] * couple
    L = np.zeros_like(D)
    L[1:] = -(inv_m[:-1] * eye + G[:-1]) * couple
    return D, L


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
        self.all_moving = self.moving.size == cols.size
        self._local = np.stack([self.local_a0, self.local_d2, self.local_normal], axis=1)
        k = cols.size
        zeros = np.zeros((k, 3))
        self._static = ColliderPose(self.local_a0, self.local_d2, self.local_normal, zeros,
                                    zeros, zeros, np.zeros(k))
        # Distance from the body origin that bounds the collider's reach (for its speed).
        self._reach = (np.linalg.norm(self.local_a0, axis=1)
                       + np.linalg.norm(self.local_d2, axis=1)
                       + self.radius)

    def pose(self, bodies):
        """``ColliderPose`` given the kinematic bodies' origins (``AnchorKinematics``)."""
        if self.moving.size == 0:
            return self._static
        if self.all_moving:
            b = self.body
            rot = quat_rotate(bodies.orientation[b][:, None, :], self._local)
            origin, vel, om = bodies.position[b], bodies.velocity[b], bodies.angular_velocity[b]
            speed = (np.sqrt(np.einsum('ij,ij->i', vel, vel))
                     + np.sqrt(np.einsum('ij,ij->i', om, om)) * self._reach)
            return ColliderPose(origin + rot[:, 0], rot[:, 1], rot[:, 2], origin, vel, om, speed)
        mv, b = self.moving, self.body[self.moving]
        local = self._local.copy()
        k = local.shape[0]
        origin, vel, om = np.zeros((k, 3)), np.zeros((k, 3)), np.zeros((k, 3))
        origin[mv] = bodies.position[b]
        local[mv] = quat_rotate(bodies.orientation[b][:, None, :], local[mv])
        local[mv, 0] += origin[mv]
        vel[mv] = bodies.velocity[b]
        om[mv] = bodies.angular_velocity[b]
        speed = np.zeros(k)
        speed[mv] = (np.linalg.norm(vel[mv], axis=1)
                     + np.linalg.norm(om[mv], axis=1) * self._reach[mv])
        return ColliderPose(local[:, 0], local[:, 1], local[:, 2], origin, vel, om, speed)


def _closest_segment_segment(p0, d1, a0, d2):
    """Clamped closest points of segments ``p0 + s d1`` (m rows) and ``a0 + t d2`` (K cols,
    ``d2`` non-zero). Returns ``s``, ``t`` of shape ``(m, K)``."""
    r = p0[:, None, :] - a0[None, :, :]
    a = np.sum(d1 * d1, axis=1)[:, None]
    e = np.sum(d2 * d2, axis=1)[None, :]
    b = d1 @ d2.T
    c = np.einsum('mj,mkj->mk', d1, r)
    f = np.einsum('kj,mkj->mk', d2, r)
    denom = a * e - b * b
    ok = denom > 1e-12 * a * e
    s = np.where(ok, np.clip((b * f - c * e) / np.where(ok, denom, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / e
    s = np.where(t < 0.0, np.clip(-c / a, 0.0, 1.0),
                 np.where(t > 1.0, np.clip((b - c) / a, 0.0, 1.0), s))
    return s, np.clip(t, 0.0, 1.0)


def _any_perpendicular(d):
    ref = np.where(np.abs(d[..., :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    p = cross(d, ref)
    return p / np.linalg.norm(p, axis=-1, keepdims=True)


class _Detector:
    """Depths of the colliding segments (capsules) in every collider, ``(m, K)`` at once.

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
    """

    def __init__(self, model, colliders):
        self.c = colliders
        self.seg = np.flatnonzero(model.collide)
        self.radius = model.radius[self.seg]
        first = model.is_first[self.seg]
        self.first_rows = np.flatnonzero(first)
        self.first_chain = model.chain_of[self.seg[first]]
        self.inner = ~first[:, None]
        self.length = model.length[self.seg]
        self.sum_radius = colliders.radius[None, :colliders.n_round] + self.radius[:, None]
        # Broad phase: the colliding chains, each within its length (+ radius) of its anchor.
        self.chains = np.unique(model.chain_of[self.seg])
        ends = [model.chain_slice(c) for c in self.chains]
        self.chain_reach = np.array([model.length[e].sum() + model.radius[e].max() for e in ends])
        self.max_half_length = 0.5 * float(self.length.max())
        # Which first segments are rooted on which round colliders. Where the anchor and the
        # collider are fixed in the same body this never changes: decided once, here.
        nr = colliders.n_round
        chain_body = model.anchor_body[self.first_chain]
        self.root_fixed = chain_body[:, None] == colliders.body[None, :nr]
        self.root_fixed_all = bool(np.all(self.root_fixed))
        self.rooted_fixed = np.zeros(self.root_fixed.shape, dtype=bool)
        if np.any(self.root_fixed):
            a0, d2 = colliders.local_a0[:nr], colliders.local_d2[:nr]
            self.rooted_fixed = self._rooted(model.attach[self.first_chain], a0, d2) \
                & self.root_fixed

    def _rooted(self, anchor, a0, d2):
        """Anchors ``(f, 3)`` inside, or within a quarter segment of, each round collider."""
        e2 = np.maximum(np.einsum('kj,kj->k', d2, d2), 1e-300)
        rel = anchor[:, None, :] - a0[None]
        ta = np.clip(np.einsum('fkj,kj->fk', rel, d2) / e2, 0.0, 1.0)
        root = self.sum_radius[self.first_rows] - np.linalg.norm(rel - ta[..., None] * d2[None],
                                                                 axis=2)
        return root > -0.25 * self.length[self.first_rows][:, None]

    def detect(self, x, h, anchor_position, pose, report=False):
        """``depth`` (m, > 0 inside), the closest-point parameters ``s`` (on the segment) and
        ``t`` (on a capsule's core), and ``own`` (the pair may make a row), each ``(m, K)``."""
        c, seg = self.c, self.seg
        p0 = x[seg] - h[seg]
        d1 = 2.0 * h[seg]
        m = seg.size
        depth, s_all, t_all, own = [], [], [], []
        nr = c.n_round
        if nr:
            s = np.empty((m, nr))
            t = np.zeros((m, nr))
            ns = c.n_sphere
            if ns:
                r = pose.a0[None, :ns] - p0[:, None, :]
                s[:, :ns] = np.clip(np.einsum('mkj,mj->mk', r, d1)
                                    / (self.length ** 2)[:, None], 0.0, 1.0)
            if c.n_capsule:
                s[:, ns:], t[:, ns:] = _closest_segment_segment(p0, d1, pose.a0[ns:nr],
                                                                pose.d2[ns:nr])
            fr = self.first_rows
            if fr.size:
                # A first segment rooted in (or within a quarter segment of) a round
                # collider: its row is at its distal joint, with the full segment as lever.
                if self.root_fixed_all:
                    rooted = self.rooted_fixed
                else:
                    rooted = np.where(self.root_fixed, self.rooted_fixed, self._rooted(
                        anchor_position[self.first_chain], pose.a0[:nr], pose.d2[:nr]))
                if np.any(rooted):
                    d2 = pose.d2[:nr]
                    e2 = np.maximum(np.einsum('kj,kj->k', d2, d2), 1e-300)
                    sf = np.where(rooted, np.maximum(s[fr], ROOT_LEVER), s[fr])
                    pf = p0[fr][:, None, :] + sf[..., None] * d1[fr][:, None, :]
                    tf = np.clip(np.einsum('fkj,kj->fk', pf - pose.a0[None, :nr], d2) / e2,
                                 0.0, 1.0)
                    s[fr], t[fr] = sf, np.where(rooted, tf, t[fr])
            core = pose.a0[None, :nr] + t[..., None] * pose.d2[None, :nr]
            diff = p0[:, None, :] + s[..., None] * d1[:, None, :] - core
            depth.append(self.sum_radius - np.sqrt(np.einsum('mkj,mkj->mk', diff, diff)))
            s_all.append(s)
            t_all.append(t)
            own.append(~(self.inner & (s <= 0.0)))
        if c.plane.size:
            pp, nn = pose.a0[nr:], pose.normal[nr:]
            off = np.sum(pp * nn, axis=1)[None]
            s1 = (p0 + d1) @ nn.T - off
            if report:
                s1 = np.minimum(s1, p0 @ nn.T - off)
            depth.append(self.radius[:, None] - s1)
            s_all.append(np.ones_like(s1))
            t_all.append(np.zeros_like(s1))
            own.append(np.ones(s1.shape, dtype=bool))
        if len(depth) == 1:
            return depth[0], s_all[0], t_all[0], own[0]
        return (np.concatenate(depth, axis=1), np.concatenate(s_all, axis=1),
                np.concatenate(t_all, axis=1), np.concatenate(own, axis=1))

    def contact_frames(self, i, j, s, t, x, h, pose):
        """For pairs (segment row ``i``, column ``j``): the normal (from the collider to the
        segment) and the touching point on the segment's surface, ``(k, 3)`` each."""
        seg = self.seg[i]
        ps = x[seg] + (2.0 * s - 1.0)[:, None] * h[seg]
        is_plane = j >= self.c.n_round
        diff = ps - (pose.a0[j] + t[:, None] * pose.d2[j])
        dist = np.linalg.norm(diff, axis=1)
        n = diff / np.where(dist > 1e-12, dist, 1.0)[:, None]
        bad = (dist <= 1e-12) & ~is_plane
        if np.any(bad):
            n[bad] = _any_perpendicular(h[seg[bad]])
        if np.any(is_plane):
            n[is_plane] = pose.normal[j[is_plane]]
        return n, ps - self.radius[i][:, None] * n


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


def _rows_concat(parts):
    parts = [p for p in parts if p is not None]
    if not parts:
        return None
    if len(parts) == 1:
        return parts[0]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


class Unilateral:
    """Contacts and joint limits of a model, resolved after every internal step chain by
    chain: each chain as if it were alone with all the colliders (``_ChainUnilateral`` of a
    model of that chain alone), as ``contact_stage.resolve_chains_into`` does: chains do
    not touch one another. ``last``: contacts and limits summed, the most position passes."""

    def __init__(self, model, dt):
        self.model = model
        self.step = self.dt = dt
        self.colliders = Colliders(model) if model.has_colliders else None
        self._chains = []
        for c, chain in enumerate(model.scene.chains):
            sub = Model(model.scene.replace(chains=(chain,)))
            if sub.has_colliders or sub.has_limits:
                self._chains.append((model.chain_slice(c), c, _ChainUnilateral(sub, dt)))
        self.last = {'contacts': 0, 'limits': 0, 'position_passes': 0}

    def pose(self, bodies):
        """``ColliderPose`` of the colliders for the kinematic bodies' origins (or ``None``)."""
        return None if self.colliders is None else self.colliders.pose(bodies)

    def _each(self, anchor):
        """Per chain with something to resolve: its segments, its anchor row, its oracle (its
        rest rotations taken from the whole model's, which the simulator's reset sets)."""
        for sl, c, uni in self._chains:
            uni.model.q_rest[:] = self.model.q_rest[sl]
            uni.dt = self.dt
            row = AnchorKinematics(*(a[c:c + 1] for a in (
                anchor.position, anchor.velocity, anchor.acceleration, anchor.orientation,
                anchor.angular_velocity)))
            yield sl, row, uni

    def rows(self, x, q, v, w, anchor, pose):
        """Every chain's rows (``_ChainUnilateral.rows``), segments numbered in the model."""
        parts = []
        for sl, row, uni in self._each(anchor):
            r = uni.rows(x[sl], q[sl], v[sl], w[sl], row, pose)
            if r is not None:
                r = dict(r, seg=r['seg'] + sl.start,
                         par=np.where(r['par'] >= 0, r['par'] + sl.start, -1))
                parts.append(r)
        return _rows_concat(parts)

    def resolve(self, x, q, v, w, anchor, pose, project=True, dt=None):
        """``_ChainUnilateral.resolve`` of every chain; returns ``(x, q, v, w)``."""
        self.dt = self.step if dt is None else dt
        out = [np.array(a, dtype=float) for a in (x, q, v, w)]
        self.last = {'contacts': 0, 'limits': 0, 'position_passes': 0}
        for sl, row, uni in self._each(anchor):
            got = uni.resolve(x[sl], q[sl], v[sl], w[sl], row, pose, project, self.dt)
            for o, g in zip(out, got, strict=True):
                o[sl] = g
            self.last['contacts'] += uni.last['contacts']
            self.last['limits'] += uni.last['limits']
            self.last['position_passes'] = max(self.last['position_passes'],
                                               uni.last['position_passes'])
        return tuple(out)


class _ChainUnilateral:
    """Contacts and joint limits of one model, resolved after every internal step."""

    def __init__(self, model, dt):
        self.model = model
        I = model.inertia
        self.axisymmetric = bool(np.allclose(I[:, 1], I[:, 2], rtol=1e-12, atol=0.0))
        self.step = self.dt = dt
        self.colliders = Colliders(model) if model.has_colliders else None
        self.detector = _Detector(model, self.colliders) if model.has_colliders else None
        self._banded = _banded_indices(model.n)
        self._inner = (~model.is_first[1:])[None, :, None]
        self._inv_I_max = model.inv_inertia.max(axis=1)
        self._has_child = model.has_child[None, :-1, None]
        self.last = {'contacts': 0, 'limits': 0, 'position_passes': 0}

    def pose(self, bodies):
        """``ColliderPose`` of the colliders for the kinematic bodies' origins (or ``None``)."""
        return None if self.colliders is None else self.colliders.pose(bodies)

    # -- rows -------------------------------------------------------------------------------
    def rows(self, x, q, v, w, anchor, pose):
        """Contact and limit rows within reach of this step's stages (dict of arrays).

        A pair is a candidate if it is inside, within the position skin, or could close within
        ``SPECULATIVE_STEPS`` steps at a bound of the two surfaces' speeds.
        """
        m, dt = self.model, self.dt
        parts = []
        if self.detector is not None and self._near(anchor.position, pose, v, w):
            det = self.detector
            h = half_vectors(m.length, q)
            depth, s, t, own = det.detect(x, h, anchor.position, pose)
            seg = det.seg
            worst = max(float(depth.max()), 0.0)
            speed = (np.sqrt(np.einsum('ij,ij->i', v[seg], v[seg]))
                     + np.sqrt(np.einsum('ij,ij->i', w[seg], w[seg])) * 0.5 * det.length)
            reach = (max(POSITION_SKIN + 4.0 * worst, VELOCITY_SKIN)
                     + SPECULATIVE_STEPS * dt * (speed[:, None] + pose.speed[None, :]))
            i, j = np.nonzero(own & (depth > -reach))
            if i.size:
                n, point = det.contact_frames(i, j, s[i, j], t[i, j], x, h, pose)
                sg = seg[i]
                arm = point - x[sg]
                v_col = pose.point_velocity(j, point)
                sep = np.einsum('ij,ij->i', n, v[sg] + cross(w[sg], arm) - v_col)
                parts.append(dict(seg=sg, par=np.full(i.size, -1), lin=n, ang=cross(arm, n),
                                  ang_par=np.zeros_like(n), depth=depth[i, j], sep=sep,
                                  mu=self.colliders.friction[j], arm=arm, v_other=v_col,
                                  contact=np.ones(i.size, bool)))
        if m.has_limits:
            def keep(gap, sep):
                # As for contacts: the skin grows with the deepest violation, so that a
                # correction does not push a neighbouring joint past its limit unseen.
                skin = ANGLE_SKIN + 4.0 * max(-float(np.min(gap)), 0.0)
                return (gap < skin) | ((sep < 0.0) & (gap < -SPECULATIVE_STEPS * dt * sep))
            lim = limits.limit_rows(m, q, w, anchor, keep)
            if lim is not None:
                k = lim['seg'].size
                lim.update(mu=np.zeros(k), arm=np.zeros((k, 3)), v_other=np.zeros((k, 3)),
                           contact=np.zeros(k, bool))
                parts.append(lim)
        return _rows_concat(parts)

    def _near(self, anchor_position, pose, v, w):
        """Broad phase: could any collider be within reach of a chain? A chain lies in the
        ball of its length about its anchor; its surface moves at most at its fastest
        centre's speed plus its fastest segment's spin times half its length."""
        c, det = self.colliders, self.detector
        p = anchor_position[det.chains]                                  # (C', 3)
        nr = c.n_round
        dist = np.empty((p.shape[0], c.cols.size))
        if nr:
            a0, d2 = pose.a0[:nr], pose.d2[:nr]
            rel = p[:, None, :] - a0[None]
            e2 = np.maximum(np.einsum('kj,kj->k', d2, d2), 1e-300)
            t = np.clip(np.einsum('ckj,kj->ck', rel, d2) / e2, 0.0, 1.0)
            dist[:, :nr] = np.linalg.norm(rel - t[..., None] * d2[None], axis=2) - c.radius[:nr]
        if nr < c.cols.size:
            nn = pose.normal[nr:]
            dist[:, nr:] = p @ nn.T - np.sum(pose.a0[nr:] * nn, axis=1)[None]
        speed = (float(np.sqrt(np.max(np.einsum('ij,ij->i', v, v))))
                 + float(np.sqrt(np.max(np.einsum('ij,ij->i', w, w)))) * det.max_half_length
                 + float(pose.speed.max()))
        reach = det.chain_reach + POSITION_SKIN + 2.0 * SPECULATIVE_STEPS * self.dt * speed
        return bool(np.any(dist < reach[:, None]))

    def _moved_rows(self, rows, dx, dth):
        """The rows after a small displacement (centres ``dx``, rotations ``dth``), to first
        order: depths change by -J_r·(dx, dth), the lever arms move with their segments."""
        seg, par = rows['seg'], rows['par']
        has = par >= 0
        rate = (np.einsum('ij,ij->i', rows['lin'], dx[seg])
                + np.einsum('ij,ij->i', rows['ang'], dth[seg])
                + np.einsum('ij,ij->i', rows['ang_par'], np.where(has[:, None], dth[par], 0.0)))
        arm = rows['arm'] + cross(dth[seg], rows['arm'])
        return dict(rows, depth=rows['depth'] - rate, arm=arm,
                    ang=np.where(rows['contact'][:, None], cross(arm, rows['lin']), rows['ang']))

    def _refresh_sep(self, rows, v, w, anchor):
        """The rows' separation rates for new velocities (geometry unchanged)."""
        seg, par = rows['seg'], rows['par']
        w_par = np.where((par >= 0)[:, None], w[par],
                         anchor.angular_velocity[self.model.chain_of[seg]])
        sep = (np.einsum('ij,ij->i', rows['lin'], v[seg] - rows['v_other'])
               + np.einsum('ij,ij->i', rows['ang'], w[seg])
               + np.einsum('ij,ij->i', rows['ang_par'], w_par))
        return dict(rows, sep=sep)

    # -- the chain's response to row impulses ------------------------------------------------
    def _factor(self, q):
        """Half-vectors, world inverse inertias and the Cholesky factor of J M⁻¹ Jᵀ at ``q``."""
        m, dyn = self.model, self
        h, G = _mass_terms(m, self.axisymmetric, q)
        D, L = _blocks(m, G)
        ab = np.zeros((_KD + 1, 3 * m.n))
        (da, db, dflat), (ca, cb, oflat) = self._banded
        ab.flat[dflat] = D[:, da, db].ravel()
        ab.flat[oflat[9:]] = L[1:, cb, ca].ravel()
        cho, info = lapack.dpbtrf(ab, lower=0, overwrite_ab=1)
        if info != 0:
            raise np.linalg.LinAlgError(f'J M⁻¹ Jᵀ is not positive definite (pbtrf info={info})')
        if dyn.axisymmetric:
            e = h / (0.5 * m.length)[:, None]
            inv_I = ((m.inv_inertia[:, 0] - m.inv_inertia[:, 1])[:, None, None]
                     * e[:, :, None] * e[:, None, :])
            inv_I[:, [0, 1, 2], [0, 1, 2]] += m.inv_inertia[:, 1:2]
        else:
            R = quat_to_matrix(q)
            inv_I = (R * m.inv_inertia[:, None, :]) @ R.transpose(0, 2, 1)
        return h, inv_I, cho

    def _response(self, fac, F, T):
        """Velocity change ``(k, n, 3)`` ×2 of the jointed chains under impulses ``F``, ``T``
        ``(k, n, 3)`` (k independent right-hand sides): M⁻¹ (Jᵀλ_r + Jᵀλ_joint), joints closed."""
        m = self.model
        h, inv_I, cho = fac
        n, k = m.n, F.shape[0]
        dv = F * m.inv_mass[:, None]
        dw = np.einsum('nij,knj->kni', inv_I, T)
        w_x_h = cross(dw, h)
        # Joint velocity error (parent's distal point minus child's proximal point).
        c_dot = w_x_h - dv
        c_dot[:, 1:] += (dv + w_x_h)[:, :-1] * self._inner
        lam, info = lapack.dpbtrs(cho, c_dot.transpose(1, 2, 0).reshape(3 * n, k), lower=0)
        lam = lam.reshape(n, 3, k).transpose(2, 0, 1)
        lam_next = np.zeros_like(lam)
        lam_next[:, :-1] = lam[:, 1:] * self._has_child
        dv += (lam - lam_next) * m.inv_mass[:, None]
        dw += np.einsum('nij,knj->kni', inv_I, cross(lam + lam_next, h))
        return dv, dw

    def _solve(self, rows, fac, b, friction_bound=None):
        """Impulses ``λ`` ``(k,)`` of the rows: exact LCP ``Wλ + b ≥ 0, λ ≥ 0, λ·(Wλ + b) = 0``,
        or with ``friction_bound`` the energy-safe friction step; and the velocity change
        ``(Δv, Δω)`` of every segment.

        Rows of different chains are independent: the j-th row of every chain shares the
        j-th right-hand side of the banded solve (k_max right-hand sides in all).
        """
        m = self.model
        seg, par = rows['seg'], rows['par']
        k = seg.size
        if m.n_chains == 1:
            chain = np.zeros(k, dtype=np.intp)
            slot = order = np.arange(k)
            groups = [order]
        else:
            chain = m.chain_of[seg]
            order = np.argsort(chain, kind='stable')
            counts = np.bincount(chain, minlength=m.n_chains)
            starts = np.cumsum(counts) - counts
            slot = np.empty(k, dtype=np.intp)
            slot[order] = np.arange(k) - starts[chain[order]]
            groups = [order[starts[c]:starts[c] + counts[c]] for c in np.flatnonzero(counts)]
        kc = int(slot.max()) + 1
        F = np.zeros((kc, m.n, 3))
        T = np.zeros((kc, m.n, 3))
        F[slot, seg] = rows['lin']
        T[slot, seg] = rows['ang']
        hp = np.flatnonzero(par >= 0)
        if hp.size:
            T[slot[hp], par[hp]] += rows['ang_par'][hp]
        dv, dw = self._response(fac, F, T)
        W = (np.einsum('rj,lrj->rl', rows['lin'], dv[:, seg])
             + np.einsum('rj,lrj->rl', rows['ang'], dw[:, seg]))
        # A row the jointed chain cannot move (W_rr ≪ its free segment's mobility, e.g. a
        # contact at the anchor) takes no impulse.
        inv_I = self._inv_I_max
        free = (np.einsum('ij,ij->i', rows['lin'], rows['lin']) * m.inv_mass[seg]
                + np.einsum('ij,ij->i', rows['ang'], rows['ang']) * inv_I[seg])
        if hp.size:
            ap = rows['ang_par'][hp]
            W[hp] += np.einsum('rj,lrj->rl', ap, dw[:, par[hp]])
            free[hp] += np.einsum('ij,ij->i', ap, ap) * inv_I[par[hp]]
        mobile = W[np.arange(k), slot] > MOBILITY * free
        lam = np.zeros(k)
        for r in groups:
            r = r[mobile[r]]
            if r.size == 0:
                continue
            Wc = W[r][:, slot[r]]
            Wc = 0.5 * (Wc + Wc.T)
            if friction_bound is None:
                lam[r] = _lcp(Wc, b[r])
            else:
                lam[r] = _friction(Wc, b[r], friction_bound[r])
        if m.n_chains == 1:
            return lam, np.einsum('k,knj->nj', lam, dv), np.einsum('k,knj->nj', lam, dw)
        weights = np.zeros((kc, m.n_chains))
        weights[slot, chain] = lam
        wseg = weights[:, m.chain_of]
        return lam, np.einsum('kn,knj->nj', wseg, dv), np.einsum('kn,knj->nj', wseg, dw)

    # -- the pass after a step ---------------------------------------------------------------
    def resolve(self, x, q, v, w, anchor, pose, project=True, dt=None):  # noqa: C901 (as it was)
        """Contacts and limits at the end of a step (of length ``dt``): positions, then
        velocities (inelastic impulses, then friction). ``anchor``: ``AnchorKinematics`` at
        that time; ``pose``: ``ColliderPose`` (``None`` without colliders). Returns
        ``(x, q, v, w)``.

        Positions: mass-weighted passes of the linearised LCP over contacts and limits, while
        a contact is deeper than ``POSITION_TOLERANCE`` (limits: one pass), then the limits'
        exact projection (``limits.project_limits``) for what the linearisation of their
        cones left (second order). Then the unchanged velocities are projected onto the moved
        joints (M-orthogonally: no kinetic energy is added) before the velocity stage.
        """
        m = self.model
        self.dt = self.step if dt is None else dt
        self.last = {'contacts': 0, 'limits': 0, 'position_passes': 0}
        x0, q0 = x, q
        rows = self.rows(x, q, v, w, anchor, pose)
        moved = False
        for passes in range(POSITION_ITERATIONS):
            if rows is None:
                break
            depth, contact = rows['depth'], rows['contact']
            worst = max(float(depth[contact].max()) if np.any(contact) else 0.0, 0.0)
            if passes == 0 and np.any(~contact):
                worst = max(worst, float(depth[~contact].max()))
            if worst <= POSITION_TOLERANCE:
                break
            active = depth > -np.where(contact, POSITION_SKIN, ANGLE_SKIN) - 4.0 * worst
            sub = {k: val[active] for k, val in rows.items()}
            _, dx, dth = self._solve(sub, self._factor(q), -sub['depth'])
            ang2 = np.einsum('ij,ij->i', dth, dth)
            clamp = np.minimum(1.0, MAX_ROTATION / np.sqrt(np.maximum(ang2, 1e-300)))
            dth *= clamp[:, None]
            q = quat_normalize(quat_integrate(q, dth, 1.0))
            self.last['position_passes'] = passes + 1
            moved = True
            x_old, x = x, project_positions(m, anchor.position, half_vectors(m.length, q))
            if np.all(clamp == 1.0) and float(np.max(ang2 * m.length)) < 0.1 * POSITION_TOLERANCE:
                # The pass was small enough for its linearisation to hold to a tenth of the
                # tolerance (error ~ l θ²): its predicted depths stand, no second detection.
                rows = self._moved_rows(rows, x - x_old, dth)
                break
            rows = self.rows(x, q, v, w, anchor, pose)
        stale = False          # rows computed before the last change of pose
        if m.has_limits:
            q_lim = limits.project_limits(m, q, anchor.orientation, POSITION_TOLERANCE)
            if q_lim is not None:
                q, moved, stale = q_lim, True, True
                x = project_positions(m, anchor.position, half_vectors(m.length, q))
        fac = None
        if moved:
            if not project:
                # Without projection the centres move by the rotations about the joints only.
                x = x0 + (project_positions(m, anchor.position, half_vectors(m.length, q))
                          - project_positions(m, anchor.position, half_vectors(m.length, q0)))
            # The velocities, unchanged, no longer fit the moved joints: their M-orthogonal
            # projection onto the joint constraints does (it never adds kinetic energy).
            fac = self._factor(q)
            v, w = self._joint_projection(fac, v, w, anchor)
            if stale:
                rows = self.rows(x, q, v, w, anchor, pose)
            elif rows is not None:
                rows = self._refresh_sep(rows, v, w, anchor)
        if rows is not None:
            v, w, fac = self._velocity_stage(rows, q, v, w, anchor, project, fac)
        if moved and project:
            v = project_velocities(m, anchor.velocity, w, half_vectors(m.length, q))
        return x, q, v, w

    def _joint_projection(self, fac, v, w, anchor):
        """Velocities closest to ``(v, w)`` in the mass metric that close every joint."""
        m = self.model
        h, inv_I, cho = fac
        w_x_h = cross(w, h)
        c_dot = m.parent_side(anchor.velocity, v + w_x_h) - (v - w_x_h)
        lam, _ = lapack.dpbtrs(cho, c_dot.reshape(-1, 1), lower=0)
        lam = lam.reshape(-1, 3)
        lam_next = m.distal_side(lam)
        return (v + (lam - lam_next) * m.inv_mass[:, None],
                w + np.einsum('nij,nj->ni', inv_I, cross(lam + lam_next, h)))

    def _velocity_stage(self, rows, q, v, w, anchor, project, fac):
        """The rows touching, or closing within SPECULATIVE_STEPS steps: inelastic impulses
        (and friction), the gap allowed to close within this step."""
        dt = self.dt
        gap = -rows['depth']
        sep = rows['sep']
        skin = np.where(rows['contact'], VELOCITY_SKIN, ANGLE_SKIN)
        near = (gap < skin) | ((sep < 0.0) & (gap < -SPECULATIVE_STEPS * dt * sep))
        rows = {k: val[near] for k, val in rows.items()}
        self.last['contacts'] = int(np.count_nonzero(rows['contact']))
        self.last['limits'] = int(np.count_nonzero(~rows['contact']))
        b = rows['sep'] + np.maximum(-rows['depth'], 0.0) / dt
        if np.any(b < 0.0):
            if fac is None:
                fac = self._factor(q)
            v, w = self._velocities(rows, fac, b, v, w)
            if project:
                v = project_velocities(self.model, anchor.velocity, w, fac[0])
        return v, w, fac

    def _velocities(self, rows, fac, b, v, w):
        """Inelastic impulses on ``rows`` (``b``: separation rates plus the speculative
        allowance), then Coulomb friction on the contacts that push."""
        lam, dv, dw = self._solve(rows, fac, b)
        v, w = v + dv, w + dw
        fr = rows['contact'] & (lam > 0.0) & (rows['mu'] > 0.0)
        if not np.any(fr):
            return v, w
        seg, arm = rows['seg'][fr], rows['arm'][fr]
        n = rows['lin'][fr]
        v_rel = v[seg] + cross(w[seg], arm) - rows['v_other'][fr]
        slip = v_rel - np.einsum('ij,ij->i', v_rel, n)[:, None] * n
        speed = np.sqrt(np.einsum('ij,ij->i', slip, slip))
        sliding = speed > 1e-9
        if not np.any(sliding):
            return v, w
        t = slip[sliding] / speed[sliding, None]
        f_rows = dict(seg=seg[sliding], par=np.full(t.shape[0], -1), lin=-t,
                      ang=-cross(arm[sliding], t), ang_par=np.zeros_like(t))
        bound = (rows['mu'][fr] * lam[fr])[sliding]
        _, dv, dw = self._solve(f_rows, fac, speed[sliding], friction_bound=bound)
        return v + dv, w + dw


def _lcp(W, b):
    """``λ ≥ 0`` with ``Wλ + b ≥ 0`` and ``λ·(Wλ + b) = 0``, W symmetric positive semi-definite.

    Principal pivoting on the (unit-diagonal scaled, 1e-9 regularised) W: start from the
    rows with ``b < 0`` active, solve the active block exactly, and move every row that
    violates a sign condition to the other side (block pivoting; after 4 rounds, only the
    lowest violating index, Murty's rule, which terminates for positive definite W). Typically
    one or two small solves; falls back to NNLS (min ½λᵀWλ + bᵀλ, λ ≥ 0) if it ever stalls.
    """
    if not np.any(b < 0.0):
        return np.zeros_like(b)
    if b.size == 1:
        return np.maximum(-b / W[0], 0.0)
    d = 1.0 / np.sqrt(np.diag(W))
    Ws = W * d[:, None] * d[None, :]
    Ws[np.diag_indices_from(Ws)] += _REG
    bs = b * d
    k = b.size
    active = bs < 0.0
    lam = np.zeros(k)
    for it in range(4 * k + 8):
        lam[:] = 0.0
        if np.any(active):
            lam[active] = np.linalg.solve(Ws[np.ix_(active, active)], -bs[active])
        slack = Ws @ lam + bs
        bad = (active & (lam < -1e-12)) | (~active & (slack < -1e-12))
        if not np.any(bad):
            return np.maximum(lam, 0.0) * d
        if it < 4:
            active ^= bad
        else:
            i = int(np.flatnonzero(bad)[0])
            active[i] = not active[i]
    L = np.linalg.cholesky(Ws)
    lam, _ = nnls(L.T, np.linalg.solve(L, -bs))
    return lam * d


def _friction(W, slip, bound):
    """Friction impulses ``0 ≤ λ ≤ bound`` against sliding speeds ``slip`` (rows: minus the
    sliding direction): the impulse that stops all of them, clipped to the Coulomb bound, then
    scaled by α ∈ [0, 1] with α ≤ λ·slip / λᵀWλ, so that ΔKE = -αλ·slip + ½α²λᵀWλ ≤ 0."""
    n = W.shape[0]
    lam = np.linalg.solve(W + _REG * np.trace(W) / n * np.eye(n), slip)
    lam = np.clip(lam, 0.0, bound)
    work = lam @ slip
    quad = lam @ W @ lam
    if work <= 0.0 or quad <= 0.0:
        return np.zeros_like(lam)
    return lam * min(1.0, work / quad)
