"""The markers' numbers (``app/messages.py``'s few-call forms, ``core.marker_kernels``'
compiled ones) are bit for bit those of ``core.rotations``: random quaternions and vectors,
with exact and signed zeros (planar motion), antiparallel and zero vectors."""
from itertools import pairwise

import numpy as np
import pytest

pytest.importorskip('rclpy', reason='rclpy (ROS 2 wheels or a sourced workspace) is not installed')

from ponytail_ros.app import messages as m  # noqa: E402
from ponytail_ros.core.rotations import (  # noqa: E402
    quat_axis_x,
    quat_from_two_vectors,
    quat_multiply,
    quat_normalize,
    quat_rotate,
)


def _quats(rng, n):
    q = rng.normal(size=(n, 4))
    # exact and signed zeros: planar rotations, axis-aligned ones, -0.0 components
    q[rng.random(n) < 0.3, 0] = 0.0
    q[rng.random(n) < 0.3, 2] = -0.0
    q[rng.random(n) < 0.1, 1] = 0.0
    q[rng.random(n) < 0.05] = [0.0, 0.0, 0.0, 1.0]
    return quat_normalize(q) * rng.choice([1.0, -1.0], size=(n, 1))


def _same(a, b):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize('seed', range(5))
def test_chain_marker_numbers(seed):
    rng = np.random.default_rng(seed)
    for n in (1, 2, 12, 40):
        q = _quats(rng, n)
        assert _same(m._axis_x(q), quat_axis_x(q))
        assert _same(m._times_z_to_x(q), quat_multiply(q, np.broadcast_to(m.Q_Z_TO_X, q.shape)))


@pytest.mark.parametrize('seed', range(5))
def test_collider_marker_numbers(seed):
    rng = np.random.default_rng(100 + seed)
    qs = _quats(rng, 3000)
    vs = rng.normal(size=(3000, 3)) * rng.choice([1e-3, 1.0, 1e3], size=(3000, 1))
    vs[rng.random(3000) < 0.2, 1] = 0.0
    vs[rng.random(3000) < 0.2, 0] = -0.0
    vs[:20] = [0.0, 0.0, 1.0]
    vs[20:40] = [0.0, 0.0, -1.0]          # antiparallel to +Z
    vs[40:45] = [0.0, 0.0, 0.0]
    z = np.array([0.0, 0.0, 1.0])
    with np.errstate(invalid='ignore', divide='ignore'):
        for q, v in zip(qs, vs, strict=True):
            assert _same(m._rotate(q.tolist(), v.tolist()), quat_rotate(q, v))
            r = quat_rotate(q, v)
            for a, b in ((z, r), (z, v), (v, r)):
                assert _same(m._from_two_vectors(a.tolist(), b.tolist()),
                             quat_from_two_vectors(a, b))


@pytest.mark.parametrize('seed', range(3))
def test_collider_kernel_rows_are_each_colliders_numbers(seed):
    """``core.marker_kernels.collider_numbers`` (every collider in one compiled call) gives
    bit for bit each collider's ``_rotate`` and ``_from_two_vectors``, and flags exactly the
    rows it leaves to ``_from_two_vectors`` (a zero axis, or one opposite +Z)."""
    from ponytail_ros.core.marker_kernels import collider_numbers
    rng = np.random.default_rng(200 + seed)
    n = 2000
    qs = _quats(rng, n)
    qs[:25] = [0.0, 0.0, 0.0, 1.0]        # (so that the next rows stay opposite +Z, or zero)
    vs = rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 1e3], size=(n, 1))
    vs[rng.random(n) < 0.2, 1] = 0.0
    vs[rng.random(n) < 0.2, 0] = -0.0
    vs[:20] = [0.0, 0.0, -1.0]
    vs[20:25] = [0.0, 0.0, 0.0]
    cs, ps = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    rows, none = np.arange(n), np.zeros(0, dtype=np.int64)
    centres, axes = cs.copy(), vs.copy()
    poses, degenerate = np.empty((n, 7)), np.empty(n, dtype=np.bool_)
    flagged = collider_numbers(centres, axes, rows, rows, ps, qs, rows, none, none, np.zeros(0),
                               poses, np.empty((0, 3)), degenerate)
    assert flagged == degenerate.sum() and degenerate[:25].all()
    for k in range(n):
        axis = m._rotate(qs[k].tolist(), vs[k].tolist())
        centre = [a + b for a, b in zip(ps[k].tolist(), m._rotate(qs[k].tolist(),
                                                                   cs[k].tolist()), strict=True)]
        assert _same(poses[k, :3], centre) and _same(axes[k], axis)
        norm = np.linalg.norm(axis)
        opposite = norm == 0.0 or 1.0 + axis[2] / norm < 1e-12
        assert degenerate[k] == opposite
        if not opposite:
            assert _same(poses[k, 3:], m._from_two_vectors([0.0, 0.0, 1.0], axis))


