"""The compiled model: a ``Scene`` flattened into arrays over all segments of all chains.

Segments of every chain are concatenated: segment ``i`` belongs to chain ``chain_of[i]``; joint
``i`` is the ball joint at segment ``i``'s proximal end, joining it to its parent (segment
``i - 1``, or the chain's anchor when ``is_first[i]``). So there are as many joints as segments,
and ``J M⁻¹ Jᵀ`` is block-tridiagonal over the whole concatenation, with zero coupling blocks
between chains: many chains (a crowd) are solved in one banded factorisation.

Tunable parameters (damping, stiffness, drag, gravity, wind) are arrays that can be changed
between steps without rebuilding; a term whose coefficients are all zero is skipped entirely.

One-sided constraints: ``swing_limit``/``twist_limit`` per joint (inf: off), ``collide`` per
segment, and the scene's colliders as arrays (``collider_*``); ``has_colliders`` and
``has_limits`` tell the simulator whether to run ``collision``/``limits`` at all.
"""
import numpy as np

from .rotations import IDENTITY_QUAT
from .step import INTEGRATORS

__all__ = ['Model']


class Model:
    """Arrays of a scene (SI units). Built once by ``Model(scene)``; structure is immutable."""

    def __init__(self, scene):
        self.scene = scene
        chains = scene.chains
        counts = np.array([c.n_segments for c in chains])
        self.n = int(counts.sum())
        self.n_chains = len(chains)
        self.chain_start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.intp)
        self.chain_end = self.chain_start + counts
        self.chain_of = np.repeat(np.arange(self.n_chains), counts)
        self.is_first = np.zeros(self.n, dtype=bool)
        self.is_first[self.chain_start] = True
        self.has_child = np.ones(self.n, dtype=bool)
        self.has_child[self.chain_end - 1] = False
        self.parent = np.where(self.is_first, -1, np.arange(self.n) - 1)
        # Gather index into [anchor rows (C), segment rows (n)]: each joint's parent side.
        self._parent_ext = np.where(self.is_first, self.chain_of, self.n_chains + self.parent)
        self._child_mask = self.has_child[:-1, None].astype(float)

        self.length = np.concatenate([c.lengths() for c in chains])
        self.mass = np.concatenate([c.masses() for c in chains])
        self.inv_mass = 1.0 / self.mass
        self.inertia = np.concatenate([c.principal_inertia() for c in chains])  # (n, 3) body axes
        self.inv_inertia = 1.0 / self.inertia
        self.radius = np.concatenate([np.full(c.n_segments, c.radius) for c in chains])

        self.attach = np.array([c.attach for c in chains], dtype=float)          # (C, 3) local
        self.anchor_body = np.array([c.anchor_body for c in chains], dtype=np.intp)
        self.rest_direction = np.array([
            c.rest_direction if c.rest_direction is not None else (np.nan, np.nan, np.nan)
            for c in chains], dtype=float)                                        # (C, 3) local
        # Rest orientation of each segment relative to its parent (the anchor body for the first
        # joint); straight chain: identity. The first joint's is set by reset() when the rest
        # direction follows gravity.
        self.q_rest = np.tile(IDENTITY_QUAT, (self.n, 1))

        self.damping = np.zeros(self.n)
        self.stiffness = np.zeros(self.n)
        self.drag_linear = np.zeros(self.n)
        self.drag_quadratic = np.zeros(self.n)
        for c, s, e in zip(chains, self.chain_start, self.chain_end, strict=True):
            self.damping[s:e] = c.damping
            self.stiffness[s:e] = c.stiffness
            self.drag_linear[s:e] = c.drag_linear
            self.drag_quadratic[s:e] = c.drag_quadratic
        # One-sided constraints (off: inf limits, no colliders).
        self.swing_limit = np.concatenate([c.joint_limits('swing_limit') for c in chains])
        self.twist_limit = np.concatenate([c.joint_limits('twist_limit') for c in chains])
        self.collide = np.concatenate([np.full(c.n_segments, bool(c.collide)) for c in chains])
        cols = scene.colliders
        self.n_colliders = len(cols)
        self.collider_kind = np.array([c.kind for c in cols], dtype=object)
        self.collider_body = np.array([-1 if c.body is None else c.body for c in cols],
                                      dtype=np.intp)
        self.collider_center = np.array([c.center for c in cols], dtype=float).reshape(-1, 3)
        axis = np.array([c.axis for c in cols], dtype=float).reshape(-1, 3)
        norm = np.linalg.norm(axis, axis=1, keepdims=True)
        self.collider_axis = axis / np.where(norm > 0.0, norm, 1.0)
        self.collider_radius = np.array([0.0 if c.kind == 'plane' else c.radius for c in cols])
        self.collider_half_length = np.array([c.half_length if c.kind == 'capsule' else 0.0
                                              for c in cols])
        self.collider_friction = np.array([c.friction for c in cols], dtype=float)
        self.has_colliders = bool(self.n_colliders and self.collide.any())
        self.has_limits = bool(np.isfinite(self.swing_limit).any()
                               or np.isfinite(self.twist_limit).any())

        self.gravity = np.array(scene.gravity, dtype=float)
        self.wind = np.array(scene.wind, dtype=float)
        self.dt = scene.solver.dt
        self.damping_method = scene.solver.damping_method
        self.damping_limit = INTEGRATORS[scene.solver.integrator].damping_limit
        self.refresh_terms()

    def parent_side(self, anchor_rows, segment_rows):
        """Per joint, the parent's value: the chain anchor's for a first joint, else segment i-1's.

        ``anchor_rows`` ``(C, k)``, ``segment_rows`` ``(n, k)`` → ``(n, k)``.
        """
        return np.concatenate([anchor_rows, segment_rows])[self._parent_ext]

    def distal_side(self, joint_rows):
        """Per segment, the value of the joint at its distal end (zero at a chain's tip)."""
        out = np.zeros_like(joint_rows)
        out[:-1] = joint_rows[1:] * self._child_mask
        return out

    def chain_slice(self, c):
        return slice(int(self.chain_start[c]), int(self.chain_end[c]))

    def refresh_terms(self):
        """Recompute which force terms are on; call after changing a parameter array.

        A switched-off term is then skipped in the step, so it costs nothing.
        """
        # Joint damping rates reach λ_max ≤ max_i 2 (c_i + c_{i+1}) / I_min,i (Gershgorin on
        # I⁻¹ C); explicit integration is kept while dt · λ_max is inside the integrator's
        # stability region (``Integrator.damping_limit``: 2.78 for RK4, 2 for the Euler kicks).
        c_sum = self.damping + self.distal_side(self.damping[:, None])[:, 0]
        self.damping_rate = float(np.max(2.0 * c_sum / self.inertia.min(axis=1)))
        self.implicit_damping = (self.damping_method == 'implicit' or (
            self.damping_method == 'auto' and self.dt * self.damping_rate > self.damping_limit))
        self.active_terms = {
            'gravity': bool(np.any(self.gravity != 0.0)),
            'damping': bool(np.any(self.damping != 0.0)),
            'stiffness': bool(np.any(self.stiffness != 0.0)),
            'drag': bool(np.any(self.drag_linear != 0.0) or np.any(self.drag_quadratic != 0.0)),
        }
