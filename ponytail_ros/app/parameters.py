"""The ponytail node's parameters: one table, from which the node declares them (description,
range, read-only flag) and builds the ``Scene`` and the input settings.

Naming: global parameters are plain (``rate``, ``gravity``), groups use a dot (``solver.dt``,
``head.window``, ``markers.style``), and every chain's parameters are prefixed with its name
(``chains: [left, right]`` → ``left.n_segments``, ``right.attach``, ...), and so are every
collider's (``colliders: [skull, floor]`` → ``skull.kind``, ``skull.radius``, ``floor.axis``,
...) and every extra frame's (``frames: [left_forearm]`` → ``left_forearm.topic``); chain,
collider and frame names share one namespace. In a params file the dots are nested YAML keys.

Frames (kinematic bodies): a chain hangs from, and a collider is fixed in, one of

* ``head``: the pose on ``head_pose`` (``<chain>.attach``, ``<collider>.center``/``axis`` are
  fixed offsets in the head frame), or, with ``head_frame`` set, the TF frame ``head_frame``
  in ``fixed_frame`` (``app/tf_buffer.py``; ``head_pose`` is then not read);
* a frame named in ``frames``: a kinematic body whose pose arrives on its own
  ``geometry_msgs/PoseStamped`` topic, ``<frame>.topic`` (default ``<frame>_pose``, relative to
  the node's namespace), e.g. a forearm carrying a capsule collider; its poses must be in the
  same frame as the head's (``header.frame_id``), and offsets are in that body's frame; they
  go through the same input checks and estimation settings as the head's (``head.*``,
  ``stale_timeout``, ``input_queue_size``, ``stamp_source``); with ``<frame>.tf_frame`` set
  (and ``head_frame``) its pose comes from TF as the head's, ``fixed_frame -> tf_frame``, and
  its topic is not read;
* ``world``: static, in the head pose's frame (a rope from a ceiling, a floor, a wall). A node
  in which nothing uses the head needs no head pose at all.

Kinematic body indices of the ``Scene``: 0 the head, 1..F the frames in the order of
``frames``, then (only when some chain hangs from the world) the static world body F + 1. World
colliders are static (``ColliderSpec.body`` None). ``<chain>.anchor`` and ``<collider>.frame``
accept ``head``, ``world`` or a frame name; anything else is rejected naming the parameter and
the allowed values.

Live or not (``ParamDef.live``):

* live, applied at the next tick: damping, stiffness, drag, gravity, wind (through
  ``Simulator.set_parameters``, the chain keeps moving), the input handling settings, ``rate``,
  ``frame_id``, the marker settings;
* live by rebuild: the structural ones (segment count, length, mass, radius, attachment, rest
  direction, anchor, joint limits, collide, every collider parameter, every ``solver.*``):
  the simulator is rebuilt from the new scene at rest at the
  current head pose on the next tick (a reset with reason ``'rebuild'``);
* read-only (fixed at start-up): ``chains`` (it decides the topics), ``colliders`` (it decides
  the parameters), ``frames``, every ``<frame>.topic`` and ``<frame>.tf_frame``,
  ``head_frame`` and ``fixed_frame`` (they decide the subscriptions), ``stamp_source``,
  ``output_stamp``,
  ``input_queue_size``, ``head.max_samples``, ``diagnostics_period``, ``record_path``.

This module does not import rclpy (the descriptors are built by the node).
"""
import math
import re
from dataclasses import dataclass, replace

import numpy as np

from ponytail_ros.core.scene import (
    COLLIDER_KINDS,
    DAMPING_METHODS,
    INTEGRATORS,
    MAX_COLLIDERS,
    MAX_LIMIT,
    MAX_SEGMENTS,
    REMOVED_SOLVER_FIELDS,
    ChainSpec,
    ColliderSpec,
    Scene,
    SceneError,
    SolverSpec,
    removed_field_error,
)

from .runner import OUTPUT_STAMPS, RunnerSettings

__all__ = ['ParamDef', 'GLOBAL_PARAMS', 'CHAIN_PARAMS', 'COLLIDER_PARAMS', 'FRAME_PARAMS',
           'NODE_PARAMS',
           'ParameterError', 'chain_param_name', 'check_values', 'build_scene',
           'build_runner_settings', 'check_names', 'collider_names', 'frame_names',
           'frame_topic', 'frame_topics', 'MARKER_STYLES', 'STAMP_SOURCES', 'RESERVED_NAMES',
           'DEFAULT_COLORS', 'FRAMES', 'MAX_FRAMES', 'REMOVED_PARAMS', 'removed_parameter_error']

MARKER_STYLES = ('capsules', 'line', 'off')
STAMP_SOURCES = ('header', 'receive')
#: What a chain hangs from, or a collider is fixed in, besides the frames named in ``frames``:
#: the head, or the head pose's frame (static).
FRAMES = ('head', 'world')
#: Most extra kinematic frames (each is a subscription and a pose estimator).
MAX_FRAMES = 256
#: Group prefixes a chain, collider or frame may not be named after.
RESERVED_NAMES = ('solver', 'head', 'markers', 'qos', 'use_sim_time', 'chains', 'colliders',
                  'frames', 'world')
