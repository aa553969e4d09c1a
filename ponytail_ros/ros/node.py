"""The ponytail node: head pose in, segment poses out, on every timer tick.

Run: ``ponytail_node --ros-args --params-file config/ponytail.yaml [-p key:=value]
[-r __ns:=/alice]`` (or ``python -m ponytail_ros.ros.node --ros-args ...``). Node name
``ponytail``.

Topics (all relative, so a namespace per character scales out; no global state):

* subscribes ``head_pose`` (``geometry_msgs/PoseStamped``), sensor-data QoS (best effort, so
  reliable and best-effort publishers both connect);
* publishes ``segment_poses`` (``geometry_msgs/PoseArray``, reliable, depth 10) when there is one
  chain, ``segment_poses/<chain>`` per chain when there are several: one pose per segment, origin
  at the proximal joint, local +X along the segment; ``header.frame_id`` = the head pose's frame
  (or parameter ``frame_id``), ``header.stamp`` = the tick time (node clock);
* publishes ``segment_markers`` (``visualization_msgs/MarkerArray``, reliable, depth 10) at up to
  ``markers.rate``: capsules or line strip + spheres (``markers.style``), one namespace per chain;
* records the run when ``record_path`` is set (``ponytail_ros/recording/recorder.py``: head
  input, outputs, parameter changes, parameters in effect; replay it with ``ponytail_replay``);
* publishes ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``, every
  ``diagnostics_period`` s of wall time): one status named ``ponytail: <node FQN>`` with the
  solve time, joint gap, dropped inputs by reason, resets by reason, dropped time, head state.
  ``/diagnostics`` is absolute by ROS convention (one aggregator for all characters); the status
  name carries the namespace.

Each tick advances the chains by the clock's elapsed time (``use_sim_time`` and ``/clock`` work;
late or skipped timer periods are caught up, at most ``solver.max_steps_per_call`` steps). The
per-tick logic (input checks, estimation, stepping) is ``ChainRunner`` (``runner.py``); the
parameters are in ``parameters.py``.

Note: no ``from __future__ import annotations`` here: rclpy passes ``TimerInfo`` to a timer
callback only if the parameter's annotation *is* the class.
"""
import sys
import time

import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from rclpy.timer import TimerInfo
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseArray, PoseStamped
from visualization_msgs.msg import MarkerArray

from .messages import ChainMessages, delete_all_marker
from .parameters import (CHAIN_PARAMS, DEFAULT_COLORS, GLOBAL_PARAMS, ParameterError,
                         build_runner_settings, chain_param_name, check_chain_names,
                         check_values, definition)
from .runner import DROP_REASONS, RESET_REASONS, ChainRunner
from ponytail_ros.ros.spin import run_node

__all__ = ['PonytailNode', 'main', 'OUTPUT_QOS', 'INPUT_QOS']

#: ``head_pose`` subscription: the sensor-data preset (best effort, volatile, keep last 5).
INPUT_QOS = qos_profile_sensor_data
#: ``segment_poses`` and ``segment_markers``: reliable, volatile, keep last 10.
OUTPUT_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)

_PARAM_TYPES = {
    'double': Parameter.Type.DOUBLE, 'int': Parameter.Type.INTEGER,
    'bool': Parameter.Type.BOOL, 'string': Parameter.Type.STRING,
    'double3': Parameter.Type.DOUBLE_ARRAY, 'double4': Parameter.Type.DOUBLE_ARRAY,
    'strings': Parameter.Type.STRING_ARRAY,
}


def _descriptor(pdef):
    d = ParameterDescriptor(description=pdef.description,
                            additional_constraints=pdef.constraints(),
                            read_only=not pdef.live)
    d.type = _PARAM_TYPES[pdef.kind].value
    if pdef.kind == 'double' and pdef.lo is not None:
        d.floating_point_range = [FloatingPointRange(from_value=float(pdef.lo),
                                                     to_value=float(pdef.hi), step=0.0)]
    elif pdef.kind == 'int' and pdef.lo is not None:
        d.integer_range = [IntegerRange(from_value=int(pdef.lo), to_value=int(pdef.hi), step=1)]
    return d


