"""Chain state in maximal coordinates: every segment's pose and velocity, as arrays.

``x`` ``(n, 3)`` centre of mass, m; ``q`` ``(n, 4)`` orientation ``(x, y, z, w)``, body to world;
``v`` ``(n, 3)`` linear velocity of the centre, m/s; ``w`` ``(n, 3)`` angular velocity ω, rad/s,
world frame. Segment frames: +X along the segment from its proximal to its distal joint.
"""
from dataclasses import dataclass

import numpy as np

from .rotations import quat_axis_x

__all__ = ['ChainState', 'joint_points']


@dataclass
class ChainState:
    x: np.ndarray
    q: np.ndarray
    v: np.ndarray
    w: np.ndarray

    def copy(self):
        return ChainState(self.x.copy(), self.q.copy(), self.v.copy(), self.w.copy())

    def is_finite(self):
        return bool(np.isfinite(self.x).all() and np.isfinite(self.q).all()
                    and np.isfinite(self.v).all() and np.isfinite(self.w).all())


def half_vectors(length, q):
    """World vectors from each centre to its distal joint, ``(n, 3)`` (the proximal is minus)."""
    return (0.5 * length)[:, None] * quat_axis_x(q)


def joint_points(model, state):
    """World positions of every segment's proximal and distal joint, each ``(n, 3)``."""
    h = half_vectors(model.length, state.q)
    return state.x - h, state.x + h
