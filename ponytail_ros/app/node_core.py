"""What the ponytail node does with a head pose, a frame's pose, a tick, a parameter change and
a diagnostics period, as messages and without an rclpy node: ``PonytailNode`` publishes what
``NodeCore`` returns, ``ponytail_replay`` records it. One implementation, so a replay is the
node's run.

Times are integer ns of the node clock (the recorded clock in a replay); the runner gets them
relative to its origin (``ChainRunner.seconds``), so nothing depends on the clock's epoch. The
per-tick logic (input checks, head estimation, stepping) is ``ChainRunner``; the parameter
table is ``parameters.py``; messages are built by ``messages.py``.
"""
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from .messages import (
    DELETE_ALL,
    IDENTITY_POSE,
    ChainMessages,
    ChainsMarkerNumbers,
    ColliderMarkers,
    SegmentMarkers,
    SegmentPoses,
)
from .parameters import (
    build_runner_settings,
    chain_param_name,
    check_names,
    check_values,
    collider_names,
    definition,
    frame_names,
    frame_topics,
)
from .runner import DROP_REASONS, RESET_REASONS, ChainRunner, TickOutput
from .tf_input import TFInput
from .wire import MarkerArrayLayout

__all__ = ['NodeCore', 'NodeTick', 'LIVE_SETTINGS', 'MIN_RATE_PERIODS', 'OVERLOAD_FRACTION',
           'OVERLOADED', 'tick_rate', 'time_msg']

#: ``RunnerSettings`` fields that follow their parameters live.
LIVE_SETTINGS = ('interpolation_delay', 'interpolation_delay_periods', 'latency_compensation',
                 'teleport_distance', 'teleport_angle', 'stale_timeout', 'window', 'degree',
                 'min_samples', 'max_extrapolation', 'max_gap', 'quat_tolerance')

#: Diagnostics keys of wall-clock timing (the node measures them; a replay has none).
TIMING_KEYS = ('solve time mean (ms)', 'solve time max (ms)', 'integrate time mean (ms)',
               'contact time mean (ms)', 'contact rows time mean (ms)',
               'contact positions time mean (ms)', 'contact velocities time mean (ms)',
               'tick time p99 (ms)', 'tick time max (ms)', 'timer lateness max (ms)')


#: A window whose tick calls came at less than this fraction of ``rate`` (on the node's clock)
#: says the node is overloaded: each tick takes longer than its period, so the timer falls
#: behind (each late tick then takes the steps of the time elapsed, and later still).
OVERLOAD_FRACTION = 0.9
#: The start of that warning's text (the node says it on its terminal too, with the fix).
OVERLOADED = 'overloaded'
#: A runner notice (``on_notice``) of one kind is said at most once per this much node clock.
NOTICE_PERIOD_NS = 10_000_000_000
#: Tick calls spanning fewer nominal periods than this say nothing about the rate (one late
#: timer callback among a few would read as a fall).
MIN_RATE_PERIODS = 10


def tick_rate(win: '_Window', rate: float) -> float | None:
    """The rate (Hz, node clock) of a window's tick calls, None over less than
    ``MIN_RATE_PERIODS`` periods of the nominal ``rate`` (Hz)."""
    span = (win.last_call_ns - win.first_call_ns) * 1e-9
    if win.calls < 2 or span * rate < MIN_RATE_PERIODS:
        return None
    return (win.calls - 1) / span


def time_msg(t_ns: int) -> Time:
    """``builtin_interfaces/Time`` of ``t_ns`` (as ``rclpy.time.Time.to_msg``)."""
    return Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)


