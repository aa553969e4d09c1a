"""The offline replay: a recording re-simulated as fast as the machine allows, its output
written exactly as the node records a run (``ponytail_replay INPUT -o OUTPUT``; the options and
what they mean: ``cli.py``).

``replay()`` runs in named stages: the input and the options (``_open_input``), the parameters
(``_resolve_parameters``), the tick source (``_tick_mode``), the recorded live changes
(``_applies_events``), the extra frames' topics (``_frame_inputs``), the output
(``_open_output``), the loop over the input's messages in file or log-time order
(``_OfflineLoop``: look-ahead scheduling, nominal or recorded ticks) and the checks of what was
simulated (``_finish``). ``ReplayNode`` (``replay_node.py``) is the node.
"""
from __future__ import annotations

import json
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from ponytail_ros.app.messages import ReceivedPose, ReceivedPoses
from ponytail_ros.app.param_values import (
    IGNORED_NAMES,
    resolve_values,
    unknown_parameter_warnings,
    values_from_metadata,
    values_from_params_file,
)
from ponytail_ros.app.parameters import ParameterError, frame_names, frame_topics as topics_of
from ponytail_ros.app.tf_input import TF_STATIC_TOPIC, TF_TOPIC, tf_frames
from ponytail_ros.app.wire import tf_message_fields

from .bag import BagError
from .inputs import (
    ReplayError,
    ReplayInput,
    event_values,
    foreign_clock,
    head_stamps,
    recorded_value,
    used_frame_names,
)
from .recorder import FRAMES_TYPE, HEAD_TYPES, RECORDING_METADATA, RunLayout, RunRecorder, stamp_ns
from .replay_node import ReplayNode
from .tf import TFMESSAGE_TYPE

__all__ = ['replay', 'ReplayResult', 'Progress', 'LOOK_AHEAD_SAMPLES', 'LOOK_AHEAD_SPAN_NS',
           'LOOK_AHEAD_VALUES', 'LOOK_AHEAD_SPLINE_DEGREE']

#: Output chunks are cut by size only: the log-time/idle limit of BagWriter is set beyond any
#: replay, so that no wall-time effect changes the bytes.
_OUTPUT_CHUNK_DURATION_NS = 3600 * 1_000_000_000
#: Look-ahead replay: a tick runs once this many head poses logged after it, spanning at least
#: LOOK_AHEAD_SPAN_NS (the fit's window), have been pushed.
LOOK_AHEAD_SAMPLES = 16
LOOK_AHEAD_SPAN_NS = 60_000_000
#: Look-ahead replay: parameters replaced (no delay; a centred interpolating fit; honest stamps).
LOOK_AHEAD_VALUES = {'interpolation_delay': 0.0, 'interpolation_delay_periods': 0.0,
                     'output_stamp': 'simulated', 'head.degree': 9, 'head.min_samples': 10,
                     'head.window': 0.05, 'head.max_samples': 512}
#: Look-ahead replay: the head (and every frame) is estimated within its history by a global
#: interpolating spline of this (odd) degree through all the stored poses
#: (``core/head_spline.py``); the fit above only extrapolates past the newest pose.
LOOK_AHEAD_SPLINE_DEGREE = 11


@dataclass
class ReplayResult:
    """What a replay did."""

    output: Path
    ticks: int = 0
    head_samples: int = 0
    #: Poses of the extra frames pushed (all frames).
    frame_samples: int = 0
    parameter_changes: int = 0
    first_tick_ns: int | None = None
    last_tick_ns: int | None = None
    wall_seconds: float = 0.0
    #: CPU time of this process (all threads) during the replay, s.
    cpu_seconds: float = 0.0
    #: Wall time of the compiled step's calls (the ticks' ``integrate`` and ``contacts``
    #: timings), s: the physics' share of ``wall_seconds``; the rest is Python (head
    #: estimation, the per-tick bookkeeping, messages and the output).
    step_seconds: float = 0.0
    tick_mode: str = ''
    parameters_from: str = ''
    truncated: bool = False
    #: The signal that stopped the replay early ("SIGINT", "SIGTERM"), else None: the output
    #: is finalised and its metadata says it is partial.
    interrupted: str | None = None

    @property
    def sim_seconds(self) -> float:
        if self.first_tick_ns is None or self.last_tick_ns is None:
            return 0.0
        return (self.last_tick_ns - self.first_tick_ns) * 1e-9

    def interrupted_line(self, input_path) -> str:
        """The one terminal line of an interrupted replay."""
        upto = (f'up to t = {self.sim_seconds:.2f} s of its run ({self.ticks} ticks, last at '
                f'log time {self.last_tick_ns} ns)' if self.last_tick_ns is not None
                else 'with no tick')
        return (f'{input_path}: interrupted by {self.interrupted}: {self.output} is partial, '
                f'simulated {upto} (its metadata says so); rerun with --overwrite to replace '
                f'it')

    def summary(self, input_path) -> str:
        speed = self.sim_seconds / self.wall_seconds if self.wall_seconds > 0 else float('inf')
        return (f'{input_path} -> {self.output}: {self.ticks} ticks ({self.tick_mode}), '
                f'{self.head_samples} head poses, {self.sim_seconds:.2f} s simulated in '
                f'{self.wall_seconds:.2f} s ({speed:.1f}x real time; the compiled step '
                f'{self.step_seconds:.2f} s of it); parameters from {self.parameters_from}')