#: A ROS topic name (relative, absolute or ``~/`` private; no substitutions).
_TOPIC_NAME = re.compile(r'^(~/|/)?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$')
_CHAIN_NAME = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')
#: A TF frame name: printable, no white space, not empty (a leading / is tolerated, as tf2's).
_TF_FRAME = re.compile(r'^/?[^\s/][^\s]*$')

#: Marker colours cycled over the chains when ``<chain>.color`` is not set.
DEFAULT_COLORS = ((0.55, 0.33, 0.16, 1.0), (0.85, 0.65, 0.30, 1.0), (0.20, 0.20, 0.22, 1.0),
                  (0.70, 0.25, 0.20, 1.0))


@dataclass(frozen=True)
class ParamDef:
    """One parameter.

    ``kind``: 'double', 'int', 'bool', 'string', 'double3' (3 doubles), 'double4', 'doubles'
    (any number of doubles, e.g. one per segment), 'strings'.
    ``lo``/``hi``: range (each element for arrays); ``choices``: allowed strings.
    ``live``: changeable at run time (False → read_only). ``rebuild``: a change rebuilds the
    simulator (structural).
    """

    name: str
    default: object
    kind: str
    description: str
    lo: float | None = None
    hi: float | None = None
    choices: tuple | None = None
    live: bool = True
    rebuild: bool = False

    def constraints(self):
        """Human-readable constraint text (``ParameterDescriptor.additional_constraints``)."""
        parts = []
        if self.choices:
            parts.append('one of: ' + ', '.join(self.choices))
        if self.kind in ('double3', 'double4') and self.lo is not None:
            n = 3 if self.kind == 'double3' else 4
            parts.append(f'{n} numbers, each in [{self.lo:g}, {self.hi:g}]')
        if self.kind == 'doubles' and self.lo is not None:
            parts.append(f'numbers, each in [{self.lo:g}, {self.hi:g}]')
        if not self.live:
            parts.append('read-only: set at start-up')
        elif self.rebuild:
            parts.append('changing it rebuilds the chains at rest at the current head pose')
        return '; '.join(parts)


_SOLVER = SolverSpec()
_CHAIN = ChainSpec()

