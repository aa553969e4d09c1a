"""Scene description: what is simulated, validated once when it is built.

A scene is a set of chains, each hung from a point fixed in one of ``n_kinematic_bodies``
kinematic bodies (heads or static anchors), optional colliders (spheres, capsules, planes fixed
in a kinematic body or in the world) and per-chain joint limits, plus world settings (gravity,
wind) and the solver settings. A feature a scene leaves out costs nothing. Everything is SI
(m, kg, s, rad), world frame Z up (REP 103).

Segment frame: origin at the centre of mass, body +X along the segment from its proximal joint
(towards the anchor) to its distal joint. A solid cylinder of length ``l``, radius ``r``, mass
``m`` has principal moments ``(I_axial, I_perp, I_perp) = (m r²/2, m(3r² + l²)/12, same)``.

Every field is checked by ``validate()``; an error names the field, the value and the allowed
range (``SceneError``, a ``ValueError``).

Types: a vector field (``attach``, ``center``, ``gravity``, ...) takes any three numbers (a
tuple keeps the spec hashable; a list or an array is accepted and checked); a per-segment or
per-joint field takes N numbers, a joint limit one angle or N of them.
"""
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Self, TypeAlias

import numpy as np
import numpy.typing as npt

__all__ = ['SceneError', 'ChainSpec', 'ColliderSpec', 'SolverSpec', 'Scene', 'cylinder_inertia',
           'INTEGRATORS', 'DAMPING_METHODS', 'COLLIDER_KINDS', 'MAX_SEGMENTS',
           'MAX_COLLIDERS', 'MAX_COLLIDING_SEGMENTS', 'REMOVED_SOLVER_FIELDS',
           'removed_field_error']

INTEGRATORS = ('rk4', 'symplectic_euler', 'rattle')
DAMPING_METHODS = ('auto', 'explicit', 'implicit')
COLLIDER_KINDS = ('sphere', 'capsule', 'plane')
MAX_SEGMENTS = 4096
#: Segments of a chain that collides with colliders: the contact solve per step grows with the
#: segments touching (rows, and a chain solve per row) far faster than the free step, and past
#: this a tick takes seconds (``python -m ponytail_ros.bench.tick_cost``, figures in
#: ``docs/bench/tick_cost.txt``).
MAX_COLLIDING_SEGMENTS = 256
MAX_COLLIDERS = 256
#: ``SolverSpec`` fields that were removed: name -> why. Setting one (a ``SolverSpec``, a
#: params file) is refused with ``removed_field_error``, which names it.
REMOVED_SOLVER_FIELDS = {
    'linear_solver': 'the compiled step, with its O(n) block-tridiagonal joint solve, always runs',
}

#: Three numbers: a point (m), a direction or a vector (m/s, m/s²), in the frame the field names.
Vector3 = Sequence[float]
#: One number per segment (or per joint), root first.
PerSegment = Sequence[float]
#: A joint limit, rad: one angle for every joint, or one per joint, root first.
Limit: TypeAlias = float | Sequence[float]
#: A float array (``np.ndarray`` of ``float64``).
FloatArray = npt.NDArray[np.float64]


class SceneError(ValueError):
    """A scene field is out of its allowed range."""

    def __init__(self, field_name: str, value: object, allowed: str) -> None:
        self.field = field_name
        self.value = value
        self.allowed = allowed
        super().__init__(f'{field_name} = {value!r} is not allowed: must be {allowed}')


def removed_field_error(name: str, value: object) -> 'SceneError':
    """The error for a removed field ``name`` (dotted: ``solver.<field>``) set to
    ``value``: it names the field and says it was removed, and why."""
    why = REMOVED_SOLVER_FIELDS[name.rpartition('.')[2]]
    return SceneError(name, value, f'left out: the field was removed ({why})')


def cylinder_inertia(mass: npt.ArrayLike, length: npt.ArrayLike,
                     radius: npt.ArrayLike) -> FloatArray:
    """Principal moments ``(n, 3)`` of solid cylinders about their centre, axis along +X."""
    mass, length, radius = np.broadcast_arrays(*(np.asarray(a, dtype=float)
                                                  for a in (mass, length, radius)))
    axial = 0.5 * mass * radius ** 2
    perp = mass * (3.0 * radius ** 2 + length ** 2) / 12.0
    return np.stack([axial, perp, perp], axis=-1)


