"""What a simulator call reports: ``StepReport`` per call, ``Rollout`` per rollout."""
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

__all__ = ['StepReport', 'Rollout']


@dataclass
class StepReport:
    """What one ``advance`` call did.

    ``timings``: wall seconds of the call's stages, like Box2D's ``b2Profile``: ``steps``
    (the anchor table and the compiled steps, contacts and limits included) and ``guard``
    (the checks of the state after the call, and a reset if one was needed); when the
    compiled step ran, also the split of its calls' time into ``integrate`` (the chains' own
    steps: forces, joint solves, integration, projection) and ``contacts`` (the contact and
    limit stage; 0 without colliders and limits), by the CPU's cycle counter
    (``stages.PROFILE_STAGES``; where there is none, ``integrate`` holds the calls' whole time),
    and of ``contacts`` into ``contact_rows``, ``contact_positions`` and
    ``contact_velocities`` (``stages.CONTACT_STAGES``; the rest of ``contacts``: the
    colliders posed, the positions kept, the call into each chain's stages).
    """

    steps: int = 0
    dropped_time: float = 0.0
    reset_reason: str | None = None
    max_gap: float = 0.0
    timings: dict = field(default_factory=dict)


class Rollout(NamedTuple):
    """What ``Simulator.rollout`` did: one ``StepReport`` per sample and the chain's state
    after it (``(T, n, 3|4)`` arrays, as ``ChainState``: centres m, unit quaternions
    ``(x, y, z, w)`` body to world, velocities m/s, angular velocities rad/s; world frame)."""

    reports: list
    x: np.ndarray
    q: np.ndarray
    v: np.ndarray
    w: np.ndarray