GLOBAL_PARAMS = (
    ParamDef('rate', 120.0, 'double', 'Simulation/publish rate of the timer, Hz. Each tick '
             'advances by the clock\'s elapsed time, not the nominal period.', 1.0, 1000.0),
    ParamDef('frame_id', '', 'string', 'frame_id of the outputs; empty: the head pose\'s '
             'frame (the simulation runs in the head pose\'s frame either way).'),
    ParamDef('head_frame', '', 'string', 'The head from TF: the TF frame of the head (e.g. '
             'head, from robot_state_publisher, mocap or ROS4HRI). Its pose is fixed_frame -> '
             'head_frame composed along the TF tree (/tf, /tf_static) at the stamps of the '
             'moving transforms on the way, interpolated between their samples; head_pose is '
             'then not read. "" = the head pose on head_pose (PoseStamped).', live=False),
    ParamDef('fixed_frame', 'world', 'string', 'The frame the simulation runs in, which must '
             'be inertial (world, odom, map: not moving or accelerating): gravity, wind and '
             'drag are in it. With head_frame set, the head pose (and every frame with a '
             '<frame>.tf_frame) is taken in it and the segments are published in it (/tf '
             'parent, segment_poses header.frame_id unless frame_id is set). With head poses '
             'on head_pose, it is their frame when their header.frame_id is empty (the poses\' '
             'frame otherwise).', live=False),
    ParamDef('chains', ['ponytail'], 'strings', 'Names of the chains (each configured by '
             '<name>.* parameters). One chain publishes segment_poses, several publish '
             'segment_poses/<name>.', live=False),
    ParamDef('colliders', [], 'strings', 'Names of the colliders (each configured by '
             '<name>.* parameters; names distinct from the chains\'); [] = no collision code '
             f'runs at all. At most {MAX_COLLIDERS}.', live=False),
    ParamDef('frames', [], 'strings', 'Names of extra kinematic frames (each configured by '
             '<name>.topic; names distinct from the chains\' and colliders\'): bodies whose pose '
             'arrives on their own PoseStamped topic, in the head pose\'s frame, which chains '
             '(<chain>.anchor) and colliders (<collider>.frame) can be fixed in, e.g. a forearm. '
             f'At most {MAX_FRAMES}; more than a few: give them one topic, frames_topic.',
             live=False),
    ParamDef('frames_topic', '', 'string', 'One geometry_msgs/PoseArray topic for all the '
             'frames (sensor-data QoS): poses[i] is the pose of frames[i], header.frame_id that '
             'of the head poses, header.stamp the time of all of them; a message with another '
             'pose count is dropped (frames_count). "" = each frame on its own <frame>.topic. '
             'One subscription instead of one per frame: a node with many characters.',
             live=False),
    ParamDef('interpolation_delay', 0.0, 'double', 'Minimum delay, s: the chain is driven by '
             'the head as it was delay = max(interpolation_delay, interpolation_delay_periods x '
             'input period) before the tick; samples on both sides of that time give smooth '
             'head velocity/acceleration at the cost of this latency.', 0.0, 0.5),
    ParamDef('interpolation_delay_periods', 2.0, 'double', 'The delay is at least this many '
             'input periods (median interval of the recent head poses): 2 ms at 1 kHz, 67 ms '
             'at 30 Hz. 0: use interpolation_delay alone.', 0.0, 10.0),
    ParamDef('latency_compensation', True, 'bool', 'Translate each output chain by its '
             'attachment point\'s displacement over the delay (extrapolated head), so that its '
             'root stays on the current head; the swing itself still lags by the delay.'),
    ParamDef('output_stamp', 'tick', 'string', 'Stamp of the published chain: tick (the tick '
             'time; the chain is the one simulated at tick - delay with its root moved onto the '
             'current head, latency_compensation: for rendering now) or simulated (the time of '
             'the state itself, no latency compensation: for analysis, pairing with the head '
             'by stamp). Recorded with the parameters; ponytail_replay compare reads it.',
             choices=OUTPUT_STAMPS, live=False),
    ParamDef('stale_timeout', 0.25, 'double', 'No head pose accepted for this long (s): the '
             'head is stale (last pose held, warning in diagnostics); likewise for each of the '
             'frames. A pose in a new frame_id is adopted once every input is stale.',
             0.01, 60.0),
    ParamDef('teleport_distance', 0.5, 'double', 'A head pose farther than this (m) from the '
             'previous one is a teleport: the chain is reset at rest at the new pose.',
             1e-3, 1e3),
    ParamDef('teleport_angle', 1.0, 'double', 'A head pose rotated more than this (rad) from '
             'the previous one is a teleport.', 1e-3, math.pi),
    ParamDef('gravity', [0.0, 0.0, -9.81], 'double3', 'Gravity in the simulation\'s frame '
             '(fixed_frame, or the head poses\' frame; inertial), m/s^2.', -1e4, 1e4),
    ParamDef('wind', [0.0, 0.0, 0.0], 'double3', 'Air velocity in the simulation\'s frame '
             '(fixed_frame, or the head poses\' frame; inertial), m/s (drag acts on the '
             'velocity relative to it).', -1e3, 1e3),
    ParamDef('stamp_source', 'header', 'string', 'Time of a head pose: header (its '
             'header.stamp; a zero stamp falls back to the receive time) or receive (the node '
             'clock on arrival: use when the publisher\'s clock differs).',
             choices=STAMP_SOURCES, live=False),
    ParamDef('input_queue_size', 256, 'int', 'Head poses buffered between ticks; beyond it the '
             'oldest are dropped (queue_overflow): bounded work per tick.', 1, 100000,
             live=False),
    ParamDef('record_path', '', 'string', 'Record the run to this MCAP file (rosbag2 layout: '
             'head input, outputs, diagnostics, parameters; replay with ponytail_replay). "" = '
             'off. Never overwrites a file (error logged, the simulation goes on); strftime % '
             'codes give one file per run, e.g. runs/ponytail_%Y%m%d_%H%M%S.mcap.', live=False),
    ParamDef('diagnostics_period', 1.0, 'double', 'Period of /diagnostics, s (steady clock).',
             0.05, 60.0, live=False),
    ParamDef('markers.style', 'capsules', 'string', 'segment_markers: capsules (cylinder + '
             'sphere per segment), line (line strip + spheres) or off.', choices=MARKER_STYLES),
    ParamDef('markers.rate', 30.0, 'double', 'Maximum rate of segment_markers, Hz (capped by '
             'rate).', 0.1, 1000.0),
    # Head estimation (HeadEstimator).
    ParamDef('head.window', 0.1, 'double', 'Head estimation: samples within this of the '
             'evaluation time enter the local polynomial fit, s (widened to the nearest '
             'head.degree + 3 samples at low rates).', 0.005, 2.0),
    ParamDef('head.degree', 3, 'int', 'Head estimation: degree of the polynomial in time '
             '(above 5 only with head.min_samples = head.degree + 1 on exact poses: '
             'interpolation, look-ahead replay).', 1, 9),
    ParamDef('head.min_samples', 0, 'int', 'Head estimation: the fit uses at least this many '
             'of the nearest samples (widening head.window); 0 = head.degree + 3. '
             'head.degree + 1 makes it interpolate (exact animation poses, look-ahead '
             'replay).', 0, 1000),
    ParamDef('head.max_extrapolation', 0.1, 'double', 'Head estimation: how far past the newest '
             'sample the head motion is extrapolated (braking to a stop), s; later the last pose '
             'is held.', 0.0, 2.0),
    ParamDef('head.max_gap', 0.5, 'double', 'Head estimation: a gap between samples longer '
             'than this starts a new history, s.', 0.01, 60.0),
    ParamDef('head.quat_tolerance', 1e-3, 'double', 'Accepted | |q| - 1 | of a head pose '
             'quaternion (renormalised); beyond it the pose is dropped (non_unit_quaternion).',
             1e-9, 0.5),
    ParamDef('head.max_samples', 128, 'int', 'Head estimation: stored samples (covers '
             'head.window at the input rate: 128 at 1 kHz).', 8, 100000, live=False),
    # Solver (SolverSpec): structural, a change rebuilds.
    ParamDef('solver.integrator', _SOLVER.integrator, 'string', 'Integrator.',
             choices=INTEGRATORS, rebuild=True),
    ParamDef('solver.dt', _SOLVER.dt, 'double', 'Fixed internal step, s.', 1e-6, 0.1,
             rebuild=True),
    ParamDef('solver.max_steps_per_call', _SOLVER.max_steps_per_call, 'int',
             'Most internal steps per tick (bounded work); time beyond is dropped and '
             'reported. Must cover one tick: '
             'max_steps_per_call * dt >= 1/rate.', 1, 1000000, rebuild=True),
    ParamDef('solver.projection', _SOLVER.projection, 'bool', 'Project positions and '
             'velocities back on the joints after each step.', rebuild=True),
    ParamDef('solver.baumgarte_stiffness', _SOLVER.baumgarte_stiffness, 'double',
             'Baumgarte stabilisation stiffness, 1/s^2.', 0.0, 1e8, rebuild=True),
    ParamDef('solver.baumgarte_damping', _SOLVER.baumgarte_damping, 'double',
             'Baumgarte stabilisation damping, 1/s.', 0.0, 1e4, rebuild=True),
    ParamDef('solver.damping_method', _SOLVER.damping_method, 'string', 'Joint damping '
             'integration: explicit (accurate, unstable for strong damping of thin segments), '
             'implicit (always stable) or auto (explicit while stable).', choices=DAMPING_METHODS,
             rebuild=True),
    ParamDef('solver.guard_max_speed', _SOLVER.guard_max_speed, 'double', 'A segment faster '
             'than this (m/s) is a blow-up: the chain is reset.', 1e-3, 1e6, rebuild=True),
    ParamDef('solver.guard_max_gap', _SOLVER.guard_max_gap, 'double', 'A joint gap larger '
             'than this (m) is a blow-up: the chain is reset.', 1e-9, 10.0, rebuild=True),
    ParamDef('solver.guard_max_step_angle', _SOLVER.guard_max_step_angle, 'double', 'A joint '
             'turning more than this (rad) in one internal step is beyond what the integrator '
             'can follow: the chain is reset (100 = off).', 1e-3, 100.0, rebuild=True),
)