def test_collider_markers_pose_every_collider_as_one_by_one():
    """``ColliderMarkers.markers`` (every collider in a few array operations) equals, bit for
    bit, each collider posed by its body one by one: spheres, capsules and planes, static and
    fixed in moving bodies."""
    from ponytail_ros.core.head import KinematicState
    from ponytail_ros.core.scene import ColliderSpec
    rng = np.random.default_rng(7)
    cols = []
    for k in range(40):
        kind = ('sphere', 'capsule', 'plane')[k % 3]
        cols.append(ColliderSpec(kind=kind, center=tuple(rng.normal(size=3)),
                                 axis=tuple(rng.normal(size=3)), radius=0.1, half_length=0.2,
                                 body=None if k % 4 == 0 else int(rng.integers(0, 5))))
    bodies = KinematicState(position=rng.normal(size=(5, 3)),
                            orientation=_quats(rng, 5),
                            linear_velocity=np.zeros((5, 3)),
                            angular_velocity=np.zeros((5, 3)),
                            linear_acceleration=np.zeros((5, 3)),
                            angular_acceleration=np.zeros((5, 3)))
    specs, poses, points, _ = m.ColliderMarkers().markers(cols, bodies, 'capsules')
    want_poses, want_points = [], []
    for c in cols:
        centre = list(map(float, c.center))
        axis = (np.asarray(c.axis) / np.linalg.norm(c.axis)).tolist() if c.kind != 'sphere' \
            else [0.0, 0.0, 1.0]
        if c.body is not None:
            qb = bodies.orientation[c.body].tolist()
            centre = [a + b for a, b in zip(bodies.position[c.body].tolist(),
                                            m._rotate(qb, centre), strict=True)]
            axis = m._rotate(qb, axis)
        want_poses.append([*centre, *m._from_two_vectors([0.0, 0.0, 1.0], axis)])
        if c.kind == 'capsule':
            want_poses.append([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
            want_points += [[a - c.half_length * b for a, b in zip(centre, axis, strict=True)],
                            [a + c.half_length * b for a, b in zip(centre, axis, strict=True)]]
    assert len(specs) == len(want_poses)
    assert _same(poses, want_poses) and _same(points, want_points)


@pytest.mark.parametrize('style', ['capsules', 'line'])
def test_many_chains_marker_numbers_are_each_chains_concatenated(style):
    """``ChainsMarkerNumbers`` (one pass over a crowd's segments) gives bit for bit the numbers
    of every chain's own ``ChainMessages.markers``, in chain order."""
    rng = np.random.default_rng(7)
    counts = [1, 5, 12, 3]
    chains = [m.ChainMessages(f'c{k}', rng.uniform(0.01, 0.1, size=n), 0.02)
              for k, n in enumerate(counts)]
    numbers = m.ChainsMarkerNumbers(counts, np.concatenate([c.lengths for c in chains]))
    origins = rng.normal(size=(sum(counts), 3))
    quats = _quats(rng, sum(counts))
    poses, points = numbers.numbers(origins, quats, style)
    starts = np.concatenate([[0], np.cumsum(counts)])
    each = [c.markers(origins[s:e], quats[s:e], style, (1.0, 0.0, 0.0, 1.0))
            for c, (s, e) in zip(chains, pairwise(starts), strict=True)]
    assert _same(poses, np.concatenate([e[1] for e in each]))
    assert _same(points, np.concatenate([e[2] for e in each]))


def test_marker_numbers_refuse_inputs_that_do_not_fit():
    """The compiled numbers read no row that is not there: a collider fixed in a body beyond
    the bodies given, or poses of another segment count, are refused, naming them."""
    from ponytail_ros.core.head import KinematicState
    from ponytail_ros.core.scene import ColliderSpec
    cols = [ColliderSpec(kind='sphere', center=(0.0, 0.0, 0.0), radius=0.1, body=2)]
    with pytest.raises(ValueError, match='fixed in body 2.*0 to 1'):
        m.ColliderMarkers().markers(cols, KinematicState.still(np.zeros((2, 3))), 'capsules')
    numbers = m.ChainsMarkerNumbers([3], np.full(3, 0.1))
    with pytest.raises(ValueError, match=r'\(3, 3\) and \(3, 4\)'):
        numbers.numbers(np.zeros((2, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (2, 1)), 'capsules')