class Progress:
    """A progress bar with ETA on a terminal (stderr): tqdm when installed (the ``pypi`` extra),
    else one line of text. Called as ``progress(done_s, total_s_or_None, final=False)``."""

    def __init__(self, stream):
        self.stream = stream
        self.wall0 = time.perf_counter()
        self.last = 0.0
        self.bar = None
        self.done = 0.0
        try:
            import tqdm  # noqa: F401
            self.tqdm = True
        except ImportError:
            self.tqdm = False

    def __call__(self, done_s: float, total_s: float | None = None,
                 final: bool = False) -> None:
        if self.tqdm:
            self._tqdm(done_s, total_s, final)
        else:
            self._text(done_s, total_s, final)

    def _tqdm(self, done_s, total_s, final):
        from tqdm import tqdm
        if self.bar is None:
            self.bar = tqdm(total=round(total_s, 3) if total_s else None, file=self.stream,
                            unit='s', unit_scale=False, desc='replay (simulated s)',
                            dynamic_ncols=True, mininterval=0.1,
                            bar_format='{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} '
                                       '[{elapsed}<{remaining}, {rate_fmt}]' if total_s else None)
        done_s = max(done_s, self.done)
        if total_s:
            done_s = min(done_s, self.bar.total)
        self.bar.update(done_s - self.done)
        self.done = done_s
        if final:
            self.bar.close()

    def close(self):
        if self.bar is not None:
            self.bar.close()

    def _text(self, done_s, total_s, final):
        now = time.perf_counter()
        if not final and now - self.last < 0.1:
            return
        self.last = now
        wall = max(now - self.wall0, 1e-9)
        if total_s:
            frac = min(max(done_s / total_s, 0.0), 1.0)
            bar = '#' * int(30 * frac) + '-' * (30 - int(30 * frac))
            eta = wall * (1 - frac) / frac if frac > 0 else float('nan')
            text = f'[{bar}] {100 * frac:5.1f}% {done_s:7.1f}/{total_s:.1f} s, ETA {eta:.0f} s'
        else:
            text = f'{done_s:7.1f} s'
        self.stream.write(f'\r{text}  {done_s / wall:6.1f}x real time')
        if final:
            self.stream.write('\n')
        self.stream.flush()