CHAIN_PARAMS = (
    ParamDef('n_segments', _CHAIN.n_segments, 'int', 'Number of rigid segments.', 1,
             MAX_SEGMENTS, rebuild=True),
    ParamDef('length', _CHAIN.length, 'double', 'Total length, m (split equally).', 1e-4, 1e3,
             rebuild=True),
    ParamDef('mass', _CHAIN.mass, 'double', 'Total mass, kg (split by length).', 1e-7, 1e4,
             rebuild=True),
    ParamDef('radius', _CHAIN.radius, 'double', 'Segment radius, m (inertia of a solid '
             'cylinder; marker size).', 1e-6, 10.0, rebuild=True),
    ParamDef('segment_lengths', [], 'doubles', 'Per-segment lengths, m, root first: '
             'n_segments numbers, overriding length. [] = length split equally.', 1e-6, 1e3,
             rebuild=True),
    ParamDef('segment_masses', [], 'doubles', 'Per-segment masses, kg, root first: n_segments '
             'numbers, overriding mass. [] = mass split in proportion to the lengths.', 1e-9,
             1e4, rebuild=True),
    ParamDef('inertia', [], 'doubles', 'Per-segment principal moments about each centre, '
             'kg m^2: 3 x n_segments numbers, (axial, across, across) for each segment, root '
             'first. [] = solid cylinders of the segment radius.', 1e-15, 1e4, rebuild=True),
    ParamDef('attach', list(_CHAIN.attach), 'double3', 'Attachment point in the head frame, '
             'm.', -1e3, 1e3, rebuild=True),
    ParamDef('rest_direction', [0.0, 0.0, 0.0], 'double3', 'Direction of the straight chain '
             'at rest in the anchor frame; [0, 0, 0]: along gravity.', -1e6, 1e6, rebuild=True),
    ParamDef('anchor', 'head', 'string', 'What the chain hangs from: head (attach and '
             'rest_direction in the head frame), world (a static point: attach and '
             'rest_direction in the head pose\'s frame, e.g. a rope from a ceiling) or one of '
             'the frames (attach and rest_direction in that frame).',
             choices=FRAMES, rebuild=True),
    ParamDef('swing_limit', 0.0, 'double', 'Cone limit of every joint, rad: the angle between '
             'a segment and its parent\'s axis (the first one: its rest direction) stays below '
             'it. 0 = off (no limit code runs).', 0.0, MAX_LIMIT, rebuild=True),
    ParamDef('twist_limit', 0.0, 'double', 'Twist limit of every joint, rad: rotation about '
             'the segment\'s own axis relative to its parent, within +-it. 0 = off.', 0.0,
             MAX_LIMIT, rebuild=True),
    ParamDef('swing_limits', [], 'doubles', 'Per-joint cone limits, rad, root first: '
             f'n_segments numbers in (0, {MAX_LIMIT}], overriding swing_limit. [] = swing_limit '
             'at every joint.', 1e-6, MAX_LIMIT, rebuild=True),
    ParamDef('twist_limits', [], 'doubles', 'Per-joint twist limits, rad, root first: '
             f'n_segments numbers in (0, {MAX_LIMIT}], overriding twist_limit. [] = '
             'twist_limit at every joint.', 1e-6, MAX_LIMIT, rebuild=True),
    ParamDef('collide', True, 'bool', 'Whether the segments collide with the colliders (as '
             'capsules of the chain\'s radius along their whole length).', rebuild=True),
    ParamDef('damping', _CHAIN.damping, 'double', 'Joint damping, N m s/rad (live).', 0.0, 1e3),
    ParamDef('stiffness', _CHAIN.stiffness, 'double', 'Bending stiffness towards the rest '
             'pose, N m/rad (live).', 0.0, 1e4),
    ParamDef('drag_linear', _CHAIN.drag_linear, 'double', 'Linear air drag per metre, '
             'N s/m^2 (live).', 0.0, 1e3),
    ParamDef('drag_quadratic', _CHAIN.drag_quadratic, 'double', 'Quadratic air drag per '
             'metre, N s^2/m^3 (live).', 0.0, 1e3),
    ParamDef('color', [0.55, 0.33, 0.16, 1.0], 'double4', 'Marker colour r, g, b, a.', 0.0,
             1.0),
)