def _plain(value):
    """Parameter value as plain Python (lists instead of array.array)."""
    if isinstance(value, (str, bool, int, float)) or value is None:
        return value
    return list(value)


def _coerce(param, kind):
    """An int given for a double (``length: 1``), ints for a double array, an integral double
    for an int: converted, so that params files and ``ros2 param set`` need no ``.0``."""
    t, v = param.type_, param.value
    if kind == 'double' and t == Parameter.Type.INTEGER:
        return Parameter(param.name, Parameter.Type.DOUBLE, float(v))
    if kind in ('double3', 'double4') and t == Parameter.Type.INTEGER_ARRAY:
        return Parameter(param.name, Parameter.Type.DOUBLE_ARRAY, [float(x) for x in v])
    if kind == 'int' and t == Parameter.Type.DOUBLE and float(v).is_integer():
        return Parameter(param.name, Parameter.Type.INTEGER, int(v))
    return param


class _Window:
    """Statistics between two diagnostics messages."""

    def __init__(self):
        self.ticks = 0
        self.solve = []
        self.tick_wall = []
        self.lateness = 0.0
        self.max_gap = 0.0
        self.steps = 0
        self.accepted = 0
        self.guard_resets = 0
        self.dropped_time = 0.0
        self.wall0 = time.monotonic()