def replay(input_path, output_path, *, params_file=None, head_topic: str | None = None,
           ticks: str = 'auto', overwrite: bool = False, look_ahead: bool = False,
           progress: Callable[..., None] | None = None,
           warn: Callable[[str], None] | None = None,
           stamp_source: str | None = None, tf: bool = True,
           tf_prefix: str | None = None, stop: Any = None,
           head_frame: str | None = None,
           fixed_frame: str | None = None) -> ReplayResult:
    """Re-simulate ``input_path`` into ``output_path`` (see the module docstring).

    Args:
        params_file: a node params file; None: the recorded parameters (or the package config).
        head_topic: the head topic; None: the recorded node's, else ``/head_pose`` (or the only
            head pose topic).
        ticks: ``'auto'``, ``'recorded'`` or ``'nominal'``.
        look_ahead: estimate the head from poses on both sides of each tick (module
            docstring).
        progress: called as ``progress(simulated_s_done, total_s_or_None, final=False)``
            during the replay (often: throttle it).
        warn: called with each warning (default: ignored).
        stamp_source: ``'header'`` or ``'receive'`` over the parameters' ``stamp_source``
            (head stamps on another clock than the log times need ``'receive'``).
        tf, tf_prefix: record the segments on ``/tf`` (``recorder.py``), their frames named
            ``<tf_prefix><chain>/<i>`` (default: the input's recorded prefix, else none).
        head_frame, fixed_frame: the parameters ``head_frame`` / ``fixed_frame`` over the
            params file's and the recorded ones (the head from the bag's ``/tf``).
        stop: checked between input messages (``interrupt.StopRequest``): once true (its
            ``name`` the signal's), the replay ends there, its output finalised and marked
            partial (``ReplayResult.interrupted``).

    Head stamps on another clock than the log times are refused (``foreign_clock``) unless
    header stamps were asked for explicitly (``stamp_source='header'``, or ``stamp_source``
    in the params file or in the node's recorded parameters): then only warned.

    Raises:
        ReplayError: bad input or options (one-line message naming the file and topic), a
            damaged input, or a run in which every head pose was dropped.
    """
    warn = warn or (lambda text: None)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    inp, output_path = _open_input(input_path, output_path, head_topic, ticks, warn)
    inp.stop = stop
    result = ReplayResult(output=output_path, truncated=inp.truncated)
    values, result.parameters_from = _resolve_parameters(inp, params_file, stamp_source,
                                                         look_ahead, warn)
    _frames_given(values, head_frame, fixed_frame)
    tf_head = inp.use_tf_head(values)
    stamps = [] if tf_head else head_stamps(inp)
    clock_note = foreign_clock(inp, stamps, values['stamp_source'])
    if clock_note:
        if not _header_stamps_asked(inp, params_file, stamp_source):
            raise ReplayError(clock_note)
        warn(clock_note)
    mode, tick_topic = _tick_mode(inp, ticks, values)
    result.tick_mode = mode
    events_topic = _events_topic(inp, params_file, warn)
    frames, frame_topics, frame_types = _frame_inputs(inp, values, warn)
    recorder = _open_output(
        inp, output_path, values, frames, frame_topics, frame_types, overwrite=overwrite, tf=tf,
        tf_prefix=tf_prefix,
        info={'source': 'ponytail_replay', 'input': inp.path.name, 'ticks': mode,
              'parameters_from': result.parameters_from,
              'head_estimation': 'look-ahead' if look_ahead else 'live'})
    node = ReplayNode(values, recorder, inp.head_type, frame_types,
                      # A node recording replays as the node ran (a zero stamp: the receive
                      # time); in another bag whose stamps are set, 0 is a stamp (sim clock).
                      zero_stamp_valid=(inp.layout is None
                                        and any(stamp for stamp, _ in stamps)))
    if look_ahead:
        _use_spline_estimators(node.runner)
    node.core.on_notice = lambda key, text: warn(f'{inp.path}: {text}')   # sparse head, gaps
    loop = _OfflineLoop(inp, node, result, values, mode=mode, tick_topic=tick_topic,
                        events_topic=events_topic, frame_topics=frame_topics,
                        frame_types=frame_types, look_ahead=look_ahead, progress=progress,
                        tf_head=tf_head)
    try:
        loop.run()
        if inp.stopped:
            result.interrupted = getattr(stop, 'name', '') or 'a stop request'
            recorder.mark_partial(f'interrupted by {result.interrupted}', result.last_tick_ns)
    except BagError as exc:
        recorder.close()
        output_path.unlink(missing_ok=True)
        raise ReplayError(str(exc)) from None
    finally:
        recorder.close()
    if tf_head:
        _tf_finish(inp, node, result, output_path, warn)
    _finish(inp, node, recorder, result, output_path, clock_note, warn)
    result.wall_seconds = time.perf_counter() - wall0
    result.cpu_seconds = time.process_time() - cpu0
    if progress is not None and result.last_tick_ns is not None and loop.t_start is not None:
        progress((result.last_tick_ns - loop.t_start) * 1e-9, loop.total_s, final=True)
    return result


def _header_stamps_asked(inp: ReplayInput, params_file, stamp_source) -> bool:
    """The user chose header stamps: ``--stamp-source header``, ``stamp_source`` in the
    ``--params`` file, or (no ``--params``) the node's own recorded choice."""
    if stamp_source is not None:
        return stamp_source == 'header'
    if params_file is not None:
        return 'stamp_source' in _given_values(inp, params_file)
    return inp.layout is not None and 'stamp_source' in (inp.recorded_parameters or {})