_COLLIDER = ColliderSpec()

COLLIDER_PARAMS = (
    ParamDef('kind', _COLLIDER.kind, 'string', 'Shape: sphere, capsule (a segment swept by a '
             'sphere) or plane (the segments stay on the side the axis points to).',
             choices=COLLIDER_KINDS, rebuild=True),
    ParamDef('frame', 'head', 'string', 'What the collider is fixed in: head (center and axis '
             'are fixed offsets in the head frame; it moves with the head), one of the frames '
             '(offsets in that frame: a forearm) or world (static, in the head pose\'s frame: a '
             'floor, a wall).', choices=FRAMES, rebuild=True),
    ParamDef('center', list(_COLLIDER.center), 'double3', 'Sphere/capsule centre, or a point '
             'of the plane, m, in its frame.', -1e3, 1e3, rebuild=True),
    ParamDef('axis', list(_COLLIDER.axis), 'double3', 'Capsule axis, or the plane\'s normal '
             '(towards the free side), in its frame; non-zero (normalised). Unused by a '
             'sphere.', -1e6, 1e6, rebuild=True),
    ParamDef('radius', _COLLIDER.radius, 'double', 'Sphere/capsule radius, m. Unused by a '
             'plane.', 1e-6, 100.0, rebuild=True),
    ParamDef('half_length', _COLLIDER.half_length, 'double', 'Half the length of a capsule\'s '
             'core segment, m. Unused by spheres and planes.', 0.0, 100.0, rebuild=True),
    ParamDef('friction', _COLLIDER.friction, 'double', 'Coulomb friction coefficient against '
             'the segments; 0 = frictionless.', 0.0, 10.0, rebuild=True),
)

FRAME_PARAMS = (
    ParamDef('topic', '', 'string', 'The frame\'s pose topic (geometry_msgs/PoseStamped, '
             'sensor-data QoS, header.frame_id that of the head poses); "" = <frame>_pose. '
             'Relative names are in the node\'s namespace.', live=False),
    ParamDef('tf_frame', '', 'string', 'The frame from TF: its pose is fixed_frame -> '
             'tf_frame composed along the TF tree, as the head\'s with head_frame (which must '
             'be set too); its topic is then not read. "" = from its topic.', live=False),
)

#: The ROS front end's own parameters (``ros/node.py`` declares them; they do not change the
#: simulation, and ``ponytail_replay`` records ``/tf`` regardless).
NODE_PARAMS = (
    ParamDef('tf.publish', True, 'bool', 'Publish every segment as a TF frame on /tf (needs '
             'tf2_msgs: a sourced ROS 2 workspace, or built into the environment; without it '
             'the node says once that live TF is off; recordings hold /tf regardless).',
             live=False),
    ParamDef('tf.prefix', '', 'string', 'TF frames of the segments are <tf.prefix><chain>/<i> '
             '(i from 0 at the root), children of the outputs\' frame (fixed_frame with the head '
             'from TF). Default: the node\'s namespace (/alice -> alice/, so alice/ponytail/3; '
             'the root namespace: none), so characters never share a frame; "" = none.',
             live=False),
)

_GLOBAL = {p.name: p for p in GLOBAL_PARAMS}
_CHAIN_DEFS = {p.name: p for p in CHAIN_PARAMS}
_COLLIDER_DEFS = {p.name: p for p in COLLIDER_PARAMS}
_FRAME_DEFS = {p.name: p for p in FRAME_PARAMS}
#: Parameters naming a frame: their choices are FRAMES plus the names in ``frames``.
_FRAME_CHOICE = {('chain', 'anchor'), ('collider', 'frame')}


