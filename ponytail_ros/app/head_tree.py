"""The demo head as a small TF tree, as a character rig publishes it.

``world -> base_link -> neck -> head``: ``base_link`` is the character's root on the ground
(below the head, turned with the head's yaw, moving), ``base_link -> neck`` a fixed offset
straight up (published once, on ``/tf_static``), ``neck -> head`` whatever remains (moving), so
that the composed ``world -> head`` is the head pose itself (to rounding). Frames per REP 103
(SI, right-handed, Z up); quaternions ``(x, y, z, w)``.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ponytail_ros.core.rotations import quat_conjugate, quat_multiply, quat_rotate

__all__ = ['Transform', 'HeadTree', 'head_tree', 'compose', 'yaw_quat', 'TREE_FRAMES']

#: The tree's frames below the fixed frame, parent first (names without the TF prefix).
TREE_FRAMES = ('base_link', 'neck', 'head')


class Transform(NamedTuple):
    """A child frame's pose in its parent: translation (m, parent frame) and rotation."""

    translation: np.ndarray     # (3,)
    rotation: np.ndarray        # (4,) x, y, z, w


class HeadTree(NamedTuple):
    base: Transform             # fixed frame -> base_link (moving)
    neck: Transform             # base_link -> neck (static)
    head: Transform             # neck -> head (moving)


def compose(a: Transform, b: Transform) -> Transform:
    """``a ∘ b``: ``b``'s child in ``a``'s parent."""
    return Transform(a.translation + quat_rotate(a.rotation, b.translation),
                     quat_multiply(a.rotation, b.rotation))


def yaw_quat(q: np.ndarray) -> np.ndarray:
    """The rotation about Z by ``q``'s yaw (its X axis projected onto the ground plane)."""
    x, y, z, w = q
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return np.array([0.0, 0.0, np.sin(yaw / 2.0), np.cos(yaw / 2.0)])


def neck_transform(neck_height: float) -> Transform:
    """``base_link -> neck``: ``neck_height`` m straight up, no rotation."""
    return Transform(np.array([0.0, 0.0, float(neck_height)]), np.array([0.0, 0.0, 0.0, 1.0]))


def head_tree(position, orientation, neck_height: float) -> HeadTree:
    """The tree of a head pose ``(position (3,), orientation (4,))`` in the fixed frame."""
    p = np.asarray(position, dtype=float)
    q = np.asarray(orientation, dtype=float)
    base = Transform(np.array([p[0], p[1], 0.0]), yaw_quat(q))
    neck = neck_transform(neck_height)
    world_neck = compose(base, neck)
    inverse = quat_conjugate(world_neck.rotation)
    head = Transform(quat_rotate(inverse, p - world_neck.translation),
                     quat_multiply(inverse, q))
    return HeadTree(base, neck, head)