def _use_spline_estimators(runner) -> None:
    """Look-ahead: the runner's head and frame estimators replaced by
    ``SplineHeadEstimator``s with the same settings (before any pose is pushed)."""
    from ponytail_ros.core.head_spline import SplineHeadEstimator

    def spline(e):
        return SplineHeadEstimator(
            window=e.window, degree=e.degree, max_extrapolation=e.max_extrapolation,
            min_samples=e.min_samples, max_samples=e.max_samples, max_gap=e.max_gap,
            quat_tolerance=e.quat_tolerance, min_interval=e.min_interval,
            spline_degree=LOOK_AHEAD_SPLINE_DEGREE)
    runner.estimator = spline(runner.estimator)
    runner.frame_estimators = [spline(e) for e in runner.frame_estimators]


# -- the stages of replay() ----------------------------------------------------------------------


def _open_input(input_path, output_path, head_topic, ticks, warn) -> tuple[ReplayInput, Path]:
    """The input opened and the options that need no parameters checked (what the input
    itself says about it warned)."""
    if ticks not in ('auto', 'recorded', 'nominal'):
        raise ReplayError(f'--ticks must be auto, recorded or nominal, not {ticks!r}')
    # (the head topic is checked once the parameters say whether the head comes from TF,
    # when it can: the input has /tf)
    inp = ReplayInput(input_path, head_topic, head_required=False)
    if TF_TOPIC not in inp.topics:
        inp.require_head()
    output_path = Path(output_path)
    if output_path.exists() and output_path.resolve() == inp.path.resolve():
        raise ReplayError(f'{output_path}: the output would overwrite the input')
    if inp.note:
        warn(inp.note)
    for note in inp.notes:
        warn(note)
    if inp.truncated:
        warn(inp.truncated_warning())
    return inp, output_path


def _given_values(inp: ReplayInput, params_file) -> dict[str, Any]:
    """The values the user or the recording gave (not completed with defaults): the names in
    it are checked for typos."""
    if params_file is not None:
        try:
            return values_from_params_file(params_file, inp.node)
        except ParameterError:
            return {}
    if inp.recorded_parameters:
        return values_from_metadata(inp.recorded_parameters)
    return {}


def _resolve_parameters(inp: ReplayInput, params_file, stamp_source, look_ahead,
                        warn) -> tuple[dict[str, Any], str]:
    """The full parameter set of the replay and where it came from (``ReplayResult``'s
    ``parameters_from``): ``--params``, else the recorded parameters, else the package
    config; ``--stamp-source`` and ``--look-ahead`` over it."""
    try:
        values, source = resolve_values(params_file, inp.recorded_parameters, inp.node)
    except ParameterError as exc:
        origin = params_file or (f'{inp.path} (recorded parameters)'
                                 if inp.recorded_parameters else 'the default config')
        raise ReplayError(f'{origin}: invalid parameters: {exc}') from None
    for text in unknown_parameter_warnings(_given_values(inp, params_file)):
        warn(f'{params_file or inp.path}: {text}')
    if stamp_source is not None:
        if stamp_source not in ('header', 'receive'):
            raise ReplayError(f'--stamp-source must be header or receive, not {stamp_source!r}')
        values['stamp_source'] = stamp_source
    parameters_from = source if source == 'the recording' else Path(source).name
    if look_ahead:
        values = {**values, **LOOK_AHEAD_VALUES}
    return values, parameters_from


def _frames_given(values, head_frame: str | None, fixed_frame: str | None) -> None:
    """``--head-frame`` / ``--fixed-frame`` over the parameters' ``head_frame`` /
    ``fixed_frame``."""
    if fixed_frame is not None and not fixed_frame.strip('/'):
        raise ReplayError(f'--fixed-frame must name a frame (e.g. world), not {fixed_frame!r}')
    for name, value in (('head_frame', head_frame), ('fixed_frame', fixed_frame)):
        if value is not None:
            values[name] = value