class ParameterError(ValueError):
    """A parameter value is rejected; the message names the parameter(s)."""

    def __init__(self, names, message):
        self.names = tuple(names) if isinstance(names, (list, tuple)) else (names,)
        super().__init__(message)


#: Parameters that were removed (``scene.REMOVED_SOLVER_FIELDS``): a params file that sets one
#: is refused (``removed_parameter_error``), a node warns and ignores it.
REMOVED_PARAMS = frozenset('solver.' + f for f in REMOVED_SOLVER_FIELDS)


def removed_parameter_error(name, value):
    """``ParameterError`` for the removed parameter ``name`` set to ``value``: it names the
    parameter and says it was removed, and why."""
    return ParameterError(name, str(removed_field_error(name, value)))


def chain_param_name(chain, field):
    return f'{chain}.{field}'


def definition(name, chains, colliders=(), frames=()):
    """The ``ParamDef`` of a full parameter name, or None if it is not one of ours. With
    ``frames``, ``<chain>.anchor`` and ``<collider>.frame`` allow the frame names too."""
    if name in _GLOBAL:
        return _GLOBAL[name]
    group, _, field = name.partition('.')
    if group in chains and field in _CHAIN_DEFS:
        return _with_frames(_CHAIN_DEFS[field], 'chain', frames)
    if group in colliders and field in _COLLIDER_DEFS:
        return _with_frames(_COLLIDER_DEFS[field], 'collider', frames)
    if group in frames and field in _FRAME_DEFS:
        return _FRAME_DEFS[field]
    return None


def _with_frames(pdef, group, frames):
    if frames and (group, pdef.name) in _FRAME_CHOICE:
        return replace(pdef, choices=FRAMES + tuple(frames))
    return pdef


def collider_names(values):
    """The collider names of a value set (``[]`` when it has none)."""
    return [str(c) for c in values.get('colliders', ())]


def frame_names(values):
    """The extra frame names of a value set (``[]`` when it has none)."""
    return [str(f) for f in values.get('frames', ())]


def frame_topic(values, frame):
    """The topic of ``frame`` as configured: ``frames_topic`` if set (all frames' poses in one
    ``PoseArray``), else ``<frame>.topic`` (default ``<frame>_pose``)."""
    return (values.get('frames_topic') or values.get(chain_param_name(frame, 'topic'))
            or f'{frame}_pose')


def frame_topics(values):
    """The topic of every frame of a value set, in the order of ``frames``."""
    return [frame_topic(values, f) for f in frame_names(values)]


def check_names(chains, colliders=(), frames=()):
    """Check the chain, collider and frame names (valid, not reserved, all distinct)."""
    if not chains:
        raise ParameterError('chains', 'chains: at least one chain name is needed')
    if len(colliders) > MAX_COLLIDERS:
        raise ParameterError('colliders', f'colliders: {len(colliders)} names, at most '
                                          f'{MAX_COLLIDERS} are allowed')
    if len(frames) > MAX_FRAMES:
        raise ParameterError('frames', f'frames: {len(frames)} names, at most {MAX_FRAMES} are '
                                       f'allowed')
    groups = (('chains', chains), ('colliders', colliders), ('frames', frames))
    for param, names in groups:
        _check_group(param, names)
    for i, (pa, a) in enumerate(groups):
        for pb, b in groups[i + 1:]:
            shared = sorted(set(a) & set(b))
            if shared:
                raise ParameterError((pa, pb), f'{pa} and {pb} share the name(s) {shared}: '
                                               f'every name prefixes its own parameters')


def _check_group(param, names):
    """The names of one list parameter (``chains``, ``colliders``, ``frames``): each valid and
    not reserved, all distinct."""
    for n in names:
        if not _CHAIN_NAME.match(n) or n in RESERVED_NAMES:
            raise ParameterError(param, f'{param}: {n!r} is not a valid name (letters, '
                                 f'digits, underscores, starting with a letter; not one of '
                                 f'{", ".join(RESERVED_NAMES)})')
    if len(set(names)) != len(names):
        raise ParameterError(param, f'{param}: duplicate names in {list(names)}')


def _check_frame_topics(values, frames):
    """Each frame's topic a valid ROS name, distinct from the head's and the others' (or the
    one ``frames_topic``, distinct from the head's)."""
    batch = values.get('frames_topic') or ''
    if batch:
        if not _TOPIC_NAME.match(batch) or batch == 'head_pose':
            raise ParameterError('frames_topic', f'frames_topic = {batch!r} is not allowed: '
                                                 f'must be "" (each frame on its <frame>.topic) '
                                                 f'or a ROS topic name other than head_pose')
        return
    seen = {'head_pose': 'the head'}
    for f in frames:
        name = chain_param_name(f, 'topic')
        topic = frame_topic(values, f)
        if not _TOPIC_NAME.match(topic):
            raise ParameterError(name, f'{name} = {values.get(name)!r} is not allowed: must be '
                                       f'"" (= {f}_pose) or a ROS topic name (letters, digits, '
                                       f'underscores and /, each part starting with a letter '
                                       f'or _; absolute /..., private ~/... or relative)')
        if topic in seen:
            raise ParameterError(name, f'{name} = {topic!r} is not allowed: {seen[topic]} '
                                       f'already reads that topic')
        seen[topic] = f'frame {f}'