class PonytailNode(Node):
    """Simulates the configured chains hanging from the head given on ``head_pose``.

    ``node_name``/``context``/``**kwargs`` go to ``rclpy.node.Node`` (e.g. ``namespace``,
    ``parameter_overrides``, ``cli_args``). Raises ``ParameterError`` (or rclpy's
    ``ParameterException``) if the parameters are invalid at start-up.
    """

    def __init__(self, node_name='ponytail', *, context=None, **kwargs):
        super().__init__(node_name, context=context, **kwargs)
        self._declare_parameters()
        self._values = {p.name: _plain(p.value) for p in self.get_parameters(self._param_names)}
        self._scene = check_values(self._values, self._chains)
        self.runner = ChainRunner(self._scene, build_runner_settings(self._values))
        self.runner.on_drop = self._on_drop
        self._stamp_source = self._values['stamp_source']

        self._chain_msgs = self._make_chain_messages(self._scene)
        if len(self._chains) == 1:
            topics = ['segment_poses']
        else:
            topics = [f'segment_poses/{c}' for c in self._chains]
        self._pose_pubs = [self.create_publisher(PoseArray, tp, OUTPUT_QOS) for tp in topics]
        self._marker_pub = self.create_publisher(MarkerArray, 'segment_markers', OUTPUT_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._head_sub = self.create_subscription(PoseStamped, 'head_pose', self._on_head_pose,
                                                  INPUT_QOS)
        self._timer = self.create_timer(1.0 / self._values['rate'], self._on_tick)
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._diag_timer = self.create_timer(self._values['diagnostics_period'],
                                             self._on_diagnostics, clock=self._steady)
        self._log_times = {}
        self._window = _Window()
        self._dropped_at_diag = dict(self.runner.dropped)
        self._last_marker_t = None
        self._send_delete_all = False
        self._published = 0
        #: Optional ``hook(output, wall_start, wall_poses_published, wall_end)`` (perf_counter
        #: times) called after every published tick (benchmarks, tests).
        self.tick_hook = None
        self.add_pre_set_parameters_callback(self._pre_set_parameters)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._post_set_parameters)
        # Recording (record_path): the publishers are wrapped to record what they publish.
        self._recorder = None
        if self._values['record_path']:
            from ponytail_ros.recording.recorder import RunRecorder
            self._recorder = RunRecorder.for_node(
                self, self._values['record_path'], self._chains, self._head_sub,
                self._pose_pubs, self._marker_pub, self._diag_pub)
        if self._recorder is not None:
            self._pose_pubs = [self._recorder.recording(p) for p in self._pose_pubs]
            self._marker_pub = self._recorder.recording(self._marker_pub)
            self._diag_pub = self._recorder.recording(self._diag_pub)
        self.get_logger().info(
            f'Simulating {len(self._chains)} chain(s) {self._chains} '
            f'({self._scene.n_segments} segments) at {self._values["rate"]:g} Hz; '
            f'head_pose -> {", ".join(topics)}, segment_markers')

    # -- parameters ------------------------------------------------------------------------
    def _declare(self, pdef, name, default):
        override = self._parameter_overrides.get(name)
        if override is not None:
            self._parameter_overrides[name] = _coerce(override, pdef.kind)
        self.declare_parameter(name, default, _descriptor(pdef))
        self._param_names.append(name)

    def _declare_parameters(self):
        self._param_names = []
        for pdef in GLOBAL_PARAMS:
            self._declare(pdef, pdef.name, pdef.default)
            if pdef.name == 'chains':
                self._chains = [str(c) for c in self.get_parameter('chains').value]
                check_chain_names(self._chains)
        for i, chain in enumerate(self._chains):
            for pdef in CHAIN_PARAMS:
                default = pdef.default
                if pdef.name == 'color':
                    default = list(DEFAULT_COLORS[i % len(DEFAULT_COLORS)])
                self._declare(pdef, chain_param_name(chain, pdef.name), default)

    def _pre_set_parameters(self, params):
        out = []
        for p in params:
            pdef = definition(p.name, self._chains)
            out.append(_coerce(p, pdef.kind) if pdef is not None else p)
        return out

    def _on_set_parameters(self, params):
        changed = {}
        for p in params:
            if definition(p.name, self._chains) is not None:
                changed[p.name] = _plain(p.value)
        if not changed:
            return SetParametersResult(successful=True)
        values = dict(self._values)
        values.update(changed)
        try:
            check_values(values, self._chains, changed)
        except ParameterError as err:
            self.get_logger().warning(f'Rejected parameter change: {err}')
            return SetParametersResult(successful=False, reason=str(err))
        return SetParametersResult(successful=True)

    def _post_set_parameters(self, params):
        changed = {p.name: _plain(p.value) for p in params
                   if definition(p.name, self._chains) is not None}
        if not changed:
            return
        self._values.update(changed)
        if self._recorder is not None:
            self._recorder.parameters_changed(changed, self.get_clock().now().nanoseconds)
        scene = check_values(self._values, self._chains)
        if scene != self._scene:
            self.runner.set_scene(scene)
            self._scene = scene
        settings = build_runner_settings(self._values)
        self.runner.update_settings(
            **{k: getattr(settings, k) for k in (
                'interpolation_delay', 'interpolation_delay_periods', 'latency_compensation',
                'teleport_distance', 'teleport_angle', 'stale_timeout',
                'window', 'degree', 'max_extrapolation', 'max_gap', 'quat_tolerance')})
        if 'rate' in changed:
            self._timer.timer_period_ns = int(round(1e9 / self._values['rate']))
        for i, c in enumerate(self._chains):
            if chain_param_name(c, 'color') in changed:
                self._chain_msgs[i].set_color(self._values[chain_param_name(c, 'color')])
        self.get_logger().info('Parameters changed: ' + ', '.join(
            f'{k}={v}' for k, v in sorted(changed.items())))

    # -- input -----------------------------------------------------------------------------
    def _on_head_pose(self, msg):
        now_ns = self.get_clock().now().nanoseconds  # the receive time (recorded as log time)
        if self._recorder is not None:
            self._recorder.head(msg, now_ns)
        st = msg.header.stamp
        if self._stamp_source == 'receive' or (st.sec == 0 and st.nanosec == 0):
            t = now_ns * 1e-9
        else:
            t = st.sec + st.nanosec * 1e-9
        p, q = msg.pose.position, msg.pose.orientation
        self.runner.push(t, (p.x, p.y, p.z), (q.x, q.y, q.z, q.w), msg.header.frame_id)

    def _on_drop(self, reason, t):
        self._log_throttled(
            'drop:' + reason, 2.0, 'warning',
            f'Dropped a head pose ({reason}, stamp {t}); {self.runner.dropped[reason]} dropped '
            f'for this reason so far')

    def _log_throttled(self, key, period, level, text):
        now = time.monotonic()
        last = self._log_times.get(key)
        if last is not None and now - last < period:
            return
        self._log_times[key] = now
        # One call site per severity: rclpy refuses a severity change at one call site.
        logger = self.get_logger()
        if level == 'info':
            logger.info(text)
        elif level == 'error':
            logger.error(text)
        else:
            logger.warning(text)

    # -- the tick --------------------------------------------------------------------------
    def _make_chain_messages(self, scene):
        return [ChainMessages(c.name, c.lengths(), c.radius) for c in scene.chains]

    def _on_tick(self, info: TimerInfo = None) -> None:
        wall0 = time.perf_counter()
        now = self.get_clock().now()
        if now.nanoseconds == 0:          # sim time before the first /clock
            return
        t = now.nanoseconds * 1e-9
        win = self._window
        if info is not None:
            late = (info.actual_call_time.nanoseconds - info.expected_call_time.nanoseconds)
            win.lateness = max(win.lateness, late * 1e-9)
        out = self.runner.tick(t)
        wall1 = time.perf_counter()
        if out is None:
            self._log_throttled('no_head', 5.0, 'warning',
                                f'No head pose received on {self._head_sub.topic_name} yet: '
                                f'nothing is published')
            return
        scene = self.runner.scene
        if any(m.n != c.n_segments or m.radius != c.radius or
               not np.array_equal(m.lengths, c.lengths())
               for m, c in zip(self._chain_msgs, scene.chains)):
            self._chain_msgs = self._make_chain_messages(scene)
            for i, c in enumerate(self._chains):
                self._chain_msgs[i].set_color(self._values[chain_param_name(c, 'color')])
        frame = self._values['frame_id'] or out.frame_id
        stamp = now.to_msg()
        model = self.runner.sim.model
        for c, (pub, cm) in enumerate(zip(self._pose_pubs, self._chain_msgs)):
            sl = model.chain_slice(c)
            pub.publish(cm.fill_poses(out.origins[sl], out.orientations[sl], frame, stamp))
        self._published += 1
        wall_published = time.perf_counter()
        self._maybe_publish_markers(out, frame, stamp)

        rep = out.report
        win.ticks += 1
        win.solve.append(wall1 - wall0)
        win.tick_wall.append(time.perf_counter() - wall0)
        win.max_gap = max(win.max_gap, rep.max_gap)
        win.steps += rep.steps
        win.accepted += out.accepted
        win.dropped_time += rep.dropped_time
        if out.reset_reason is not None:
            if out.reset_reason == 'guard':
                win.guard_resets += 1
            level = 'warning' if out.reset_reason in ('guard', 'clock_backwards') else 'info'
            self._log_throttled('reset:' + out.reset_reason, 2.0, level,
                                f'Chain reset at rest ({self.runner.last_reset})')
        if out.head_stale:
            self._log_throttled('stale', 5.0, 'warning',
                                'Head pose stale (no pose accepted for over '
                                f'{self.runner.settings.stale_timeout:g} s): holding the last '
                                'pose')
        if rep.dropped_time > 0.0:
            self._log_throttled('dropped_time', 5.0, 'warning',
                                f'Dropped {rep.dropped_time:.3f} s of simulation time '
                                f'(solver.max_steps_per_call reached)')
        if self.tick_hook is not None:
            self.tick_hook(out, wall0, wall_published, time.perf_counter())

    def _maybe_publish_markers(self, out, frame, stamp):
        style = self._values['markers.style']
        period = 1.0 / self._values['markers.rate']
        if self._last_marker_t is not None and out.t - self._last_marker_t < 0.999 * period \
                and out.t >= self._last_marker_t:
            return
        self._last_marker_t = out.t
        model = self.runner.sim.model
        array = MarkerArray()
        delete = False
        markers = []
        for c, cm in enumerate(self._chain_msgs):
            sl = model.chain_slice(c)
            color = self._values[chain_param_name(self._chains[c], 'color')]
            ms, changed = cm.markers(out.origins[sl], out.orientations[sl], style, color,
                                     frame, stamp)
            delete = delete or changed
            markers.extend(ms)
        if delete:
            markers.insert(0, delete_all_marker(frame, stamp))
        if not markers:
            return
        array.markers = markers
        self._marker_pub.publish(array)

    # -- diagnostics -----------------------------------------------------------------------
    def diagnostic_status(self):
        """The node's ``DiagnosticStatus`` over the window since the last call (resets it)."""
        win, self._window = self._window, _Window()
        r = self.runner
        wall = max(time.monotonic() - win.wall0, 1e-9)
        t = self.get_clock().now().nanoseconds * 1e-9
        dropped_now = dict(r.dropped)
        dropped_window = {k: dropped_now[k] - self._dropped_at_diag.get(k, 0)
                          for k in DROP_REASONS}
        self._dropped_at_diag = dropped_now
        solve = np.array(win.solve) if win.solve else np.zeros(1)
        age = r.head_age(t)
        if not r.has_head:
            head = 'none'
        elif r.head_stale(t):
            head = 'stale'
        else:
            head = 'ok'

        level, problems = DiagnosticStatus.OK, []

        def flag(lvl, text):
            nonlocal level
            level = max(level, lvl)
            problems.append(text)
        if head == 'none':
            flag(DiagnosticStatus.WARN, 'no head pose received')
        elif head == 'stale':
            flag(DiagnosticStatus.WARN, 'head pose stale')
        elif age is not None and abs(age) > max(r.settings.stale_timeout, 0.5):
            flag(DiagnosticStatus.WARN, f'head pose stamps {age:+.3g} s off the node clock '
                                        f'(clocks differ? use_sim_time / stamp_source)')
        if sum(dropped_window.values()):
            flag(DiagnosticStatus.WARN, f'{sum(dropped_window.values())} head poses dropped')
        if win.dropped_time > 0.0:
            flag(DiagnosticStatus.WARN, f'{win.dropped_time:.3g} s of simulation dropped')
        if win.guard_resets:
            flag(DiagnosticStatus.ERROR, f'{win.guard_resets} blow-up resets')

        kv = [
            ('head', head),
            ('head frame', r.frame_id or ''),
            ('head input age (s)', 'n/a' if age is None else f'{age:.4f}'),
            ('head poses accepted per s', f'{win.accepted / wall:.1f}'),
            ('head poses accepted', str(r.accepted_total)),
            ('ticks per s', f'{win.ticks / wall:.1f}'),
            ('solve time mean (ms)', f'{1e3 * float(np.mean(solve)):.3f}'),
            ('solve time max (ms)', f'{1e3 * float(np.max(solve)):.3f}'),
            ('tick time max (ms)', f'{1e3 * max(win.tick_wall, default=0.0):.3f}'),
            ('timer lateness max (ms)', f'{1e3 * win.lateness:.3f}'),
            ('steps per tick', f'{win.steps / max(win.ticks, 1):.2f}'),
            ('joint gap max (m)', f'{win.max_gap:.3g}'),
            ('interpolation delay (s)', f'{r.delay:.4f}'),
            ('dropped inputs', str(sum(dropped_now.values()))),
        ]
        kv += [(f'dropped inputs: {k}', str(dropped_now[k])) for k in DROP_REASONS]
        kv += [('resets', str(sum(r.resets.values())))]
        kv += [(f'resets: {k}', str(r.resets[k])) for k in RESET_REASONS]
        kv += [('last reset', r.last_reset or ''),
               ('head history restarts', str(r.history_restarts)),
               ('dropped time (s)', f'{r.dropped_time_total:.4f}'),
               ('segments', str(self._scene.n_segments))]
        fqn = self.get_fully_qualified_name()
        return DiagnosticStatus(
            level=level, name=f'ponytail: {fqn}', hardware_id=fqn,
            message='; '.join(problems) if problems else 'ok',
            values=[KeyValue(key=k, value=v) for k, v in kv])

    def _on_diagnostics(self):
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [self.diagnostic_status()]
        self._diag_pub.publish(msg)

    def destroy_node(self):
        """Finalise the recording (if any), then destroy the node."""
        recorder, self._recorder = getattr(self, '_recorder', None), None
        if recorder is not None:
            recorder.close()
        return super().destroy_node()


def main(args=None):
    """Entry point of ``ponytail_node``; returns the exit code."""
    return run_node('ponytail_node', PonytailNode, args, bad_input=(ParameterError, ParameterException))


if __name__ == '__main__':
    sys.exit(main())
