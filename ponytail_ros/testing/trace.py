"""What a test run produced, tick by tick: the published chain and, measured at each tick with
the core's own maths (``ponytail_ros.core``), the quantities the checks bound.

Frames and units: every position is in the head poses' frame (the simulation's world frame,
``header.frame_id`` of the output; REP 103), m; orientations are unit quaternions
``(x, y, z, w)``, segment to world, local +X along the segment (as published); times are node
clock (sim time) seconds; energies J; angles rad. Does not import rclpy.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ponytail_ros.app.runner import ChainRunner, TickOutput
from ponytail_ros.core.collision import segment_depths
from ponytail_ros.core.limits import joint_angles
from ponytail_ros.core.model import Model
from ponytail_ros.core.scene import Scene
from ponytail_ros.core.state import half_vectors

from .config import Config

__all__ = ['Trace', 'TickMeter', 'TraceBuilder', 'Reset']

#: m: where the depth models put every chain's attachment point, so that no first segment
#: counts as "rooted" on a collider (the solver holds a rooted first segment out only on its
#: outer half; a check measures the whole capsule).
_FAR = 1.0e3


@dataclass(frozen=True)
class Reset:
    """A reset of the chains at rest: tick time ``t`` (s), ``reason`` (``RESET_REASONS``) and
    the runner's description (a guard reset says what tripped it)."""

    t: float
    reason: str
    detail: str


@dataclass
class Trace:
    """One run, ``T`` ticks, ``n`` segments (all chains, chain order), ``C`` chains, ``K``
    colliders.

    Attributes:
        config: the parameters the run used.
        t: ``(T,)`` tick times (``header.stamp`` of the outputs), s.
        t_head: ``(T,)`` head time each tick's dynamics were advanced to (``t - delay``), s.
        origins: ``(T, n, 3)`` published proximal joint of every segment, m.
        orientations: ``(T, n, 4)`` published orientations ``(x, y, z, w)``.
        anchors: ``(T, C, 3)`` each chain's attachment point on the head the node estimated
            for the instant the published chain shows (``t`` with latency compensation, else
            ``t_head``), m: where the chain's root belongs.
        depth: ``(T, n, K)`` penetration of each segment (a capsule along its whole length) into
            each collider, m; > 0 inside, <= 0 clear, ``-inf`` where the segment does not
            collide. Judged on the chain as simulated: for head time ``t_head`` against the
            kinematic bodies at ``t_head`` (the published chain is that chain translated so its
            root sits on the head at ``t``; drawn against a head that has turned on over the
            delay it can show up to ω × delay × reach more).
        swing, twist: ``(T, n)`` joint angles as the limits see them, rad (the chain as
            simulated, relative to the anchor body at ``t_head``).
        kinetic, potential: ``(T, C)`` energy of each chain in the simulator's state after the
            tick (its last internal step), J; potential ``-m x·g``.
        steps: ``(T,)`` internal steps taken per tick.
        resets: every reset at rest, in order.
        frame_id: the output's ``header.frame_id`` (last tick).
        poses, markers, diagnostics: the messages (``PoseArray`` per topic, ``MarkerArray``,
            ``DiagnosticArray``), in arrival order.
        wall_time: s of wall time the run took (informative only).
    """

    config: Config
    t: np.ndarray
    t_head: np.ndarray
    origins: np.ndarray
    orientations: np.ndarray
    anchors: np.ndarray
    depth: np.ndarray
    swing: np.ndarray
    twist: np.ndarray
    kinetic: np.ndarray
    potential: np.ndarray
    steps: np.ndarray
    resets: list[Reset]
    frame_id: str
    poses: dict[str, list[Any]] = field(default_factory=dict)
    markers: list[Any] = field(default_factory=list)
    diagnostics: list[Any] = field(default_factory=list)
    wall_time: float = 0.0

    # -- layout ------------------------------------------------------------------------------
    @property
    def chains(self) -> list[str]:
        return list(self.config.chains)

    @property
    def colliders(self) -> list[str]:
        return list(self.config.colliders)

    @property
    def n_ticks(self) -> int:
        return int(self.t.shape[0])

    @property
    def duration(self) -> float:
        """Sim time from the first to the last tick, s (0 for fewer than two ticks)."""
        return float(self.t[-1] - self.t[0]) if self.n_ticks > 1 else 0.0

    def chain_index(self, chain: str) -> int:
        if chain not in self.config.chains:
            raise KeyError(f'no chain {chain!r} in this run (chains: {self.config.chains})')
        return self.config.chains.index(chain)

    def segments(self, chain: str) -> slice:
        """The rows of ``chain``'s segments in the ``n`` axis."""
        sizes = [c.n_segments for c in self.config.scene.chains]
        i = self.chain_index(chain)
        start = int(sum(sizes[:i]))
        return slice(start, start + sizes[i])

    def lengths(self) -> np.ndarray:
        """``(n,)`` segment lengths, m."""
        return np.concatenate([c.lengths() for c in self.config.scene.chains])

    def distal(self) -> np.ndarray:
        """``(T, n, 3)`` far joint of every segment (origin + length along local +X), m."""
        n = self.origins.shape[1]
        if n == 0:
            return self.origins.copy()
        flat_q = self.orientations.reshape(-1, 4)
        h = half_vectors(np.tile(self.lengths(), self.n_ticks), flat_q).reshape(self.origins.shape)
        return self.origins + 2.0 * h

    def tips(self, chain: str | None = None) -> np.ndarray:
        """``(T, 3)`` the far end of ``chain``'s last segment (default: the only chain), m."""
        chain = self._one_chain(chain)
        return self.distal()[:, self.segments(chain).stop - 1]

    def energy(self, chain: str | None = None) -> np.ndarray:
        """``(T,)`` kinetic + potential energy of ``chain`` (default: the only chain), J."""
        i = self.chain_index(self._one_chain(chain))
        return self.kinetic[:, i] + self.potential[:, i]

    def _one_chain(self, chain: str | None) -> str:
        if chain is not None:
            return chain
        if len(self.config.chains) != 1:
            raise ValueError(f'this run has chains {self.config.chains}: name one')
        return self.config.chains[0]

    def where(self, k: int) -> str:
        """``'t = 1.234 s (tick 149 of 360)'`` for tick index ``k``."""
        return f't = {self.t[k]:.3f} s (tick {k + 1} of {self.n_ticks})'