def _check_tf_frames(values, frames):
    """``fixed_frame`` a TF frame name, ``head_frame`` and each ``<frame>.tf_frame`` empty or
    one other than ``fixed_frame``; a frame from TF only with the head from TF."""
    fixed = values.get('fixed_frame', 'world')
    if not _TF_FRAME.match(str(fixed)):
        raise ParameterError('fixed_frame', f'fixed_frame = {fixed!r} is not allowed: must be '
                                            f'a TF frame name (no spaces, not empty), e.g. '
                                            f'world, odom or map: an inertial frame')
    head = values.get('head_frame', '')
    names = [('head_frame', head)] + [(chain_param_name(f, 'tf_frame'),
                                       values.get(chain_param_name(f, 'tf_frame'), ''))
                                      for f in frames]
    for name, frame in names:
        if frame and (not _TF_FRAME.match(str(frame)) or frame.lstrip('/') == fixed.lstrip('/')):
            raise ParameterError(name, f'{name} = {frame!r} is not allowed: must be "" or a TF '
                                       f'frame name (no spaces) other than fixed_frame '
                                       f'({fixed!r})')
        if frame and not head:
            raise ParameterError((name, 'head_frame'), f'{name} = {frame!r} needs the head from '
                                                       f'TF too: set head_frame')
        if frame and name != 'head_frame' and values.get('frames_topic'):
            raise ParameterError((name, 'frames_topic'), f'{name} = {frame!r} is not allowed '
                                                         f'with frames_topic (every frame\'s '
                                                         f'pose on that one topic)')


def _check_value(name, pdef, value):
    """Type/shape/choice/range check of one value (rclpy checks only scalar ranges)."""
    if pdef.kind in ('double3', 'double4'):
        n = 3 if pdef.kind == 'double3' else 4
        try:
            arr = np.asarray(list(value), dtype=float)
        except (TypeError, ValueError):
            arr = np.zeros(0)
        if arr.shape != (n,) or not np.all(np.isfinite(arr)) or \
                (pdef.lo is not None and (np.any(arr < pdef.lo) or np.any(arr > pdef.hi))):
            shown = [float(x) for x in arr.ravel()] if arr.size else value
            raise ParameterError(name, f'{name} = {shown} is not allowed: must be {n} finite '
                                       f'numbers, each in [{pdef.lo:g}, {pdef.hi:g}]')
    elif pdef.kind == 'doubles':
        try:
            arr = np.asarray(list(value), dtype=float)
        except (TypeError, ValueError):
            arr = np.full(1, np.nan)
        if arr.ndim != 1 or arr.size > 3 * MAX_SEGMENTS or not np.all(np.isfinite(arr)) or \
                np.any(arr < pdef.lo) or np.any(arr > pdef.hi):
            raise ParameterError(name, f'{name} = {value!r} is not allowed: must be a list of '
                                       f'finite numbers, each in [{pdef.lo:g}, {pdef.hi:g}]')
    elif pdef.choices is not None and value not in pdef.choices:
        raise ParameterError(name, f'{name} = {value!r} is not allowed: must be one of '
                                   f'{", ".join(pdef.choices)}')
    elif pdef.kind in ('double', 'int') and pdef.lo is not None:
        if not (math.isfinite(value) and pdef.lo <= value <= pdef.hi):
            raise ParameterError(name, f'{name} = {value!r} is out of range '
                                       f'[{pdef.lo:g}, {pdef.hi:g}]')


def _scene_error_name(err, chains, colliders=()):
    """Map a ``SceneError`` field (``chains[0].length``, ``solver.dt``) to a parameter name."""
    f = err.field
    m = re.match(r'^chains\[(\d+)\]\.(.*)$', f)
    if m:
        field = m.group(2)
        if field in ('swing_limit', 'twist_limit') and isinstance(err.value, (tuple, list)):
            field += 's'                        # the per-joint list was given
        return chain_param_name(chains[int(m.group(1))],
                                'anchor' if field == 'anchor_body' else field)
    m = re.match(r'^colliders\[(\d+)\]\.(.*)$', f)
    if m:
        field = m.group(2)
        return chain_param_name(colliders[int(m.group(1))], 'frame' if field == 'body' else field)
    return f


def _vector(value):
    return tuple(float(x) for x in value)