def check_range(name: str, value: float, lo: float, hi: float, lo_open: bool = False,
                 hi_open: bool = False) -> None:
    ok = (math.isfinite(value) and (value > lo if lo_open else value >= lo)
          and (value < hi if hi_open else value <= hi))
    if not ok:
        raise SceneError(name, value,
                         f'in {"(" if lo_open else "["}{lo}, {hi}{")" if hi_open else "]"}')


def check_vector(name: str, value: Any, n: int = 3, max_abs: float = 1e6) -> FloatArray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (n,) or not np.all(np.isfinite(arr)) or np.any(np.abs(arr) > max_abs):
        raise SceneError(name, value, f'{n} finite numbers, each within ±{max_abs:g}')
    return arr


MAX_LIMIT = 3.1


def _check_limit(name: str, value: Limit | None, n: int) -> None:
    """A joint limit: ``None``, one angle or ``n`` angles, each in (0, MAX_LIMIT] rad."""
    if value is None:
        return
    allowed = f'None, or one angle or {n} angles (one per joint), each in (0, {MAX_LIMIT}] rad'
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise SceneError(name, value, allowed) from None
    if arr.shape not in ((), (n,)) or not np.all(np.isfinite(arr)) or np.any(arr <= 0.0) \
            or np.any(arr > MAX_LIMIT):
        raise SceneError(name, value, allowed)


