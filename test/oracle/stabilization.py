"""Putting the state back on the joint constraints after a step (drift removal).

The acceleration-level constraint C̈ = 0 keeps the joints together only up to the
integrator's truncation error, which accumulates (drift). After each step the chain is walked
outward from its anchor, all segments at once (a cumulative sum per chain):

- positions: orientations are kept; every centre is placed so that each segment's proximal
  joint lies exactly on its parent's distal joint, starting at the anchor point;
- velocities: angular velocities are kept; every centre's velocity is made equal to the
  rigid-chain velocity implied by the anchor point's velocity and the ω of the segments above.

Both are exact for a chain (joint gap at rounding level) and cost O(n). The correction is of
the size of one step's truncation error, so it does not lower the integrator's order. It is
not mass-weighted: an applied impulse goes through ``apply_impulse`` instead, which solves the
velocity-level system J M⁻¹ Jᵀ λ = -J u with the same banded factorisation.
"""
import numpy as np

from ponytail_ros.core.rotations import cross

__all__ = ['project_positions', 'project_velocities', 'segmented_prefix']


def segmented_prefix(model, d):
    """Sum of ``d`` over the segments before each one in its own chain, ``(n, 3)``."""
    cs = np.cumsum(d, axis=0) - d
    return cs - cs[model.chain_start][model.chain_of]


def project_positions(model, anchor_position, h):
    """Centres ``(n, 3)`` that close every joint exactly, given half-vectors ``h``."""
    return anchor_position[model.chain_of] + segmented_prefix(model, 2.0 * h) + h


def project_velocities(model, anchor_velocity, w, h):
    """Centre velocities ``(n, 3)`` consistent with ``w`` and the anchor point's velocity."""
    w_x_h = cross(w, h)
    return anchor_velocity[model.chain_of] + segmented_prefix(model, 2.0 * w_x_h) + w_x_h