def build_scene(values, chains):
    """The ``Scene`` of a full set of parameter ``values`` (dict name → value); raises
    ``ParameterError`` naming the offending parameter(s).

    Kinematic bodies: 0 is the head, 1..F the frames (``frames``, in order); a static body F + 1
    (identity pose, the head pose's frame) is added only when some chain hangs from the world.
    World colliders are static (body None).
    """
    colliders = collider_names(values)
    frames = frame_names(values)
    bodies = {'head': 0, **{f: 1 + i for i, f in enumerate(frames)}}
    world_body = 1 + len(frames)

    def body_of(name, value, world):
        if value in bodies:
            return bodies[value]
        if value == 'world':
            return world
        raise ParameterError(name, f'{name} = {value!r} is not allowed: must be one of '
                                   f'{", ".join(FRAMES + tuple(frames))}')
    world_anchor = any(values[chain_param_name(c, 'anchor')] == 'world' for c in chains)
    specs = []
    for c in chains:
        v = {f: values[chain_param_name(c, f)] for f in _CHAIN_DEFS}
        rest = _vector(v['rest_direction'])
        n = int(v['n_segments'])
        per_segment = {f: _vector(v[f]) or None for f in ('segment_lengths', 'segment_masses')}
        inertia = _vector(v['inertia'])
        if inertia and len(inertia) != 3 * n:
            name = chain_param_name(c, 'inertia')
            raise ParameterError(name, f'{name} = {list(inertia)} is not allowed: must be '
                                       f'3 x n_segments = {3 * n} numbers (axial, across, across '
                                       f'moment of each segment, kg m^2) or [] (solid cylinders)')
        specs.append(ChainSpec(
            name=c, n_segments=n, length=float(v['length']),
            mass=float(v['mass']), radius=float(v['radius']), **per_segment,
            inertia=tuple(zip(inertia[0::3], inertia[1::3], inertia[2::3], strict=True)) or None,
            anchor_body=body_of(chain_param_name(c, 'anchor'), v['anchor'], world_body),
            attach=_vector(v['attach']),
            rest_direction=None if not any(rest) else rest,
            damping=float(v['damping']), stiffness=float(v['stiffness']),
            drag_linear=float(v['drag_linear']), drag_quadratic=float(v['drag_quadratic']),
            swing_limit=_vector(v['swing_limits']) or float(v['swing_limit']) or None,
            twist_limit=_vector(v['twist_limits']) or float(v['twist_limit']) or None,
            collide=bool(v['collide'])))
    collider_specs = []
    for c in colliders:
        v = {f: values[chain_param_name(c, f)] for f in _COLLIDER_DEFS}
        collider_specs.append(ColliderSpec(
            kind=v['kind'], body=body_of(chain_param_name(c, 'frame'), v['frame'], None),
            center=_vector(v['center']),
            axis=_vector(v['axis']), radius=float(v['radius']),
            half_length=float(v['half_length']), friction=float(v['friction'])))
    solver = SolverSpec(
        integrator=values['solver.integrator'], dt=float(values['solver.dt']),
        max_steps_per_call=int(values['solver.max_steps_per_call']),
        projection=bool(values['solver.projection']),
        baumgarte_stiffness=float(values['solver.baumgarte_stiffness']),
        baumgarte_damping=float(values['solver.baumgarte_damping']),
        damping_method=values['solver.damping_method'],
        guard_max_speed=float(values['solver.guard_max_speed']),
        guard_max_gap=float(values['solver.guard_max_gap']),
        guard_max_step_angle=float(values['solver.guard_max_step_angle']))
    try:
        return Scene(chains=tuple(specs),
                     n_kinematic_bodies=1 + len(frames) + (1 if world_anchor else 0),
                     gravity=_vector(values['gravity']), wind=_vector(values['wind']),
                     solver=solver, colliders=tuple(collider_specs))
    except SceneError as err:
        name = _scene_error_name(err, chains, colliders)
        raise ParameterError(name, f'{name} = {err.value!r} is not allowed: must be '
                                   f'{err.allowed}') from err


def build_runner_settings(values):
    return RunnerSettings(
        interpolation_delay=float(values['interpolation_delay']),
        interpolation_delay_periods=float(values['interpolation_delay_periods']),
        latency_compensation=bool(values['latency_compensation']),
        teleport_distance=float(values['teleport_distance']),
        teleport_angle=float(values['teleport_angle']),
        stale_timeout=float(values['stale_timeout']),
        max_queue=int(values['input_queue_size']),
        window=float(values['head.window']), degree=int(values['head.degree']),
        max_extrapolation=float(values['head.max_extrapolation']),
        max_gap=float(values['head.max_gap']),
        quat_tolerance=float(values['head.quat_tolerance']),
        max_samples=int(values['head.max_samples']),
        min_samples=int(values['head.min_samples']),
        output_stamp=str(values['output_stamp']))


def check_values(values, chains, changed=None):
    """Check a full set of ``values``: every value (or those in ``changed``), then the scene and
    the cross-parameter consistency. Returns the ``Scene``; raises ``ParameterError``."""
    names = values.keys() if changed is None else changed
    colliders = collider_names(values)
    frames = frame_names(values)
    for name in names:
        pdef = definition(name, chains, colliders, frames)
        if pdef is not None:
            _check_value(name, pdef, values[name])
    _check_frame_topics(values, frames)
    _check_tf_frames(values, frames)
    scene = build_scene(values, chains)
    dt, steps, rate = (values['solver.dt'], values['solver.max_steps_per_call'], values['rate'])
    if steps * dt < 1.0 / rate * (1.0 - 1e-9):
        raise ParameterError(
            ('solver.max_steps_per_call', 'solver.dt', 'rate'),
            f'inconsistent: solver.max_steps_per_call * solver.dt = {steps} * {dt:g} s = '
            f'{steps * dt:g} s is shorter than one tick (1/rate = {1.0 / rate:g} s): every tick '
            f'would drop time')
    return scene
