"""The named benchmark scenes.

Each is a chain, a head motion, a duration and what it can be checked against:

``moving``   the reference ponytail (``../shared/reference/``): N = 10 uniform solid cylinders,
             0.40 m, 0.10 kg, radius 1 cm, attached at head-local (-0.10, 0, 0.05), hanging at
             rest, on a head swaying ±5 cm at 1.5 Hz and yawing ±0.6 rad at 0.8 Hz; 3 s.
             With N in {2, 5, 10} it is ``ponytail_N{N}_moving_hanging``.
``release``  the same ponytail on a still head, released horizontal (head-local -X), no damping;
             ``ponytail_N{N}_still_horizontal``. Chaotic for N = 10: the shared file is valid to
             1e-6 m up to 1.96 s, so it runs 1.9 s.
``shake``    the same ponytail on a violent head shake: ±0.1 m along X at 4 Hz plus ±1 rad yaw
             at 3 Hz (``motions.SHAKE``; ~10 g at the attachment point); 2 s.
``rope``     a long rope: 40 segments, 2 m, 0.2 kg, radius 5 mm, from a ceiling anchor at
             3 m, released straight at 60° from the vertical, no damping; 2 s.

``damped``   ``moving`` with the shared files' joint damping c = 1e-4 N·m·s/rad
             (``ponytail_N{N}_moving_hanging_damped``): at game steps this damping is stiff about
             the segments' axes, so the core integrates it implicitly (first order); 3 s.

All use gravity (0, 0, -9.81) and no drag or stiffness, and all but ``damped`` no damping
(still scenes then conserve energy exactly, which is what their energy drift is measured
against).
"""
import os
from dataclasses import dataclass, replace

import numpy as np

from ponytail_ros.app.motions import reference_motion, shake_motion
from ponytail_ros.core.head import StillMotion
from ponytail_ros.core.scene import ChainSpec, Scene, SolverSpec

__all__ = ['BenchScene', 'make_scene', 'SCENES', 'EXTRA_SCENES', 'REFERENCE_DIR',
           'shared_reference_path', 'ponytail_chain']

SCENES = ('moving', 'release', 'shake', 'rope')
EXTRA_SCENES = ('damped',)
REFERENCE_DIR = os.environ.get(
    'PONYTAIL_REFERENCE_DIR',
    os.path.normpath(os.path.join(os.path.dirname(__file__), '..', '..', '..', 'shared',
                                  'reference')))


@dataclass
class BenchScene:
    """A scene to benchmark: ``scene`` (solver replaced per setting), ``motion``, ``duration``.

    ``still``: the head never moves (energy is conserved and its drift is measured).
    ``shared``: name of the matching file in ``../shared/reference/`` (or None).
    ``valid_until``: the shared file is trustworthy to 1e-6 m up to this time.
    """

    name: str
    scene: Scene
    motion: object
    duration: float
    still: bool
    shared: str | None = None
    description: str = ''

    @property
    def n_segments(self):
        return self.scene.chains[0].n_segments

    def with_solver(self, solver):
        return replace(self, scene=self.scene.replace(solver=solver))

    def with_duration(self, duration):
        return replace(self, duration=float(duration))


def ponytail_chain(n_segments=10, **kw):
    """The reference ponytail (0.40 m, 0.10 kg, r = 1 cm, solid cylinders), undamped unless
    ``damping`` is given (as in ``../shared/reference/``, whatever ``ChainSpec``'s default)."""
    kw.setdefault('damping', 0.0)
    return ChainSpec(name='ponytail', n_segments=n_segments, length=0.4, mass=0.1, radius=0.01,
                     attach=(-0.10, 0.0, 0.05), **kw)


def shared_reference_path(name):
    return os.path.join(REFERENCE_DIR, name + '.json')


def make_scene(name, n_segments=None, solver=None, duration=None):
    """The named scene (``SCENES``), optionally with another segment count, solver or duration."""
    solver = solver or SolverSpec()
    if name == 'moving':
        n = n_segments or 10
        sc = Scene(chains=(ponytail_chain(n),), solver=solver)
        b = BenchScene(name, sc, reference_motion(), 3.0, False,
                       f'ponytail_N{n}_moving_hanging' if n in (2, 5, 10) else None,
                       f'ponytail N={n} on the swaying, yawing reference head')
    elif name == 'damped':
        n = n_segments or 10
        sc = Scene(chains=(ponytail_chain(n, damping=1e-4),), solver=solver)
        b = BenchScene(name, sc, reference_motion(), 3.0, False,
                       f'ponytail_N{n}_moving_hanging_damped' if n in (2, 5, 10) else None,
                       f'damped ponytail N={n} (c = 1e-4) on the moving reference head')
    elif name == 'release':
        n = n_segments or 10
        sc = Scene(chains=(ponytail_chain(n, rest_direction=(-1.0, 0.0, 0.0)),), solver=solver)
        b = BenchScene(name, sc, StillMotion((0.0, 0.0, 1.6)), 1.9, True,
                       f'ponytail_N{n}_still_horizontal' if n in (2, 5, 10) else None,
                       f'ponytail N={n} released horizontal from a still head')
    elif name == 'shake':
        n = n_segments or 10
        sc = Scene(chains=(ponytail_chain(n),), solver=solver)
        b = BenchScene(name, sc, shake_motion(), 2.0, False, None,
                       f'ponytail N={n} on a violent shake (±0.1 m @ 4 Hz, ±1 rad yaw @ 3 Hz)')
    elif name == 'rope':
        n = n_segments or 40
        a = np.radians(60.0)
        chain = ChainSpec(name='rope', n_segments=n, length=2.0, mass=0.2, radius=0.005,
                          damping=0.0, attach=(0.0, 0.0, 0.0),
                          rest_direction=(np.sin(a), 0.0, -np.cos(a)))
        sc = Scene(chains=(chain,), solver=solver)
        b = BenchScene(name, sc, StillMotion((0.0, 0.0, 3.0)), 2.0, True, None,
                       f'rope N={n}, 2 m, released at 60° from a ceiling anchor')
    else:
        raise ValueError(f'unknown scene {name!r}: one of {SCENES + EXTRA_SCENES}')
    if duration is not None:
        b = b.with_duration(duration)
    return b
