"""Head motions for tests: timestamped head poses, from a list or sampled from a function.

A head pose is the pose of the head frame in the world frame (the frame every pose on
``head_pose`` is given in; REP 103: x forward, y left, z up): ``position`` in m and
``orientation`` as a unit quaternion ``(x, y, z, w)``, head to world. Times are simulated
(``/clock``) seconds. Does not import rclpy.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from typing import NamedTuple, TypeAlias

__all__ = ['PoseSample', 'Motion', 'HeadInput', 'sample_motion', 'head_samples', 'still',
           'stamp_ns']


class PoseSample(NamedTuple):
    """One head pose: ``t`` s (sim time), ``position`` m, ``orientation`` ``(x, y, z, w)``."""

    t: float
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]


#: A head motion: sim time ``t`` (s) -> ``(position (3,), orientation (4,) as (x, y, z, w))``.
Motion = Callable[[float], tuple[Sequence[float], Sequence[float]]]
#: What a run accepts as head input: samples (``PoseSample`` or ``(t, position, orientation)``
#: tuples, stamps increasing) or a ``Motion`` (sampled at ``input_rate``).
SampleLike: TypeAlias = PoseSample | tuple[float, Sequence[float], Sequence[float]]
HeadInput: TypeAlias = Motion | Iterable[SampleLike]


def stamp_ns(t: float) -> int:
    """The integer ns of ``t`` s (the ``header.stamp`` a sample at ``t`` carries)."""
    return int(round(float(t) * 1e9))


def _sample(t: float, position: Sequence[float], orientation: Sequence[float]) -> PoseSample:
    p = tuple(float(x) for x in position)
    q = tuple(float(x) for x in orientation)
    if len(p) != 3 or len(q) != 4:
        raise ValueError(f'head pose at t = {t} s: position needs 3 values and orientation 4 '
                         f'(x, y, z, w), got {len(p)} and {len(q)}')
    return PoseSample(float(t), (p[0], p[1], p[2]), (q[0], q[1], q[2], q[3]))


def sample_motion(motion: Motion, duration: float, input_rate: float = 100.0,
                  start: float = 0.0) -> list[PoseSample]:
    """``motion`` sampled every ``1 / input_rate`` s over ``[start, start + duration]``
    (sim time, s; both ends included)."""
    if not (input_rate > 0.0 and math.isfinite(input_rate)):
        raise ValueError(f'input_rate must be a positive number of Hz, got {input_rate!r}')
    n = int(math.floor(duration * input_rate + 1e-9))
    out = []
    for k in range(n + 1):
        t = start + k / input_rate
        p, q = motion(t)
        out.append(_sample(t, p, q))
    return out


def head_samples(head: HeadInput, duration: float | None = None,
                 input_rate: float = 100.0) -> list[PoseSample]:
    """Normalise a ``HeadInput`` to a list of ``PoseSample`` (a motion function needs
    ``duration``)."""
    if callable(head):
        if duration is None:
            raise ValueError('a head motion function needs a duration (s)')
        return sample_motion(head, duration, input_rate)
    out = [s if isinstance(s, PoseSample) else _sample(*s) for s in head]
    return out


def still(position: Sequence[float] = (0.0, 0.0, 1.6),
          orientation: Sequence[float] = (0.0, 0.0, 0.0, 1.0)) -> Motion:
    """A head at rest at ``position`` (m) with ``orientation`` (x, y, z, w)."""
    p = tuple(float(x) for x in position)
    q = tuple(float(x) for x in orientation)
    return lambda t: (p, q)