@dataclass
class NodeTick:
    """The messages of one tick: ``segments[i]`` is chain ``i``'s ``SegmentPoses`` (its
    ``PoseArray`` as CDR bytes, ``.cdr``); ``segment_markers`` the ``SegmentMarkers`` (the
    ``MarkerArray`` as CDR) when markers are due (``markers.rate``), else None. The node and
    the recorder use the bytes; the message objects (``poses``, ``markers``) are built when
    first asked for."""

    output: TickOutput
    frame_id: str
    segments: list[SegmentPoses]
    segment_markers: SegmentMarkers | None

    @property
    def poses(self) -> list[Any]:
        """The ``PoseArray`` message per chain."""
        return [s.message() for s in self.segments]

    @property
    def markers(self) -> Any | None:
        """The ``MarkerArray`` message, or None (no markers this tick)."""
        return None if self.segment_markers is None else self.segment_markers.message()


@dataclass
class _Window:
    """Counts between two diagnostics messages."""

    t0_ns: int = 0
    ticks: int = 0
    #: Tick calls (published or not) and the node-clock times of the first and last: the rate
    #: the node's timer achieved (``OVERLOAD_FRACTION``).
    calls: int = 0
    first_call_ns: int = 0
    last_call_ns: int = 0
    max_gap: float = 0.0
    steps: int = 0
    accepted: int = 0
    guard_resets: int = 0
    dropped_time: float = 0.0
    extra: dict = field(default_factory=dict)