def _tick_mode(inp: ReplayInput, ticks: str, values) -> tuple[str, str | None]:
    """``'recorded'`` (the node's own tick times, on the returned topic) or ``'nominal'``."""
    tick_topic = inp.tick_topic()
    recorded_rate = None
    if inp.recorded_parameters and 'rate' in inp.recorded_parameters:
        try:
            recorded_rate = float(json.loads(inp.recorded_parameters['rate']))
        except (TypeError, ValueError):
            recorded_rate = None
    if ticks == 'recorded':
        if tick_topic is None:
            raise ReplayError(f'{inp.path}: --ticks recorded needs a ponytail_node recording '
                              f'(with its segment_poses); this one has none')
        return 'recorded', tick_topic
    if ticks == 'auto' and tick_topic is not None and recorded_rate == values['rate']:
        return 'recorded', tick_topic
    return 'nominal', tick_topic


def _events_topic(inp: ReplayInput, params_file, warn) -> str | None:
    """The topic of the recorded live parameter changes to apply, or None: none recorded, or
    ``--params`` given (then they are not applied, with a warning if there are any)."""
    if inp.layout is None or (inp.topics.get(inp.layout.parameter_events_topic)
                              != 'rcl_interfaces/msg/ParameterEvent'):
        return None
    if params_file is not None:
        changes = inp.message_count(inp.layout.parameter_events_topic)
        if changes:
            warn(f'{inp.path}: its {changes} live parameter change(s) are not applied over '
                 f'--params')
        return None
    return inp.layout.parameter_events_topic


def _frame_inputs(inp: ReplayInput, values, warn) -> tuple[tuple, tuple, list[str]]:
    """The extra frames, their topics (the recorded node's, else as configured) and types; a
    frame the scene uses must have its topic in the input."""
    frames = tuple(frame_names(values))
    frame_topics = tuple(inp.frame_topic(f, t)
                         for f, t in zip(frames, topics_of(values), strict=True))
    used = used_frame_names(values)
    from_tf = tf_frames(values) if inp.use_tf_head(values) else {}
    for i, (f, topic) in enumerate(zip(frames, frame_topics, strict=True)):
        if i in from_tf:
            continue                    # its poses come from TF (recorded on its topic)
        if topic not in inp.topics:
            if f in used:
                raise ReplayError(f'{inp.path} has no topic {topic} (the poses of frame {f}, '
                                  f'which the scene uses)')
            warn(f'{inp.path} has no topic {topic}: frame {f} gets no poses')
        elif inp.topics[topic] not in (*HEAD_TYPES, FRAMES_TYPE):
            raise ReplayError(f'{inp.path}: topic {topic} (frame {f}) holds {inp.topics[topic]}, '
                              f'not a pose ({" or ".join((*HEAD_TYPES, FRAMES_TYPE))})')
    return frames, frame_topics, [HEAD_TYPES[0] if i in from_tf
                                  else inp.topics.get(topic, HEAD_TYPES[0])
                                  for i, topic in enumerate(frame_topics)]


def _output_layout(inp: ReplayInput, values, frames, frame_topics) -> RunLayout:
    """The output's node name and topics: the recorded ones when the chains are the same."""
    chains = tuple(values['chains'])
    if inp.layout is not None and inp.layout.chains == chains:
        return RunLayout(node=inp.layout.node, chains=chains, head_topic=inp.head_topic,
                         pose_topics=inp.layout.pose_topics,
                         marker_topic=inp.layout.marker_topic,
                         diagnostics_topic=inp.layout.diagnostics_topic,
                         parameter_events_topic=inp.layout.parameter_events_topic,
                         frames=frames, frame_topics=frame_topics)
    return RunLayout.for_node(inp.node, chains, head_topic=inp.head_topic,
                              frames=frames, frame_topics=frame_topics)


def _open_output(inp: ReplayInput, output_path: Path, values, frames, frame_topics,
                 frame_types, *, overwrite, tf, tf_prefix, info) -> RunRecorder:
    """The output recording, laid out as the node records a run."""
    layout = _output_layout(inp, values, frames, frame_topics)
    recorded_all = values_from_metadata(inp.recorded_parameters or {})
    # The node's other parameters (use_sim_time, ...) as recorded; ours as replayed.
    parameters = {**{k: v for k, v in recorded_all.items() if k in IGNORED_NAMES}, **values,
                  'record_path': str(output_path)}
    try:
        return RunRecorder(
            output_path, layout, parameters, head_type=inp.head_type, frame_types=frame_types,
            overwrite=overwrite, background=False,     # offline: nothing waits on the disk
            chunk_duration_ns=_OUTPUT_CHUNK_DURATION_NS, tf=tf,
            tf_prefix=(tf_prefix if tf_prefix is not None
                       else inp.metadata.get(RECORDING_METADATA, {}).get('tf_prefix', '')),
            info=info)
    except BagError as exc:
        text = str(exc)
        if 'already exists' in text:
            partial = _partial_output(output_path)
            text = (f'{output_path} already exists{f" ({partial})" if partial else ""} (use '
                    f'--overwrite to replace it)')
        raise ReplayError(text) from None