@dataclass(frozen=True)
class ChainSpec:
    """One chain of ``n_segments`` rigid segments joined end to end by ball joints.

    Attributes:
        name: label (topic suffix in the node).
        n_segments: number of segments N, 1 ≤ N ≤ 4096.
        length: total length, m (split equally unless ``segment_lengths`` is given).
        mass: total mass, kg (split in proportion to length unless ``segment_masses`` is given).
        radius: segment radius, m (for the default solid-cylinder inertia and for collision).
        segment_lengths, segment_masses: optional per-segment overrides, ``(N,)``.
        inertia: optional principal moments ``(N, 3)`` about each centre, body axes
            (axial X, then Y, Z), kg·m²; default: solid cylinder.
        anchor_body: index of the kinematic body the chain hangs from.
        attach: attachment point in the anchor body's frame, m.
        rest_direction: direction of a straight chain at rest, in the anchor body's frame; used
            by ``reset`` and as the bending stiffness' rest pose. ``None``: along gravity.
        damping: joint damping c, N·m·s/rad: torque ``-c (ω_child - ω_parent)`` at every joint
            (default 1e-3: hair and rope lose energy at their joints; an undamped chain driven
            hard pumps energy into fast whip modes until no fixed step can follow them).
        stiffness: bending stiffness k, N·m/rad, towards the straight rest pose at every joint.
        drag_linear: linear air drag per metre of segment, N·s/m².
        drag_quadratic: quadratic air drag per metre of segment, N·s²/m³.
        swing_limit: cone half-angle θ_max, rad, in (0, 3.1] (or one per joint), or ``None``
            (off): the angle between a segment's axis and its rest direction relative to its
            parent (the parent segment's axis; for the first joint the rest direction in the
            anchor frame, ``rest_direction`` or the hanging direction taken by ``reset``).
        twist_limit: ±φ_max, rad, in (0, 3.1] (or one per joint), or ``None`` (off): rotation
            about the segment's own axis relative to its parent's rest frame (swing–twist
            decomposition).
        collide: whether the segments collide with the scene's colliders (as capsules of
            radius ``radius`` along their whole length).
    """

    name: str = 'ponytail'
    n_segments: int = 10
    length: float = 0.4
    mass: float = 0.1
    radius: float = 0.01
    segment_lengths: PerSegment | None = None
    segment_masses: PerSegment | None = None
    inertia: Sequence[Sequence[float]] | None = None
    anchor_body: int = 0
    attach: Vector3 = (-0.10, 0.0, 0.05)
    rest_direction: Vector3 | None = None
    damping: float = 1e-3
    stiffness: float = 0.0
    drag_linear: float = 0.0
    drag_quadratic: float = 0.0
    swing_limit: Limit | None = None
    twist_limit: Limit | None = None
    collide: bool = True

    def validate(self, prefix: str = 'chain', n_kinematic_bodies: int = 1) -> Self:  # noqa: C901
        """This chain, if every field is in range (``prefix`` names it); else ``SceneError``."""
        p = prefix + '.'
        if not isinstance(self.n_segments, (int, np.integer)) \
                or isinstance(self.n_segments, bool) or not 1 <= self.n_segments <= MAX_SEGMENTS:
            raise SceneError(p + 'n_segments', self.n_segments,
                             f'an integer in [1, {MAX_SEGMENTS}]')
        check_range(p + 'length', self.length, 1e-4, 1e3)
        check_range(p + 'mass', self.mass, 1e-7, 1e4)
        check_range(p + 'radius', self.radius, 1e-6, 10.0)
        n = self.n_segments
        for name in ('segment_lengths', 'segment_masses'):
            val = getattr(self, name)
            if val is not None:
                arr = np.asarray(val, dtype=float)
                if arr.shape != (n,) or not np.all(np.isfinite(arr)) or np.any(arr <= 0.0):
                    raise SceneError(p + name, val,
                                     f'{n} positive finite numbers (one per segment)')
        if self.inertia is not None:
            arr = np.asarray(self.inertia, dtype=float)
            if arr.shape != (n, 3) or not np.all(np.isfinite(arr)) or np.any(arr <= 0.0):
                raise SceneError(p + 'inertia', self.inertia, f'an array of shape ({n}, 3) of '
                                 'positive principal moments, kg·m²')
        if not isinstance(self.anchor_body, (int, np.integer)) or not \
                0 <= self.anchor_body < n_kinematic_bodies:
            raise SceneError(p + 'anchor_body', self.anchor_body,
                             f'an integer in [0, {n_kinematic_bodies - 1}]')
        check_vector(p + 'attach', self.attach, max_abs=1e3)
        if self.rest_direction is not None:
            d = check_vector(p + 'rest_direction', self.rest_direction)
            if np.linalg.norm(d) < 1e-9:
                raise SceneError(p + 'rest_direction', self.rest_direction, 'a non-zero vector')
        check_range(p + 'damping', self.damping, 0.0, 1e3)
        check_range(p + 'stiffness', self.stiffness, 0.0, 1e4)
        check_range(p + 'drag_linear', self.drag_linear, 0.0, 1e3)
        check_range(p + 'drag_quadratic', self.drag_quadratic, 0.0, 1e3)
        for name in ('swing_limit', 'twist_limit'):
            _check_limit(p + name, getattr(self, name), n)
        if not isinstance(self.collide, (bool, np.bool_)):
            raise SceneError(p + 'collide', self.collide, 'True or False')
        return self

    def joint_limits(self, name: str) -> FloatArray:
        """``(N,)`` array of a limit (``'swing_limit'``/``'twist_limit'``), rad; inf where off."""
        val = getattr(self, name)
        if val is None:
            return np.full(self.n_segments, np.inf)
        return np.broadcast_to(np.asarray(val, dtype=float), (self.n_segments,)).copy()

    def lengths(self) -> FloatArray:
        """``(N,)`` segment lengths, m, root first."""
        if self.segment_lengths is not None:
            return np.asarray(self.segment_lengths, dtype=float)
        return np.full(self.n_segments, self.length / self.n_segments)

    def masses(self) -> FloatArray:
        """``(N,)`` segment masses, kg, root first."""
        if self.segment_masses is not None:
            return np.asarray(self.segment_masses, dtype=float)
        lengths = self.lengths()
        return self.mass * lengths / lengths.sum()

    def principal_inertia(self) -> FloatArray:
        """``(N, 3)`` principal moments about each centre (axial X, then Y, Z), kg·m²."""
        if self.inertia is not None:
            return np.asarray(self.inertia, dtype=float)
        return cylinder_inertia(self.masses(), self.lengths(), self.radius)


