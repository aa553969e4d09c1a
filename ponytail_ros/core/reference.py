"""The reference ponytail scene of ``../shared/reference/`` as a core ``Scene`` and head motion.

Those files hold trajectories of an exactly specified scene computed by an independent
reduced-coordinate solver (see their README). ``load_reference`` reads one, ``reference_scene``
builds our equivalent, ``reference_errors`` replays it and measures the distance of every joint
point to the reference.
"""
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .head import StillMotion, SwayYawMotion
from .scene import ChainSpec, Scene, SolverSpec
from .simulator import Simulator

__all__ = ['ReferenceRun', 'load_reference', 'reference_scene', 'reference_errors',
           'default_reference_dir']


def default_reference_dir():
    """``../shared/reference`` beside the project root (present in a checkout, not an install)."""
    return Path(__file__).resolve().parents[3] / 'shared' / 'reference'


@dataclass
class ReferenceRun:
    name: str
    scene: dict
    t: np.ndarray            # (K,) s
    points: np.ndarray       # (N, K, 3) far end of every segment, m
    valid_until: dict        # tolerance (str) -> time (s) up to which the reference is good

    def window(self, tolerance='1e-6'):
        return float(self.valid_until.get(tolerance, self.t[-1]))


def load_reference(path):
    path = Path(path)
    d = json.loads(path.read_text())
    return ReferenceRun(path.stem, d['scene'], np.asarray(d['t']),
                        np.asarray(d['points']), d['convergence']['valid_until'])


def reference_scene(ref, solver=None):
    """``(Scene, HeadMotion)`` reproducing ``ref.scene`` (one chain on one head)."""
    sc = ref.scene
    # 'hanging': straight down (at t = 0 the head frame is the world frame); 'horizontal':
    # along head-local -X.
    rest = (0.0, 0.0, -1.0) if sc['init'] == 'hanging' else (-1.0, 0.0, 0.0)
    chain = ChainSpec(
        name='ponytail', n_segments=int(sc['n_segments']), length=sc['total_length'],
        mass=sc['total_mass'], radius=sc['radius'], attach=tuple(sc['attach_local']),
        rest_direction=rest, damping=sc['damping'],
        inertia=tuple((sc['I_axial'], sc['I_perp'], sc['I_perp']) for _ in range(sc['n_segments'])))
    scene = Scene(chains=(chain,), gravity=tuple(sc['gravity']),
                  solver=solver if solver is not None else SolverSpec())
    if sc['head'] == 'moving':
        motion = SwayYawMotion(sc['head_pos0'], sc['head_amp'], sc['head_freq'],
                               sc['head_yaw_amp'], sc['head_yaw_freq'])
    else:
        motion = StillMotion(sc['head_pos0'])
    return scene, motion


def reference_errors(ref, solver=None, tolerance='1e-6'):
    """Distance ``(N, K')`` of every joint point to the reference over its valid window, m.

    The head is driven exactly (its formulas evaluated at every integrator stage).
    """
    scene, motion = reference_scene(ref, solver)
    sim = Simulator(scene, motion)
    times = ref.t[ref.t <= ref.window(tolerance) + 1e-9]
    errors = np.empty((scene.n_segments, times.size))
    for k, tk in enumerate(times):
        sim.advance_to(tk, motion)
        _, distal = sim.joint_positions()
        errors[:, k] = np.linalg.norm(distal - ref.points[:, k], axis=1)
    return errors