def _partial_output(path: Path) -> str | None:
    """How an existing output is partial (an interrupted replay's), or None."""
    from .bag import BagReader
    from .inputs import partial_note
    try:
        return partial_note(path, BagReader(path).metadata())
    except BagError:
        return None


class _OfflineLoop:
    """The input's messages, in its order, into the ``ReplayNode``: head and frame poses at
    their log times, the recorded live changes, and the ticks (the node's recorded ones, or
    every ``1/rate`` s from the first input pose). With look-ahead, ticks and parameter
    changes wait until ``LOOK_AHEAD_SAMPLES`` head poses logged after them are in; without
    it they run at once. Counts into ``result``."""

    def __init__(self, inp: ReplayInput, node: ReplayNode, result: ReplayResult, values, *,
                 mode: str, tick_topic: str | None, events_topic: str | None,
                 frame_topics, frame_types, look_ahead: bool,
                 progress: Callable[..., None] | None, tf_head: bool = False):
        self.inp, self.node, self.result = inp, node, result
        self.mode, self.events_topic = mode, events_topic
        self.look_ahead, self.progress = look_ahead, progress
        span = inp.span_ns() if progress is not None else None
        self.t_start = span[0] if span else None
        self.total_s = (span[1] - span[0]) * 1e-9 if span else None
        self.wanted = {inp.head_topic: inp.head_type}
        #: With the head from TF: the TF topics (read with ``wire.tf_message_fields``; their
        #: composed poses go the way of head and frame poses), else empty.
        self.tf_topics: dict[str, bool] = {}
        tf_sources = node.core.tf.sources if tf_head and node.core.tf is not None else {}
        if tf_head:
            del self.wanted[inp.head_topic]
            self.tf_topics = {t: t == TF_STATIC_TOPIC for t in (TF_TOPIC, TF_STATIC_TOPIC)
                              if t in inp.topics}
        #: topic -> the frames (indices) whose poses it carries
        self.frame_index: dict[str, list[int]] = {}
        for i, (topic, type_name) in enumerate(zip(frame_topics, frame_types, strict=True)):
            if i in tf_sources:
                continue
            if topic in inp.topics and topic != inp.head_topic:
                self.wanted[topic] = type_name
                self.frame_index.setdefault(topic, []).append(i)
        if mode == 'recorded' and tick_topic is not None:     # (recorded: there is one)
            self.wanted[tick_topic] = 'geometry_msgs/msg/PoseArray'
        if events_topic is not None:
            self.wanted[events_topic] = 'rcl_interfaces/msg/ParameterEvent'
        self.pending: list[tuple[int, Callable, tuple]] = []
        self.recent_heads: Any = deque(maxlen=LOOK_AHEAD_SAMPLES)
        self.newest_head: int | None = None
        # Ticks of a node recording are its poses' log times when their stamps are not tick
        # times.
        self.recorded_stamp = recorded_value(inp.recorded_parameters, 'output_stamp', 'tick')
        self.period_ns = int(round(1e9 / values['rate']))
        self.next_tick: int | None = None
        self.last_log: int | None = None

    def _decoders(self) -> dict[str, Callable[[bytes], Any]]:
        """Topic -> bytes to what the node takes: ``PoseStamped`` poses as ``ReceivedPose``
        (their fields read with ``struct``, recorded again as they are: no message object and
        no serialisation), everything else deserialised."""
        from rclpy.serialization import deserialize_message

        from .bag.msgdefs import _message_class
        def pose(cls: type, data: bytes) -> Any:
            return ReceivedPose.decode(data) or deserialize_message(data, cls)

        def poses(cls: type, data: bytes) -> Any:
            return (ReceivedPoses.decode(data)
                    or ReceivedPoses.of_message(deserialize_message(data, cls)))

        def message(cls: type, data: bytes) -> Any:
            return deserialize_message(data, cls)

        out: dict[str, Callable[[bytes], Any]] = {}
        for topic, type_name in self.wanted.items():
            cls = _message_class(type_name)
            if type_name == HEAD_TYPES[0]:
                out[topic] = partial(pose, cls)
            elif type_name == FRAMES_TYPE and topic in self.frame_index:
                out[topic] = partial(poses, cls)
            else:
                out[topic] = partial(message, cls)
        return out

    def run(self) -> None:
        decode = self._decoders()
        wanted = {**self.wanted, **{t: TFMESSAGE_TYPE for t in self.tf_topics}}
        for topic, _, data, log_ns in self.inp.messages(wanted, raw=True):
            if topic in self.tf_topics:
                self._tf(topic, data, log_ns)
                continue
            msg = decode[topic](data)
            self._ticks_before(log_ns)
            if topic == self.inp.head_topic:
                self._head(msg, log_ns)
            elif topic in self.frame_index:
                self._frame(topic, msg, log_ns)
            elif topic == self.events_topic:
                self._event(msg, log_ns)
            else:
                self._schedule_tick(log_ns if self.recorded_stamp == 'simulated'
                                    else stamp_ns(msg.header.stamp))
        if self.mode == 'nominal' and self.next_tick is not None and self.last_log is not None:
            while self.next_tick <= self.last_log:
                self._schedule_tick(self.next_tick)
                self.next_tick += self.period_ns
        self._run_due(flush=True)
        if self.result.last_tick_ns is not None:
            self.node.final_diagnostics(self.result.last_tick_ns)

    def _ticks_before(self, log_ns: int) -> None:
        """Nominal ticks: those due before a message logged at ``log_ns``."""
        if self.mode == 'nominal' and self.next_tick is not None:
            while self.next_tick < log_ns:
                self._schedule_tick(self.next_tick)
                self.next_tick += self.period_ns

    # -- the messages ----------------------------------------------------------------------
    def _head(self, msg, log_ns: int) -> None:
        self.node.head(msg, log_ns)
        self.recent_heads.append(log_ns)
        self.newest_head = log_ns if self.newest_head is None else max(self.newest_head, log_ns)
        self._run_due()
        self.result.head_samples += 1
        self._input_seen(log_ns)

    def _tf(self, topic: str, data: bytes, log_ns: int) -> None:
        """A ``TFMessage``: the head (and frames) now due from TF, as poses on their topics
        (the ticks due before this message first, as for any input)."""
        self._ticks_before(log_ns)
        tf_in = self.node.core.tf
        assert tf_in is not None            # (TF topics are read with the head from TF only)
        try:
            transforms = tf_message_fields(data)
        except ValueError as err:
            tf_in.bad_message(f'{topic} at log time {log_ns}: {err}')
            return
        for source, pose in tf_in.add(transforms, self.tf_topics[topic]):
            if source == 'head':
                self._head(pose, log_ns)
            else:
                self.node.frame(int(source), pose, log_ns)
                self.result.frame_samples += 1
                self._input_seen(log_ns)

    def _frame(self, topic: str, msg, log_ns: int) -> None:
        if isinstance(msg, ReceivedPoses):       # (frames_topic: every frame in one message)
            self.node.frame_poses(msg, log_ns)
        else:
            for i in self.frame_index[topic]:
                self.node.frame(i, msg, log_ns)
        self.result.frame_samples += 1
        self._input_seen(log_ns)

    def _input_seen(self, log_ns: int) -> None:
        """An input pose at ``log_ns``: the nominal ticks start one period after the first."""
        self.last_log = log_ns if self.last_log is None else max(self.last_log, log_ns)
        if self.next_tick is None:
            self.next_tick = log_ns + self.period_ns
        if self.t_start is None:
            self.t_start = log_ns

    def _event(self, msg, log_ns: int) -> None:
        layout = self.inp.layout            # (there are events to read with a layout only)
        if layout is None or msg.node != layout.node:
            return
        changed = event_values(msg)
        if not changed:
            return
        self._schedule(log_ns, self.node.set_parameters, changed, log_ns)
        self.result.parameter_changes += 1
        if 'rate' in changed:
            # (look-ahead: the change is still pending; its value as given)
            self.period_ns = int(round(1e9 / float(
                changed['rate'] if self.look_ahead else self.node.values['rate'])))

    # -- ticks and look-ahead --------------------------------------------------------------
    def _schedule_tick(self, t_ns: int) -> None:
        self._schedule(t_ns, self._tick, t_ns)

    def _tick(self, t_ns: int) -> None:
        out = self.node.tick(t_ns)
        result = self.result
        if out is not None:
            result.ticks += 1
            timings = out.report.timings
            result.step_seconds += timings.get('integrate', 0.0) + timings.get('contacts', 0.0)
            if result.first_tick_ns is None:
                result.first_tick_ns = t_ns
            result.last_tick_ns = t_ns
        self.node.maybe_diagnostics(t_ns)
        if self.progress is not None and self.t_start is not None:
            self.progress((t_ns - self.t_start) * 1e-9, self.total_s)

    def _schedule(self, t_ns: int, fn: Callable, *args) -> None:
        if self.look_ahead:
            self.pending.append((t_ns, fn, args))
        else:
            fn(*args)

    def _run_due(self, flush: bool = False) -> None:
        full = len(self.recent_heads) == LOOK_AHEAD_SAMPLES
        pending = self.pending
        while pending and (flush or (full and pending[0][0] < self.recent_heads[0]
                                     and (newest := self.newest_head) is not None
                                     and pending[0][0] + LOOK_AHEAD_SPAN_NS <= newest)):
            _, fn, args = pending.pop(0)
            fn(*args)