@dataclass(frozen=True)
class ColliderSpec:
    """A kinematic collider the chains' segments cannot enter (one-sided contact).

    Segments collide as capsules (radius ``ChainSpec.radius``) along their whole length.

    Attributes:
        kind: ``'sphere'``, ``'capsule'`` or ``'plane'``.
        body: index of the kinematic body the collider is fixed in (it moves with it), or
            ``None``: fixed in the world (static).
        center: sphere/capsule centre, or a point of the plane, m, in that body's frame
            (world frame when ``body`` is ``None``); each coordinate within ±1000.
        axis: capsule axis direction, or the plane's normal (pointing to the free side), in
            that frame; a non-zero vector (normalised). Unused by a sphere.
        radius: sphere/capsule radius, m, in (0, 100]. Unused by a plane.
        half_length: half the length of a capsule's core segment, m, in [0, 100]. Unused by
            spheres and planes.
        friction: Coulomb friction coefficient μ against the segments, in [0, 10].
    """

    kind: str = 'sphere'
    body: int | None = 0
    center: Vector3 = (0.0, 0.0, 0.0)
    axis: Vector3 = (0.0, 0.0, 1.0)
    radius: float = 0.1
    half_length: float = 0.0
    friction: float = 0.0

    @classmethod
    def sphere(cls, center: Vector3 = (0.0, 0.0, 0.0), radius: float = 0.1,
               body: int | None = 0, friction: float = 0.0) -> Self:
        """A sphere of ``radius`` about ``center``."""
        return cls('sphere', body, tuple(center), (0.0, 0.0, 1.0), radius, 0.0, friction)

    @classmethod
    def capsule(cls, center: Vector3 = (0.0, 0.0, 0.0), axis: Vector3 = (0.0, 0.0, 1.0),
                half_length: float = 0.1, radius: float = 0.05, body: int | None = 0,
                friction: float = 0.0) -> Self:
        """A capsule: the points within ``radius`` of ``center ± half_length · axis``."""
        return cls('capsule', body, tuple(center), tuple(axis), radius, half_length, friction)

    @classmethod
    def plane(cls, point: Vector3 = (0.0, 0.0, 0.0), normal: Vector3 = (0.0, 0.0, 1.0),
              body: int | None = None, friction: float = 0.0) -> Self:
        """A plane through ``point``; ``normal`` points to the free side."""
        return cls('plane', body, tuple(point), tuple(normal), 0.1, 0.0, friction)

    def validate(self, prefix: str = 'collider', n_kinematic_bodies: int = 1) -> Self:
        """This collider, if every field is in range (``prefix`` names it); else ``SceneError``."""
        p = prefix + '.'
        if self.kind not in COLLIDER_KINDS:
            raise SceneError(p + 'kind', self.kind, f'one of {COLLIDER_KINDS}')
        if self.body is not None and (
                not isinstance(self.body, (int, np.integer)) or isinstance(self.body, bool)
                or not 0 <= self.body < n_kinematic_bodies):
            raise SceneError(p + 'body', self.body,
                             f'None (world) or an integer in [0, {n_kinematic_bodies - 1}]')
        check_vector(p + 'center', self.center, max_abs=1e3)
        axis = check_vector(p + 'axis', self.axis)
        if self.kind != 'sphere' and np.linalg.norm(axis) < 1e-9:
            raise SceneError(p + 'axis', self.axis, 'a non-zero vector')
        if self.kind != 'plane':
            check_range(p + 'radius', self.radius, 0.0, 100.0, lo_open=True)
        if self.kind == 'capsule':
            check_range(p + 'half_length', self.half_length, 0.0, 100.0)
        check_range(p + 'friction', self.friction, 0.0, 10.0)
        return self