@dataclass
class _Measured:
    t: float
    t_head: float
    origins: np.ndarray
    orientations: np.ndarray
    anchors: np.ndarray
    depth: np.ndarray
    swing: np.ndarray
    twist: np.ndarray
    kinetic: np.ndarray
    potential: np.ndarray
    steps: int


class TickMeter:
    """Measures a tick right after ``ChainRunner.tick`` (``NodeCore.tick``) returned, with the
    core's maths: per-collider penetration (``collision.segment_depths``), joint angles
    (``limits.joint_angles``), energy (``Simulator.energy``). Reads the runner, never changes
    it."""

    def __init__(self) -> None:
        self._scene: Scene | None = None
        self._depth_models: list[Model] = []

    def _models(self, scene: Scene) -> list[Model]:
        if scene is not self._scene:
            far = tuple(replace(c, attach=(_FAR, _FAR, _FAR)) for c in scene.chains)
            self._depth_models = [Model(scene.replace(chains=far, colliders=(col,)))
                                  for col in scene.colliders]
            self._scene = scene
        return self._depth_models

    def measure(self, runner: ChainRunner, out: TickOutput) -> _Measured:
        sim = runner.sim
        model = sim.model
        # Where the published roots belong: the head estimated at t (latency compensation),
        # else at t_head.
        t_root = out.t if runner.settings.latency_compensation else out.t_head
        anchors = sim.anchors(runner.bodies_at(t_root))
        # The chain as simulated: the published one put back on its anchor at t_head, judged
        # against the bodies at t_head.
        bodies = runner.bodies_at(out.t_head)
        sim_anchors = sim.anchors(bodies)
        q = out.orientations
        origins = out.origins + (sim_anchors.position
                                 - out.origins[model.chain_start])[model.chain_of]
        x = origins + half_vectors(model.length, q)
        k = bodies.n_bodies
        body_origins = bodies.point_kinematics(np.arange(k), np.zeros((k, 3)))
        models = self._models(runner.scene)
        depth = np.full((model.n, len(models)), -np.inf)
        far = np.full((model.n_chains, 3), _FAR)
        for j, m in enumerate(models):
            depth[:, j] = segment_depths(m, x, q, far, body_origins)
        swing, twist = joint_angles(model, q, sim_anchors.orientation)
        ke, pe = sim.energy()
        return _Measured(out.t, out.t_head, out.origins.copy(), q.copy(),
                         np.array(anchors.position, dtype=float), depth, swing, twist,
                         np.asarray(ke, dtype=float), np.asarray(pe, dtype=float),
                         int(out.report.steps))


class TraceBuilder:
    """Collects measured ticks and resets; ``build`` stacks them into a ``Trace``."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self.meter = TickMeter()
        self.ticks: list[_Measured] = []
        self.resets: list[Reset] = []
        self.frame_id = ''

    def record(self, runner: ChainRunner, out: TickOutput, frame_id: str) -> None:
        self.ticks.append(self.meter.measure(runner, out))
        self.frame_id = frame_id
        if out.reset_reason is not None:
            self.resets.append(Reset(out.t, out.reset_reason, str(runner.last_reset)))

    def build(self, poses: dict[str, list[Any]] | None = None,
              markers: Sequence[Any] | None = None,
              diagnostics: Sequence[Any] | None = None, wall_time: float = 0.0) -> Trace:
        n = self.config.scene.n_segments
        c, k = len(self.config.chains), len(self.config.colliders)
        ticks = self.ticks

        def stack(name: str, shape: tuple[int, ...]) -> np.ndarray:
            if not ticks:
                return np.zeros((0,) + shape)
            shapes = {np.shape(getattr(m, name)) for m in ticks}
            if len(shapes) != 1:
                raise ValueError(f'the chains changed shape during the run ({name}: '
                                 f'{sorted(shapes)}; a structural parameter change rebuilt '
                                 f'them): a Trace holds one layout, run each in its own')
            return np.stack([np.asarray(getattr(m, name), dtype=float) for m in ticks])
        return Trace(
            config=self.config,
            t=np.array([m.t for m in ticks], dtype=float),
            t_head=np.array([m.t_head for m in ticks], dtype=float),
            origins=stack('origins', (n, 3)), orientations=stack('orientations', (n, 4)),
            anchors=stack('anchors', (c, 3)), depth=stack('depth', (n, k)),
            swing=stack('swing', (n,)), twist=stack('twist', (n,)),
            kinetic=stack('kinetic', (c,)), potential=stack('potential', (c,)),
            steps=np.array([m.steps for m in ticks], dtype=int),
            resets=list(self.resets), frame_id=self.frame_id,
            poses=dict(poses or {}), markers=list(markers or []),
            diagnostics=list(diagnostics or []), wall_time=wall_time)