def _tf_finish(inp: ReplayInput, node: ReplayNode, result: ReplayResult, output_path: Path,
               warn) -> None:
    """The head from TF: none at all is an error naming the frames; transforms held past
    their samples, late stamps and bad messages are warned."""
    tf_in = node.core.tf
    if tf_in is None:
        return
    for source, src in tf_in.sources.items():
        what = f'{tf_in.name(source)} pose from TF ({tf_in.fixed_frame} -> {src.frame})'
        if src.last_ns is None:
            output_path.unlink(missing_ok=True)
            raise ReplayError(f'{inp.path}: no {what}: '
                              f'{src.error or "no moving transform on the way between them"}')
        if src.extrapolated:
            held = ', '.join(f'{edge} {n} times' for edge, n in sorted(src.extrapolated.items()))
            stale = sum(src.stale.values())
            warn(f'{inp.path}: the {what} held transforms past their samples: {held}'
                 + (f' ({stale} by more than stale_timeout)' if stale else ''))
    if tf_in.bad_messages:
        warn(f'{inp.path}: {tf_in.bad_messages} TF messages ignored ({tf_in.last_bad})')


def _finish(inp: ReplayInput, node: ReplayNode, recorder: RunRecorder, result: ReplayResult,
            output_path: Path, clock_note: str | None, warn) -> None:
    """What was simulated checked (nothing: an error, the output removed) and said; an
    interrupted replay's output is kept as it is (marked partial)."""
    if recorder.error is not None:
        raise ReplayError(f'writing {output_path} failed: {recorder.error}')
    if result.interrupted:
        return
    if result.head_samples == 0 and (node.runner.needs_head or result.ticks == 0):
        output_path.unlink(missing_ok=True)
        raise ReplayError(f'{inp.path}: no message on {inp.head_topic} could be read')
    dropped = {k: v for k, v in node.runner.dropped.items() if v}
    reasons = ', '.join(f'{v} {k}' for k, v in sorted(dropped.items()))
    if result.ticks == 0:
        output_path.unlink(missing_ok=True)
        why = (f'all {result.head_samples} head poses were dropped ({reasons})' if dropped
               else f'no tick had the inputs it needs ({", ".join(node.runner.missing_inputs())}'
                    f' missing)')
        raise ReplayError(f'{inp.path}: nothing simulated: {why}'
                          + (f'; {clock_note}' if clock_note else ''))
    if dropped:
        warn(f'{inp.path}: {sum(dropped.values())} of {result.head_samples + result.frame_samples}'
             f' input poses dropped ({reasons})')
    if inp.reader.out_of_order and inp.order == 'log_time':
        warn(f'{inp.path}: {inp.reader.out_of_order} messages are stored out of log-time order; '
             f'replayed in log-time order, as ros2 bag play does')
    if inp.truncated and inp.reader.truncation:
        inp.truncation = inp.reader.truncation
    if inp.truncated:
        warn(f'{inp.path}: replayed {result.head_samples} head poses and {result.ticks} ticks '
             f'(all that could be read)')