@dataclass(frozen=True)
class SolverSpec:
    """How time is advanced.

    Attributes:
        integrator: ``'rk4'`` (classical Runge–Kutta, 4th order, four solves per step),
            ``'symplectic_euler'`` (a constrained symplectic Euler step, SHAKE/RATTLE type:
            1st order, cheapest, bounded energy error, any spin about a segment's own axis) or
            ``'rattle'`` (the same split into two half kicks: 2nd order, bounded energy error
            ∝ dt², about the same cost; needs ``projection``). See ``step``.
        dt: fixed internal step, s, in [1e-6, 0.1]; default 1/960 s (eight steps per
            120 Hz tick: the cheapest RK4 step that follows violent head motion without a
            guard reset and ordinary motion to about a millimetre, ``docs/bench``). Frames of
            any length are advanced in these steps (an accumulator), so results do not
            depend on the frame rate.
        max_steps_per_call: cap on internal steps per ``advance``; time beyond it is dropped
            and reported (a frame hitch must not cause a spiral of death).
        projection: after each step, put positions and velocities back on the joint
            constraints (removes drift; on by default). For symplectic Euler it also switches
            its step's own position correction and velocity projection (off: the velocity form
            of C̈ = 0, which drifts).
        baumgarte_stiffness, baumgarte_damping: optional constraint stabilisation inside the
            acceleration solve, ``C̈ + 2ζ Ċ + κ C = 0`` with κ (1/s²) and 2ζ (1/s) (RK4, and
            symplectic Euler without projection).
        damping_method: how joint damping is integrated. ``'explicit'``: inside the
            integrator, as accurate as it, but unstable once ``dt`` times the damping rate
            (up to ~4c/I_axial: thin segments twist easily) leaves the integrator's stability
            region. ``'implicit'``: implicit Euler after each step, stable for any damping and
            step, first order in the damping term. ``'auto'`` (default): explicit while
            ``dt · λ_max`` (λ_max by Gershgorin) is inside the integrator's stability region
            (``step.Integrator.damping_limit``: 2.78 for RK4, 2 for the others), else
            implicit; re-decided whenever the damping is changed.
        guard_max_speed: a segment faster than this (m/s) is a blow-up: reset and report.
        guard_max_gap: a joint gap larger than this (m) after projection: reset and report.
        guard_max_step_angle: the most a joint may turn per internal step (sub-step, with
            colliders or limits), ``dt · max|ω_child - ω_parent|`` in rad (the first joint's
            parent is the head), before the state counts as a blow-up: reset and report.
            In (0, 100], default 2.5 (100: off). It catches a spin-up that the speed check
            cannot see on a short or thin segment. RK4's reach is ~2.5 for a swing (2.8 is its
            linear limit) but only ~1 for the gyroscopic precession of a segment spinning
            about its own axis, so that rate is held to a 2.5× smaller angle; symplectic Euler
            follows a spin about a segment's own axis exactly (left out of its check) and a
            swing to dt·ω < 2. The largest angles seen in clean runs are in ``docs/bench``.
    """

    integrator: str = 'rk4'
    dt: float = 1.0 / 960.0
    max_steps_per_call: int = 240
    projection: bool = True
    baumgarte_stiffness: float = 0.0
    baumgarte_damping: float = 0.0
    damping_method: str = 'auto'
    guard_max_speed: float = 200.0
    guard_max_gap: float = 1e-3
    guard_max_step_angle: float = 2.5

    def __new__(cls, *args: Any, **kwargs: Any) -> Self:
        # A removed field is refused by name, before the dataclass's own TypeError.
        for name in REMOVED_SOLVER_FIELDS.keys() & kwargs.keys():
            raise removed_field_error('solver.' + name, kwargs[name])
        return super().__new__(cls)

    def validate(self, prefix: str = 'solver') -> Self:
        """These settings, if every field is in range (``prefix`` names them), else SceneError."""
        p = prefix + '.'
        if self.integrator not in INTEGRATORS:
            raise SceneError(p + 'integrator', self.integrator, f'one of {INTEGRATORS}')
        if self.integrator == 'rattle' and not self.projection:
            raise SceneError(p + 'projection', self.projection, "true with integrator 'rattle' "
                             '(its velocity projection is part of the step)')
        check_range(p + 'dt', self.dt, 1e-6, 0.1)
        if not isinstance(self.max_steps_per_call, (int, np.integer)) or \
                not 1 <= self.max_steps_per_call <= 1_000_000:
            raise SceneError(p + 'max_steps_per_call', self.max_steps_per_call,
                             'an integer in [1, 1000000]')
        if self.damping_method not in DAMPING_METHODS:
            raise SceneError(p + 'damping_method', self.damping_method,
                             f'one of {DAMPING_METHODS}')
        check_range(p + 'baumgarte_stiffness', self.baumgarte_stiffness, 0.0, 1e8)
        check_range(p + 'baumgarte_damping', self.baumgarte_damping, 0.0, 1e4)
        check_range(p + 'guard_max_speed', self.guard_max_speed, 1e-3, 1e6, lo_open=True)
        check_range(p + 'guard_max_gap', self.guard_max_gap, 1e-9, 10.0)
        check_range(p + 'guard_max_step_angle', self.guard_max_step_angle, 0.0, 100.0,
                     lo_open=True)
        return self