class NodeCore:
    """The node's state and behaviour over a full parameter value set ``values`` (name ->
    plain value, as ``recording.params.complete_values`` gives or the node declares).

    Raises ``ParameterError`` (naming the parameter) if the values are invalid.
    """

    def __init__(self, values: Mapping[str, Any]):
        self.values = dict(values)
        self.chains = [str(c) for c in self.values['chains']]
        self.colliders = collider_names(self.values)
        #: Extra kinematic frames (bodies 1..F) and their topics as configured (relative).
        self.frames = frame_names(self.values)
        check_names(self.chains, self.colliders, self.frames)
        self.scene = check_values(self.values, self.chains)
        self.frame_topics = frame_topics(self.values)
        #: The one ``PoseArray`` topic of all the frames' poses, or '' (a topic each).
        self.frames_topic = str(self.values.get('frames_topic') or '')
        self.runner = ChainRunner(self.scene, build_runner_settings(self.values), self.frames)
        self.stamp_source = self.values['stamp_source']
        #: The head (and frames) from TF (``head_frame`` set), else None.
        self.tf: TFInput | None = (TFInput(self.values) if self.values.get('head_frame')
                                      else None)
        self._chain_msgs = self._make_chain_messages(self.scene)
        self._color_names = [chain_param_name(c, 'color') for c in self.chains]
        self._slices_model: Any = None
        self._slices: list[slice] = []
        self._msgs_scene = None     # the scene the chain messages were last checked against
        self._collider_markers = ColliderMarkers()
        self._marker_key: Any = None
        self._marker_layout: MarkerArrayLayout | None = None
        self._numbers: Any = None
        self._numbers_for: Any = None
        self._last_marker_t = None
        self.published = 0
        self.window = _Window()
        #: Called as ``on_notice(key, text)`` with what the user should read on the terminal
        #: (a sparse head stream, a gap in it: ``ChainRunner.on_notice``), throttled per key.
        self.on_notice: Callable[[str, str], None] | None = None
        self._notices: dict = {}
        self._clock_ns: int | None = None
        self.runner.on_notice = self._runner_notice
        self._dropped_at_diag = dict(self.runner.dropped)

    def is_parameter(self, name: str) -> bool:
        return definition(name, self.chains, self.colliders, self.frames) is not None

    def definition(self, name: str):
        """The ``ParamDef`` of one of this node's parameters (None if not one)."""
        return definition(name, self.chains, self.colliders, self.frames)

    # -- input ---------------------------------------------------------------------------------
    def _stamp(self, stamp, receive_ns):
        """The runner time (s) of a pose: its stamp (or receive time) as integer ns, made
        relative to the run's origin before it becomes a float (``ChainRunner.seconds``)."""
        if self.stamp_source == 'receive' or (stamp.sec == 0 and stamp.nanosec == 0):
            return self.runner.seconds(receive_ns)
        return self.runner.seconds(stamp.sec * 1_000_000_000 + stamp.nanosec)

    def _runner_notice(self, key: str, text: str) -> None:
        """A runner notice (a sparse head, a gap) passed to ``on_notice``, a key said at most
        once per ``NOTICE_PERIOD_NS`` of the node clock (the later ones counted into the
        next)."""
        t_ns = self._clock_ns
        last, held = self._notices.get(key, (None, 0))
        if last is not None and t_ns is not None and t_ns - last < NOTICE_PERIOD_NS:
            self._notices[key] = (last, held + 1)
            return
        self._notices[key] = (t_ns, 0)
        if held:
            text += f' ({held} more since the last such notice)'
        if self.on_notice is not None:
            self.on_notice(key, text)

    def push_head(self, stamp, receive_ns: int, position, orientation, frame_id: str) -> None:
        """Queue a head pose: ``stamp`` its ``header.stamp`` (a zero stamp, or ``stamp_source:
        receive``, uses the receive time), ``position``/``orientation`` tuples."""
        self.runner.push(self._stamp(stamp, receive_ns), position, orientation, frame_id)

    def push_frame(self, i: int, stamp, receive_ns: int, position, orientation,
                   frame_id: str) -> None:
        """Queue a pose of frame ``i`` (``frames[i]``), as :meth:`push_head`."""
        self.runner.push_frame(i, self._stamp(stamp, receive_ns), position, orientation,
                               frame_id)

    def push_frames(self, stamp, receive_ns: int, poses, frame_id: str) -> None:
        """Queue one pose of every frame from one ``PoseArray`` (``frames_topic``): ``poses``
        ``(F, 7)`` (x, y, z, qx, qy, qz, qw), row i the pose of ``frames[i]``, each checked as
        :meth:`push_frame`'s. Another count than F drops the message (``frames_count``)."""
        self.runner.push_frames(self._stamp(stamp, receive_ns), poses, frame_id)

    # -- the tick ------------------------------------------------------------------------------
    def _make_chain_messages(self, scene):
        msgs = [ChainMessages(c.name, c.lengths(), c.radius) for c in scene.chains]
        for m, name in zip(msgs, self.chains, strict=True):
            m.set_color(self.values[chain_param_name(name, 'color')])
        return msgs

    def tick(self, t_ns: int) -> NodeTick | None:
        """Advance to ``t_ns``; the tick's messages, or None (no clock yet, no head pose yet, or
        no pose yet of a frame the scene uses)."""
        if t_ns == 0:                    # sim time before the first /clock
            return None
        win = self.window
        if win.calls == 0:
            win.first_call_ns = t_ns
        win.last_call_ns = t_ns
        win.calls += 1
        self._clock_ns = t_ns
        runner = self.runner
        if runner.origin_ns is None and runner.missing_inputs():
            # No input yet (a pose sets the origin): nothing to simulate, and the origin stays
            # the first input's, as in a replay of this run (which sees no such tick).
            return None
        out = runner.tick(runner.seconds(t_ns))
        if out is None:
            return None
        scene = self.runner.scene
        if scene is not self._msgs_scene:     # (a Scene is frozen: the same one, the same chains)
            if any(m.n != c.n_segments or m.radius != c.radius or
                   not np.array_equal(m.lengths, c.lengths())
                   for m, c in zip(self._chain_msgs, scene.chains, strict=True)):
                self._chain_msgs = self._make_chain_messages(scene)
            self._msgs_scene = scene
        # No frame set and no head pose frame (an empty header.frame_id, or chains hanging
        # from the world only): fixed_frame.
        values = self.values
        frame = values['frame_id'] or out.frame_id or values.get('fixed_frame', 'world')
        stamp_ns = self.stamp_ns(t_ns, out)
        slices = self._chain_slices()
        origins, orientations = out.origins, out.orientations
        poses = [cm.segment_poses(origins[sl], orientations[sl], frame, stamp_ns)
                 for sl, cm in zip(slices, self._chain_msgs, strict=True)]
        self.published += 1
        win, rep = self.window, out.report
        win.ticks += 1
        win.max_gap = max(win.max_gap, rep.max_gap)
        win.steps += rep.steps
        win.accepted += out.accepted
        win.dropped_time += rep.dropped_time
        if out.reset_reason == 'guard':
            win.guard_resets += 1
        return NodeTick(out, frame, poses, self._markers(out, frame, stamp_ns))

    def stamp_ns(self, t_ns: int, out: TickOutput) -> int:
        """The outputs' stamp (ns) of the tick at ``t_ns``: the tick time (``output_stamp:
        tick``) or the time of the published chain state (``simulated``), in whole ns of the
        tick time so that a zero delay gives the tick's own stamp."""
        if self.values['output_stamp'] != 'simulated':
            return t_ns
        return t_ns - int(round((out.t - out.t_state) * 1e9))

    def _chain_slices(self):
        """Each chain's rows in the tick's arrays (the simulator's model's, kept while it is
        the same model)."""
        model = self.runner.sim.model
        if model is not self._slices_model:
            self._slices = [model.chain_slice(c) for c in range(len(self._chain_msgs))]
            self._slices_model = model
        return self._slices

    def _markers(self, out, frame, stamp_ns):
        values = self.values
        style = values['markers.style']
        period = 1.0 / values['markers.rate']
        if self._last_marker_t is not None and out.t - self._last_marker_t < 0.999 * period \
                and out.t >= self._last_marker_t:
            return None
        self._last_marker_t = out.t
        delete = False
        chain_specs = []
        for cm, color_name in zip(self._chain_msgs, self._color_names, strict=True):
            specs, changed = cm.marker_specs(style, values[color_name])
            delete = delete or changed
            chain_specs.append(specs)
        parts = []           # (poses, points) in marker order
        if style != 'off':
            # Every chain's numbers in one pass (the chains' rows of the tick's arrays).
            numbers = self._chains_numbers()
            parts.append(numbers.numbers(out.origins[:numbers.n], out.orientations[:numbers.n],
                                         style))
        collider_specs, *part, changed = self._collider_markers.markers(
            self.runner.scene.colliders,
            self.runner.bodies_at(out.t_state if self.values['output_stamp'] == 'simulated'
                                  else out.t), style)
        delete = delete or changed
        parts.append(part)
        # (the same tuples while nothing changes: the layout is kept)
        specs = (((DELETE_ALL,),) if delete else ()) + (*chain_specs, collider_specs)
        if delete:
            parts.insert(0, (IDENTITY_POSE[None], np.zeros((0, 3))))
        if not any(specs):
            return None
        if (frame, specs) != self._marker_key:
            self._marker_key = (frame, specs)
            self._marker_layout = MarkerArrayLayout(frame, [s for ss in specs for s in ss])
        return SegmentMarkers(self._marker_layout, stamp_ns,
                              np.concatenate([p[0] for p in parts]),
                              np.concatenate([p[1] for p in parts]))

    def _chains_numbers(self):
        """The chains' ``ChainsMarkerNumbers`` (kept while the chains' messages are the same;
        the model's chains are laid end to end in chain order)."""
        if self._numbers_for is not self._chain_msgs:
            self._numbers = ChainsMarkerNumbers([cm.n for cm in self._chain_msgs],
                                                np.concatenate([cm.lengths
                                                                for cm in self._chain_msgs]))
            self._numbers_for = self._chain_msgs
        return self._numbers

    # -- parameters ----------------------------------------------------------------------------
    def ours(self, changed: Mapping[str, Any]) -> dict:
        """The entries of ``changed`` that are this node's parameters."""
        return {k: v for k, v in changed.items() if self.is_parameter(k)}

    def check_change(self, changed: Mapping[str, Any]) -> None:
        """Raise ``ParameterError`` (naming the parameter) if ``changed`` is not acceptable; the
        running values are untouched either way."""
        values = dict(self.values)
        values.update(changed)
        check_values(values, self.chains, changed)

    def apply_change(self, changed: Mapping[str, Any]) -> None:
        """Apply an accepted change: tunables at the next tick, structural ones by a rebuild
        (``ChainRunner.set_scene``), input settings and marker colours at once."""
        self.values.update(changed)
        scene = check_values(self.values, self.chains)
        if scene != self.scene:
            self.runner.set_scene(scene)
            self.scene = scene
        settings = build_runner_settings(self.values)
        self.runner.update_settings(**{k: getattr(settings, k) for k in LIVE_SETTINGS})
        for i, c in enumerate(self.chains):
            if chain_param_name(c, 'color') in changed:
                self._chain_msgs[i].set_color(self.values[chain_param_name(c, 'color')])

    # -- diagnostics ---------------------------------------------------------------------------
    def diagnostic_status(self, t_ns: int, span: float, name: str,
                          timing: Mapping[str, str] | None = None) -> DiagnosticStatus:
        """The status over the window since the last call (which it starts anew).

        ``span``: the window's length, s (wall time in the node, recorded time in a replay);
        ``name``: the node's fully qualified name; ``timing``: values of ``TIMING_KEYS``
        (``'n/a (replay)'`` when None).
        """
        win, self.window = self.window, _Window(t0_ns=t_ns)
        r = self.runner
        span = max(span, 1e-9)
        t = r.seconds(t_ns)
        dropped_now = dict(r.dropped)
        dropped_window = sum(dropped_now[k] - self._dropped_at_diag.get(k, 0)
                             for k in DROP_REASONS)
        self._dropped_at_diag = dropped_now
        age = r.head_age(t)
        # The problems in the order the message says them: the inputs, then the run.
        problems = _Problems()
        head = self._head_input(t, age, problems)
        frames = self._frame_inputs(t, problems)
        tf_kv = self._tf_input(problems)
        rate = float(self.values['rate'])
        achieved = tick_rate(win, rate)
        self._run_problems(win, dropped_window, rate, achieved, problems)
        timing = timing or {k: 'n/a (replay)' for k in TIMING_KEYS}
        kv = (self._input_values(win, span, head, age, frames, tf_kv)
              + self._run_values(win, span, achieved, timing, dropped_now))
        return DiagnosticStatus(
            level=problems.level, name=f'ponytail: {name}', hardware_id=name,
            message='; '.join(problems.texts) if problems.texts else 'ok',
            values=[KeyValue(key=k, value=v) for k, v in kv])

    def _head_input(self, t: float, age: float | None, problems: '_Problems') -> str:
        """The head input's state at runner time ``t`` (``'none'``, ``'not needed'``,
        ``'stale'``, ``'ok'``); a missing or stale head the scene uses, or stamps ``age`` s
        off the node clock, flagged."""
        r = self.runner
        if not r.has_head:
            head = 'none' if r.needs_head else 'not needed'
        else:
            head = 'stale' if r.head_stale(t) else 'ok'
        if head == 'none':
            problems.flag(DiagnosticStatus.WARN, 'no head pose received')
        elif head == 'stale' and r.needs_head:
            problems.flag(DiagnosticStatus.WARN, 'head pose stale')
        elif head == 'ok' and age is not None and abs(age) > max(r.settings.stale_timeout, 0.5):
            problems.flag(DiagnosticStatus.WARN,
                          f'head pose stamps {age:+.3g} s off the node clock '
                          f'(clocks differ? use_sim_time / stamp_source)')
        return head

    def _frame_inputs(self, t: float, problems: '_Problems') -> list[tuple[str, str]]:
        """``(key, state)`` of every extra frame at runner time ``t`` (state as the head's); a
        missing or stale frame the scene uses flagged, with its topic."""
        r = self.runner
        frames = []
        for i, (f, topic) in enumerate(zip(self.frames, self.frame_topics, strict=True)):
            state = ('none' if not r.has_frame(i)
                     else 'stale' if r.frame_stale(i, t) else 'ok')
            frames.append((f'frame {f}', state))
            if r.needs_frame(i) and state == 'none':
                problems.flag(DiagnosticStatus.WARN, f'no pose received for frame {f} ({topic})')
            elif r.needs_frame(i) and state == 'stale':
                problems.flag(DiagnosticStatus.WARN, f'frame {f} pose stale ({topic})')
        return frames

    def _tf_input(self, problems: '_Problems') -> list[Any]:
        """The TF input's key-value pairs (none without one); its problems flagged."""
        if self.tf is None:
            return []
        tf_problems, tf_kv = self.tf.diagnostics()
        for text in tf_problems:
            problems.flag(DiagnosticStatus.WARN, text)
        return tf_kv

    def _run_problems(self, win: '_Window', dropped_window: int, rate: float,
                      achieved: float | None, problems: '_Problems') -> None:
        """Flag what went wrong in the run over the window: dropped inputs, dropped simulation
        time, blow-up resets (an error), tick calls falling behind ``rate`` (overload)."""
        if dropped_window:
            problems.flag(DiagnosticStatus.WARN,
                          f'{dropped_window} head poses dropped' if not self.frames
                          else f'{dropped_window} input poses dropped')
        if win.dropped_time > 0.0:
            problems.flag(DiagnosticStatus.WARN,
                          f'{win.dropped_time:.3g} s of simulation dropped')
        if win.guard_resets:
            problems.flag(DiagnosticStatus.ERROR, f'{win.guard_resets} blow-up resets')
        if achieved is not None and achieved < OVERLOAD_FRACTION * rate:
            problems.flag(DiagnosticStatus.WARN, f'{OVERLOADED}: ticking at {achieved:.1f} Hz '
                                                 f'of rate {rate:g} Hz')

    def _input_values(self, win: '_Window', span: float, head: str, age: float | None,
                      frames: list[tuple[str, str]], tf_kv: list[Any]) -> list[Any]:
        """The status's key-value pairs of the inputs (the head, the frames, TF)."""
        r = self.runner
        kv: list[Any] = [
            ('head', head),
            ('head frame', r.frame_id or ''),
            ('head input age (s)', 'n/a' if age is None else f'{age:.4f}'),
            ('head poses accepted per s', f'{win.accepted / span:.1f}'),
            ('head poses accepted', str(r.accepted_total)),
        ]
        for (key, state), n in zip(frames, r.frame_accepted_total, strict=True):
            kv += [(key, state), (f'{key} poses accepted', str(n))]
        return kv + tf_kv

    def _run_values(self, win: '_Window', span: float, achieved: float | None,
                    timing: Mapping[str, str], dropped_now: dict) -> list[Any]:
        """The status's key-value pairs of the run: ticks, timing, steps, drops, resets."""
        r = self.runner
        kv: list[Any] = [
            ('ticks per s', f'{win.ticks / span:.1f}'),
            ('tick rate (Hz)', 'n/a' if achieved is None else f'{achieved:.1f}'),
        ]
        kv += [(k, timing[k]) for k in TIMING_KEYS]
        kv += [
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
               ('segments', str(self.scene.n_segments)),
               ('colliders', str(len(self.scene.colliders)))]
        return kv


class _Problems:
    """What a diagnostics window found wrong: the worst level flagged (OK if none) and the
    texts, in the order flagged."""

    def __init__(self) -> None:
        self.level = DiagnosticStatus.OK
        self.texts: list[str] = []

    def flag(self, level, text: str) -> None:
        self.level = max(self.level, level)
        self.texts.append(text)