@dataclass(frozen=True)
class Scene:
    """Chains, kinematic bodies, world settings and solver settings.

    Attributes:
        chains: the chains, each a ``ChainSpec`` (a list is stored as a tuple).
        n_kinematic_bodies: how many heads/anchors the motion supplies each instant.
        gravity: m/s², world frame.
        wind: velocity of the air, m/s, world frame (drag acts on velocity relative to it).
        solver: a ``SolverSpec``.
        colliders: ``ColliderSpec``s (at most 256; a list is stored as a tuple); empty: no
            collision code runs at all.
    """

    chains: tuple[ChainSpec, ...] = (ChainSpec(),)
    n_kinematic_bodies: int = 1
    gravity: Vector3 = (0.0, 0.0, -9.81)
    wind: Vector3 = (0.0, 0.0, 0.0)
    solver: SolverSpec = field(default_factory=SolverSpec)
    colliders: tuple[ColliderSpec, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, 'chains', tuple(self.chains))
        object.__setattr__(self, 'colliders', tuple(self.colliders))
        self.validate()

    def validate(self) -> Self:
        """This scene, if every field of it is in range; else ``SceneError`` naming the field."""
        if not isinstance(self.n_kinematic_bodies, (int, np.integer)) or \
                not 1 <= self.n_kinematic_bodies <= 1_000_000:
            raise SceneError('n_kinematic_bodies', self.n_kinematic_bodies,
                             'an integer in [1, 1000000]')
        if not 1 <= len(self.chains) <= 1_000_000:
            raise SceneError('chains', len(self.chains), 'between 1 and 1000000 chains')
        for i, c in enumerate(self.chains):
            if not isinstance(c, ChainSpec):
                raise SceneError(f'chains[{i}]', c, 'a ChainSpec')
            c.validate(f'chains[{i}]', self.n_kinematic_bodies)
        check_vector('gravity', self.gravity, max_abs=1e4)
        check_vector('wind', self.wind, max_abs=1e3)
        if not isinstance(self.solver, SolverSpec):
            raise SceneError('solver', self.solver, 'a SolverSpec')
        self.solver.validate()
        if len(self.colliders) > MAX_COLLIDERS:
            raise SceneError('colliders', len(self.colliders),
                             f'at most {MAX_COLLIDERS} colliders')
        for i, col in enumerate(self.colliders):
            if not isinstance(col, ColliderSpec):
                raise SceneError(f'colliders[{i}]', col, 'a ColliderSpec')
            col.validate(f'colliders[{i}]', self.n_kinematic_bodies)
        self._check_colliding_segments()
        return self

    def _check_colliding_segments(self) -> None:
        if not self.colliders:
            return
        for i, c in enumerate(self.chains):
            if c.collide and c.n_segments > MAX_COLLIDING_SEGMENTS:
                raise SceneError(f'chains[{i}].n_segments', c.n_segments,
                                 f'an integer in [1, {MAX_COLLIDING_SEGMENTS}] for a chain that '
                                 f'collides (collide: true); up to {MAX_SEGMENTS} with '
                                 'collide: false')

    @property
    def n_segments(self) -> int:
        """Segments of all chains."""
        return sum(c.n_segments for c in self.chains)

    def replace(self, **changes: Any) -> Self:
        """A validated copy with ``changes`` applied (dataclasses.replace)."""
        return replace(self, **changes)

