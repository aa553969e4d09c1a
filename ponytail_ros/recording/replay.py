"""``ponytail_replay``: re-simulate a recording offline, compare two runs, or play a recording's
head poses into a running graph.

Usage::

    ponytail_replay INPUT.mcap -o OUTPUT.mcap [--params FILE.yaml] [--head-topic /head_pose]
                    [--ticks auto|recorded|nominal] [--look-ahead] [--overwrite] [--quiet]
    ponytail_replay compare A.mcap B.mcap [--plot out.png]      (or --compare A B)
    ponytail_replay --live INPUT.mcap [--rate 1.0] [--no-clock] [--restamp] [--loop]
    ponytail_replay repair IN.mcap OUT.mcap [--overwrite]    (a killed or damaged recording)

Offline replay (no ROS graph, no sleeping; as fast as the machine allows): the head poses
(``geometry_msgs/msg/PoseStamped`` or ``TransformStamped``) of any rosbag2 MCAP file -- one
written by the node (``record_path``) or by ``ros2 bag record -s mcap`` -- are pushed into a
``ChainRunner`` at their log times (receive times), the runner is ticked on the recorded clock
and the output is written exactly as the node records a run (same topics, types, metadata).

* Extra frames (``frames``): each frame's poses are read from the recorded node's topic for it
  (``frame_topics`` in the recording's metadata), else from its ``<frame>.topic`` resolved in
  the node's namespace (default ``/<frame>_pose``), and pushed like the head's, in file order.
  A frame the scene uses whose topic is not in the file is an error.

* Parameters: ``--params`` (a node params file, ``/**: ros__parameters:``), else the input's
  ``ponytail_ros/parameters`` metadata (then the live changes recorded on
  ``/parameter_events`` are applied at their times too), else the package's
  ``config/ponytail.yaml``.
* Ticks (``--ticks``): ``recorded`` ticks at the node's own tick times (the header stamps of its
  first ``segment_poses`` topic) and feeds every head pose and parameter change in the file
  order, i.e. exactly as the node interleaved them with its ticks; ``nominal`` ticks every
  ``1/rate`` s from the first head pose, a head pose counting for a tick if its log time is <=
  the tick time. ``auto`` (default): ``recorded`` if the input has the node's ticks and the
  replay's ``rate`` equals the recorded one, else ``nominal``.
  File order rather than time decides what came before a tick: under ``use_sim_time`` a pose
  received just after a tick carries the same clock time as the tick.
* Deterministic: the same input, parameters and output path give a byte-identical output file
  (the output's chunks are cut by size only, never by wall time, and the CDR is canonical, see
  ``cdr.py``). Replaying a node's recording with its recorded parameters and ticks reproduces
  its ``segment_poses`` and ``segment_markers`` bit for bit: ``ReplayNode`` makes exactly the
  node's ``ChainRunner`` calls with the same floats (it mirrors ``PonytailNode``'s callbacks;
  ``test_replay.py`` checks the two stay in step).
* Look-ahead (``--look-ahead``): every head pose is known ahead of time, so each tick is run
  only once ``LOOK_AHEAD_SAMPLES`` head poses logged after it, and ``LOOK_AHEAD_SPAN_NS`` of
  them, have been pushed (the frames' poses and the parameter changes in between are applied
  in file order), and the head is estimated at the tick time itself (no delay) by a centred
  fit through the poses on both sides: the estimator settings of ``LOOK_AHEAD_VALUES``
  (degree 9 over ±0.05 s, at least the 10 nearest poses: it interpolates at low rates and
  smooths float rounding at high ones; for animation, noisy tracker data wants the default
  replay) and ``output_stamp: simulated``. The output's parameters record them. Input resets
  (a teleport, a frame change) then take effect up to that look-ahead early. Not bit-exact
  with the live run, by design: the default replay is.
* Diagnostics are written every ``diagnostics_period`` s of the recorded clock with the node's
  keys; wall-time measurements (solve time, timer lateness) are ``n/a`` offline.

Compare: per chain, the tip (last segment's far end; segment length from the recorded
parameters, else the joint spacing) of two runs at the same stamps (each run's ``output_stamp``
is read from its parameters and printed: ``tick`` stamps label a chain simulated ``delay``
earlier, ``simulated`` ones its own time; recordings without it are ``tick``) -- or, when the
tick times differ (a nominal replay of a live run), at the nearest stamps within half a tick --
printed as RMS / max / final distance with the parameters that differ; ``--plot`` draws the
distance over time and both tips' coordinates.

Live: the head poses (and the recorded frames' poses, on their topics) are published at the
recorded pace (``--rate`` scales it) on the recorded head topic, with ``/clock`` from the
recorded log times before each pose and at ``--clock-rate`` Hz in between, for nodes with
``use_sim_time:=true``. For a node on the system clock use ``--no-clock --restamp`` (or its
``stamp_source:=receive``).

Nothing is lost or wrong in silence:

* a **damaged** input (changed bytes: a chunk or data-section CRC mismatch, a record that does
  not fit its length) is refused with the byte offset and the problem (``BagReader``); ``repair``
  keeps every intact record in a new file;
* a **truncated** input (a recording whose writer was killed) replays what can be read, with a
  warning saying where it is cut; ``repair`` makes it a complete, indexed file (``repair.py``);
* a bag not written by the node is replayed in **log-time order** (as ``ros2 bag play``), with a
  warning if it was stored out of that order; the node's own recordings in file order (the order
  the node handled the messages);
* head stamps on **another clock** than the log times (median offset over 5 s) are said on the
  terminal with the fix, ``--stamp-source receive``; in such a bag a first stamp of exactly 0 is
  a stamp, not "no stamp";
* unknown ``--params`` names are warned with the closest known name; dropped input poses are
  counted on the terminal; the last (partial) diagnostics period is written; a run in which
  nothing could be simulated (every pose dropped) is an error saying why.

Every recording and replay output also holds the segments as TF frames on ``/tf``
(``--tf-prefix``, ``--no-tf``; ``tf.py``). On a terminal a progress bar (tqdm) shows the
simulated time and the ETA; ``--quiet`` silences it, the summary and the warnings.

Exit status: 0 on success (warnings on stderr), 2 on bad or damaged input (one line on stderr
naming the file and the problem: not an MCAP file, damaged, truncated before the head topic, no
such topic, not a head pose type, invalid parameters, nothing simulated), 1 on an unexpected
error.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import yaml

from ponytail_ros.app.node_core import NodeCore, time_msg
from ponytail_ros.app.parameters import ParameterError, frame_names
from ponytail_ros.app.parameters import frame_topics as topics_of
from ponytail_ros.app.sink import HEAD, TickSink

from .bag import PARAMETERS_METADATA, BagError, BagReader
from ponytail_ros.app.param_values import (IGNORED_NAMES, resolve_values, unknown_parameter_warnings,
                     values_from_metadata, values_from_params_file)
from .recorder import (HEAD_TYPES, RECORDING_METADATA, RunLayout, RunRecorder, resolve_topic,
                       stamp_ns)

__all__ = ['main', 'replay', 'ReplayError', 'ReplayResult', 'ReplayInput', 'compare',
           'load_chain_runs', 'format_comparison', 'plot_comparison', 'live_replay']

#: Output chunks are cut by size only: the log-time/idle limit of BagWriter is set beyond any
#: replay, so that no wall-time effect changes the bytes.
_OUTPUT_CHUNK_DURATION_NS = 3600 * 1_000_000_000
_NA = 'n/a (replay)'
#: Look-ahead replay: a tick runs once this many head poses logged after it, spanning at least
#: LOOK_AHEAD_SPAN_NS (the fit's window), have been pushed.
LOOK_AHEAD_SAMPLES = 16
LOOK_AHEAD_SPAN_NS = 60_000_000
#: Look-ahead replay: parameters replaced (no delay; a centred interpolating fit; honest stamps).
LOOK_AHEAD_VALUES = {'interpolation_delay': 0.0, 'interpolation_delay_periods': 0.0,
                     'output_stamp': 'simulated', 'head.degree': 9, 'head.min_samples': 10,
                     'head.window': 0.05, 'head.max_samples': 512}


class ReplayError(Exception):
    """Bad input or options; the message is one line naming the file (and topic)."""


# -- input -------------------------------------------------------------------------------------


class ReplayInput:
    """An input recording: its topics, metadata, the head topic and what the node recorded.

    Raises:
        ReplayError: not readable, not MCAP, no head topic, or the head topic is not a pose.
    """

    def __init__(self, path, head_topic: Optional[str] = None):
        self.path = Path(path)
        try:
            self.reader = BagReader(self.path)
            self.topics = self.reader.topics()
            self.metadata = self.reader.metadata()   # a full walk: finds a cut or damage
        except BagError as exc:
            raise ReplayError(str(exc)) from None
        self.truncated = not self.reader.finished
        #: "truncated at byte N of M: why" for a cut file, else None.
        self.truncation = self.reader.truncation if self.truncated else None
        self.layout = None
        if RECORDING_METADATA in self.metadata:
            try:
                self.layout = RunLayout.from_metadata(self.metadata[RECORDING_METADATA])
            except (KeyError, ValueError):
                self.layout = None  # not ours after all: treat as a plain recording
        #: Our recordings are replayed in the order the node handled the messages (file order,
        #: see recorder.py); any other bag in log-time order, as rosbag2 plays it.
        self.order = 'file' if self.layout is not None else 'log_time'
        self.recorded_parameters = self.metadata.get(PARAMETERS_METADATA)
        self.note = None
        if head_topic is None:
            head_topic = self.layout.head_topic if self.layout else '/head_pose'
            if head_topic not in self.topics:
                heads = sorted(t for t, ty in self.topics.items() if ty in HEAD_TYPES)
                if len(heads) == 1:
                    self.note = f'using {heads[0]}, the only head pose topic in {self.path}'
                    head_topic = heads[0]
        self.head_topic = head_topic
        if head_topic not in self.topics:
            recorded = ', '.join(f'{t} ({ty})' for t, ty in sorted(self.topics.items()))
            if self.truncated:
                raise ReplayError(
                    f'{self.path} is {self.truncation or "truncated (no footer)"}; the part '
                    f'that can be read has no topic {head_topic} (recorded: {recorded or "none"})')
            raise ReplayError(f'{self.path} has no topic {head_topic} (recorded: '
                              f'{recorded or "none"}); choose one with --head-topic')
        self.head_type = self.topics[head_topic]
        if self.head_type not in HEAD_TYPES:
            raise ReplayError(f'{self.path}: topic {head_topic} holds {self.head_type}, not a head '
                              f'pose ({" or ".join(HEAD_TYPES)})')

    def messages(self, topics):
        """``BagReader.messages`` in this input's order (:attr:`order`)."""
        return self.reader.messages(topics, order=self.order)

    def truncated_warning(self) -> str:
        return (f'{self.path} is {self.truncation or "truncated (no footer)"}; replaying what '
                f'can be read (ponytail_replay repair makes it a complete, indexed file)')

    @property
    def node(self) -> str:
        return self.layout.node if self.layout else '/ponytail'

    def frame_topic(self, frame: str, configured: str) -> str:
        """Where frame ``frame``'s poses are: the recorded node's topic for it, else
        ``configured`` (``<frame>.topic``) resolved in the node's namespace."""
        if self.layout is not None and frame in self.layout.frames:
            return self.layout.frame_topics[self.layout.frames.index(frame)]
        return resolve_topic(self.node, configured)

    def tick_topic(self) -> Optional[str]:
        """The node's first ``segment_poses`` topic, if this is a node recording with ticks."""
        if self.layout and self.layout.pose_topics[0] in self.topics:
            return self.layout.pose_topics[0]
        return None

    def message_count(self, topic: str) -> int:
        """Messages on ``topic`` by the final rosbag2 metadata (0 if unknown: truncated)."""
        try:
            bag = yaml.safe_load(self.metadata['rosbag2']['serialized_metadata'])
            return next(t['message_count'] for t in bag['topics_with_message_count']
                        if t['topic_metadata']['name'] == topic)
        except (KeyError, TypeError, StopIteration, yaml.YAMLError):
            return 0

    def span_ns(self) -> Optional[Tuple[int, int]]:
        """(first, last) log time of a finished file (summary statistics), else None."""
        if self.truncated:
            return None
        from mcap.reader import make_reader
        try:
            with self.path.open('rb') as f:
                stats = make_reader(f).get_summary().statistics
            return stats.message_start_time, stats.message_end_time
        except Exception:  # noqa: BLE001 - only the progress bar needs it
            return None


def _head_pose(msg, head_type):
    """(position, orientation) tuples of a PoseStamped or TransformStamped."""
    if head_type == HEAD_TYPES[0]:
        p, q = msg.pose.position, msg.pose.orientation
    else:
        p, q = msg.transform.translation, msg.transform.rotation
    return (p.x, p.y, p.z), (q.x, q.y, q.z, q.w)


# -- the node, offline -------------------------------------------------------------------------


class ReplayNode:
    """What ``PonytailNode`` does with a head pose, a tick and a parameter change, on the
    recorded clock: the same ``NodeCore`` (``ponytail_ros/app/node_core.py``) with the same
    arguments, its output sent to a ``TickSink`` (``app/sink.py``; here the ``RunRecorder``)
    through the same calls as the node's sinks. Times are integer ns of the recorded clock."""

    def __init__(self, values: Mapping[str, Any], recorder: RunRecorder, head_type: str,
                 frame_types: Sequence[str] = (), zero_stamp_valid: bool = False):
        self.core = NodeCore(values)
        self.runner = self.core.runner
        self._recorder = recorder
        #: Where the output goes (the node's is its recorder and its publishers).
        self.sink: TickSink = recorder
        self._head_type = head_type
        self._frame_types = list(frame_types) or [HEAD_TYPES[0]] * len(self.core.frames)
        self._diag_period_ns = int(round(self.core.values['diagnostics_period'] * 1e9))
        self._diag_next_ns = None
        self._diag_last_ns = None
        #: A zero header stamp is a real stamp (a simulator clock starting at 0), not "no
        #: stamp", when the stream has other non-zero stamps.
        self._zero_stamp_valid = zero_stamp_valid

    @property
    def values(self):
        return dict(self.core.values)

    @property
    def published(self):
        return self.core.published

    def head(self, msg, log_time_ns: int) -> None:
        """A recorded head pose at its receive time."""
        self.sink.on_input(HEAD, msg, log_time_ns)
        p, q = _head_pose(msg, self._head_type)
        stamp = msg.header.stamp
        if (self._zero_stamp_valid and stamp.sec == 0 and stamp.nanosec == 0
                and self.core.stamp_source == 'header'):
            self.runner.push(0.0, p, q, msg.header.frame_id)  # NodeCore would take "no stamp"
            return
        self.core.push_head(stamp, log_time_ns, p, q, msg.header.frame_id)

    def frame(self, i: int, msg, log_time_ns: int) -> None:
        """A recorded pose of frame ``i`` at its receive time."""
        self.sink.on_input(i, msg, log_time_ns)
        p, q = _head_pose(msg, self._frame_types[i])
        self.core.push_frame(i, msg.header.stamp, log_time_ns, p, q, msg.header.frame_id)

    def tick(self, t_ns: int):
        """Tick at ``t_ns``; its ``TickOutput`` (None: nothing to publish yet)."""
        tick = self.core.tick(t_ns)
        if tick is None:
            return None
        self.sink.on_tick(tick, t_ns)
        return tick.output

    def set_parameters(self, changed: Mapping[str, Any], log_time_ns: int) -> None:
        """A recorded live change: checked and applied as the node's parameter callbacks do."""
        changed = self.core.ours(changed)
        if not changed:
            return
        try:
            self.core.check_change(changed)
        except ParameterError:
            return  # the node rejects it too
        self.sink.on_parameters(changed, log_time_ns)
        self.core.apply_change(changed)

    def maybe_diagnostics(self, t_ns: int) -> None:
        """Diagnostics every ``diagnostics_period`` of the recorded clock (the node's timer)."""
        if self._diag_next_ns is None:
            self._diag_next_ns = t_ns + self._diag_period_ns
            self.core.window.t0_ns = t_ns
            return
        if t_ns < self._diag_next_ns:
            return
        self._diag_next_ns += self._diag_period_ns * max(
            1, (t_ns - self._diag_next_ns) // self._diag_period_ns + 1)
        self.sink.on_diagnostics(self.diagnostics_message(t_ns), t_ns)
        self._diag_last_ns = t_ns

    def final_diagnostics(self, t_ns: int) -> None:
        """The last, partial period's diagnostics at the end of the input (the node's last
        period ends when it is stopped; a replay's at its last tick), so that the drop and reset
        counts in the file are the run's totals."""
        if self._diag_next_ns is not None and t_ns != self._diag_last_ns \
                and t_ns > self.core.window.t0_ns:
            self.sink.on_diagnostics(self.diagnostics_message(t_ns), t_ns)
            self._diag_last_ns = t_ns

    def diagnostics_message(self, t_ns: int):
        from diagnostic_msgs.msg import DiagnosticArray
        span = (t_ns - self.core.window.t0_ns) * 1e-9
        status = self.core.diagnostic_status(t_ns, span, self._recorder.layout.node)
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = time_msg(t_ns)
        return msg


# -- offline replay ----------------------------------------------------------------------------


@dataclass
class ReplayResult:
    """What a replay did."""

    output: Path
    ticks: int = 0
    head_samples: int = 0
    #: Poses of the extra frames pushed (all frames).
    frame_samples: int = 0
    parameter_changes: int = 0
    first_tick_ns: Optional[int] = None
    last_tick_ns: Optional[int] = None
    wall_seconds: float = 0.0
    #: CPU time of this process (all threads) during the replay, s.
    cpu_seconds: float = 0.0
    tick_mode: str = ''
    parameters_from: str = ''
    truncated: bool = False

    @property
    def sim_seconds(self) -> float:
        if self.first_tick_ns is None:
            return 0.0
        return (self.last_tick_ns - self.first_tick_ns) * 1e-9

    def summary(self, input_path) -> str:
        speed = self.sim_seconds / self.wall_seconds if self.wall_seconds > 0 else float('inf')
        return (f'{input_path} -> {self.output}: {self.ticks} ticks ({self.tick_mode}), '
                f'{self.head_samples} head poses, {self.sim_seconds:.2f} s simulated in '
                f'{self.wall_seconds:.2f} s ({speed:.1f}x real time); parameters from '
                f'{self.parameters_from}')


class _Progress:
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

    def __call__(self, done_s: float, total_s: Optional[float] = None,
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


def replay(input_path, output_path, *, params_file=None, head_topic: Optional[str] = None,
           ticks: str = 'auto', overwrite: bool = False, look_ahead: bool = False,
           progress: Optional[Callable[..., None]] = None,
           warn: Optional[Callable[[str], None]] = None,
           stamp_source: Optional[str] = None, tf: bool = True,
           tf_prefix: Optional[str] = None) -> ReplayResult:
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

    Raises:
        ReplayError: bad input or options (one-line message naming the file and topic), a
            damaged input, or a run in which every head pose was dropped.
    """
    warn = warn or (lambda text: None)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    if ticks not in ('auto', 'recorded', 'nominal'):
        raise ReplayError(f'--ticks must be auto, recorded or nominal, not {ticks!r}')
    inp = ReplayInput(input_path, head_topic)
    output_path = Path(output_path)
    if output_path.exists() and output_path.resolve() == inp.path.resolve():
        raise ReplayError(f'{output_path}: the output would overwrite the input')
    result = ReplayResult(output=output_path, truncated=inp.truncated)
    if inp.note:
        warn(inp.note)
    if inp.truncated:
        warn(inp.truncated_warning())

    try:
        values, source = resolve_values(params_file, inp.recorded_parameters, inp.node)
    except ParameterError as exc:
        origin = params_file or (f'{inp.path} (recorded parameters)'
                                 if inp.recorded_parameters else 'the default config')
        raise ReplayError(f'{origin}: invalid parameters: {exc}') from None
    partial = values_from_metadata(inp.recorded_parameters) if (
        params_file is None and inp.recorded_parameters) else {}
    if params_file is not None:
        try:
            partial = values_from_params_file(params_file, inp.node)
        except ParameterError:
            partial = {}
    for text in unknown_parameter_warnings(partial):
        warn(f'{params_file or inp.path}: {text}')
    if stamp_source is not None:
        if stamp_source not in ('header', 'receive'):
            raise ReplayError(f'--stamp-source must be header or receive, not {stamp_source!r}')
        values['stamp_source'] = stamp_source
    result.parameters_from = source if source == 'the recording' else Path(source).name
    if look_ahead:
        values = {**values, **LOOK_AHEAD_VALUES}

    head_stamps = _head_stamps(inp)
    clock_note = _foreign_clock(inp, head_stamps, values['stamp_source'])
    if clock_note:
        warn(clock_note)

    # Ticks: the node's own where possible.
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
        mode = 'recorded'
    elif ticks == 'auto' and tick_topic is not None and recorded_rate == values['rate']:
        mode = 'recorded'
    else:
        mode = 'nominal'
    result.tick_mode = mode
    apply_events = (inp.layout is not None
                    and inp.topics.get(inp.layout.parameter_events_topic)
                    == 'rcl_interfaces/msg/ParameterEvent')
    if apply_events and params_file is not None:
        apply_events = False
        changes = inp.message_count(inp.layout.parameter_events_topic)
        if changes:
            warn(f'{inp.path}: its {changes} live parameter change(s) are not applied over '
                 f'--params')

    # The extra frames' topics (the recorded node's, else as configured) and types.
    frames = tuple(frame_names(values))
    frame_topics = tuple(inp.frame_topic(f, t) for f, t in zip(frames, topics_of(values)))
    used = _used_frame_names(values)
    for f, topic in zip(frames, frame_topics):
        if topic not in inp.topics:
            if f in used:
                raise ReplayError(f'{inp.path} has no topic {topic} (the poses of frame {f}, '
                                  f'which the scene uses)')
            warn(f'{inp.path} has no topic {topic}: frame {f} gets no poses')
        elif inp.topics[topic] not in HEAD_TYPES:
            raise ReplayError(f'{inp.path}: topic {topic} (frame {f}) holds {inp.topics[topic]}, '
                              f'not a pose ({" or ".join(HEAD_TYPES)})')
    frame_types = [inp.topics.get(topic, HEAD_TYPES[0]) for topic in frame_topics]

    # The output: the node's layout (the recorded one when the chains are the same).
    chains = tuple(values['chains'])
    if inp.layout is not None and inp.layout.chains == chains:
        layout = RunLayout(node=inp.layout.node, chains=chains, head_topic=inp.head_topic,
                           pose_topics=inp.layout.pose_topics,
                           marker_topic=inp.layout.marker_topic,
                           diagnostics_topic=inp.layout.diagnostics_topic,
                           parameter_events_topic=inp.layout.parameter_events_topic,
                           frames=frames, frame_topics=frame_topics)
    else:
        layout = RunLayout.for_node(inp.node, chains, head_topic=inp.head_topic,
                                    frames=frames, frame_topics=frame_topics)
    recorded_all = values_from_metadata(inp.recorded_parameters or {})
    # The node's other parameters (use_sim_time, ...) as recorded; ours as replayed.
    parameters = {**{k: v for k, v in recorded_all.items() if k in IGNORED_NAMES}, **values,
                  'record_path': str(output_path)}
    try:
        recorder = RunRecorder(
            output_path, layout, parameters, head_type=inp.head_type, frame_types=frame_types,
            overwrite=overwrite,
            chunk_duration_ns=_OUTPUT_CHUNK_DURATION_NS, tf=tf,
            tf_prefix=(tf_prefix if tf_prefix is not None
                       else inp.metadata.get(RECORDING_METADATA, {}).get('tf_prefix', '')),
            info={'source': 'ponytail_replay', 'input': inp.path.name, 'ticks': mode,
                  'parameters_from': result.parameters_from,
                  'head_estimation': 'look-ahead' if look_ahead else 'live'})
    except BagError as exc:
        text = str(exc)
        if 'already exists' in text:
            text = f'{output_path} already exists (use --overwrite to replace it)'
        raise ReplayError(text) from None

    node = ReplayNode(values, recorder, inp.head_type, frame_types,
                      # A node recording replays as the node ran (a zero stamp: the receive
                      # time); in another bag whose stamps are set, 0 is a stamp (sim clock).
                      zero_stamp_valid=(inp.layout is None
                                        and any(stamp for stamp, _ in head_stamps)))
    span = inp.span_ns() if progress is not None else None
    t_start = span[0] if span else None
    total_s = (span[1] - span[0]) * 1e-9 if span else None
    wanted = {inp.head_topic: inp.head_type}
    #: topic -> the frames (indices) whose poses it carries
    frame_index: Dict[str, List[int]] = {}
    for i, (topic, type_name) in enumerate(zip(frame_topics, frame_types)):
        if topic in inp.topics and topic != inp.head_topic:
            wanted[topic] = type_name
            frame_index.setdefault(topic, []).append(i)
    if mode == 'recorded':
        wanted[tick_topic] = 'geometry_msgs/msg/PoseArray'
    if apply_events:
        wanted[inp.layout.parameter_events_topic] = 'rcl_interfaces/msg/ParameterEvent'
    events_topic = inp.layout.parameter_events_topic if apply_events else None

    def do_tick(t_ns):
        out = node.tick(t_ns)
        if out is not None:
            result.ticks += 1
            if result.first_tick_ns is None:
                result.first_tick_ns = t_ns
            result.last_tick_ns = t_ns
        node.maybe_diagnostics(t_ns)
        if progress is not None and t_start is not None:
            progress((t_ns - t_start) * 1e-9, total_s)

    # Look-ahead: ticks and parameter changes wait until LOOK_AHEAD_SAMPLES head poses logged
    # after them are in; without it they run at once.
    pending: List[Tuple[int, Callable, tuple]] = []
    recent_heads: Any = deque(maxlen=LOOK_AHEAD_SAMPLES)
    newest_head = [None]

    def schedule(t_ns, fn, *args):
        if look_ahead:
            pending.append((t_ns, fn, args))
        else:
            fn(*args)

    def run_due(flush=False):
        full = len(recent_heads) == LOOK_AHEAD_SAMPLES
        while pending and (flush or (full and pending[0][0] < recent_heads[0]
                                     and pending[0][0] + LOOK_AHEAD_SPAN_NS <= newest_head[0])):
            _, fn, args = pending.pop(0)
            fn(*args)

    # Ticks of a node recording are its poses' log times when their stamps are not tick times.
    recorded_stamp = _recorded_value(inp.recorded_parameters, 'output_stamp', 'tick')
    period_ns = int(round(1e9 / values['rate']))
    next_tick = None
    last_log = None
    try:
        for topic, _, msg, log_ns in inp.messages(wanted):
            if mode == 'nominal' and next_tick is not None:
                while next_tick < log_ns:
                    schedule(next_tick, do_tick, next_tick)
                    next_tick += period_ns
            if topic == inp.head_topic:
                node.head(msg, log_ns)
                recent_heads.append(log_ns)
                newest_head[0] = log_ns if newest_head[0] is None else max(newest_head[0], log_ns)
                run_due()
                result.head_samples += 1
                last_log = log_ns if last_log is None else max(last_log, log_ns)
                if next_tick is None:
                    next_tick = log_ns + period_ns
                if t_start is None:
                    t_start = log_ns
            elif topic in frame_index:
                for i in frame_index[topic]:
                    node.frame(i, msg, log_ns)
                result.frame_samples += 1
                last_log = log_ns if last_log is None else max(last_log, log_ns)
                if next_tick is None:
                    next_tick = log_ns + period_ns
                if t_start is None:
                    t_start = log_ns
            elif topic == events_topic:
                if msg.node == inp.layout.node:
                    changed = _event_values(msg)
                    if changed:
                        schedule(log_ns, node.set_parameters, changed, log_ns)
                        result.parameter_changes += 1
                        if 'rate' in changed:
                            # (look-ahead: the change is still pending; its value as given)
                            period_ns = int(round(1e9 / float(
                                changed['rate'] if look_ahead else node.values['rate'])))
            else:
                t_tick = log_ns if recorded_stamp == 'simulated' else stamp_ns(msg.header.stamp)
                schedule(t_tick, do_tick, t_tick)
        if mode == 'nominal' and next_tick is not None and last_log is not None:
            while next_tick <= last_log:
                schedule(next_tick, do_tick, next_tick)
                next_tick += period_ns
        run_due(flush=True)
        if result.last_tick_ns is not None:
            node.final_diagnostics(result.last_tick_ns)
    except BagError as exc:
        recorder.close()
        output_path.unlink(missing_ok=True)
        raise ReplayError(str(exc)) from None
    finally:
        recorder.close()
    if recorder.error is not None:
        raise ReplayError(f'writing {output_path} failed: {recorder.error}')
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
    result.wall_seconds = time.perf_counter() - wall0
    result.cpu_seconds = time.process_time() - cpu0
    if progress is not None and result.first_tick_ns is not None and t_start is not None:
        progress((result.last_tick_ns - t_start) * 1e-9, total_s, final=True)
    return result


#: Head stamps further than this from their log times (median) are on another clock.
FOREIGN_CLOCK_S = 5.0
_STAMP_SAMPLE = 200


def _head_stamps(inp: ReplayInput):
    """(header stamp, log time) ns of the first head poses."""
    out = []
    try:
        for _, _, msg, log_ns in inp.messages({inp.head_topic: inp.head_type}):
            out.append((stamp_ns(msg.header.stamp), log_ns))
            if len(out) >= _STAMP_SAMPLE:
                break
    except BagError as exc:
        raise ReplayError(str(exc)) from None
    return out


def _foreign_clock(inp: ReplayInput, head_stamps, stamp_source: str) -> Optional[str]:
    """A warning if the head stamps are on another clock than the log times (a bag stamped
    by a simulator clock from 0, or from another epoch) and would be used (``stamp_source:
    header``): the head motion would be estimated on one clock and simulated on the other."""
    if stamp_source != 'header':
        return None
    pairs = [(s, l) for s, l in head_stamps if s]
    if not pairs:
        return None
    offset = float(np.median([s - l for s, l in pairs])) * 1e-9
    if abs(offset) <= FOREIGN_CLOCK_S:
        return None
    return (f'{inp.path}: the head pose stamps on {inp.head_topic} are {offset:+.6g} s off their '
            f'log times (another clock: a simulator from 0, or another machine); the replay '
            f'would be physically wrong. Use --stamp-source receive (stamp_source: receive in '
            f'the params file) to time the poses by their log times')


def _recorded_value(recorded: Optional[Mapping[str, str]], name: str, default: Any) -> Any:
    """A parameter's value in a recording's parameters metadata (JSON), else ``default``."""
    try:
        return json.loads(recorded[name])
    except (KeyError, TypeError, ValueError):
        return default


def _used_frame_names(values) -> set:
    """The frames some chain hangs from or some collider is fixed in."""
    frames = set(frame_names(values))
    used = {values[f'{c}.anchor'] for c in values['chains']}
    used |= {values[f'{c}.frame'] for c in values.get('colliders', ())}
    return frames & used


def _event_values(event) -> Dict[str, Any]:
    from rclpy.parameter import Parameter
    changed = {}
    for p in list(event.new_parameters) + list(event.changed_parameters):
        value = Parameter.from_parameter_msg(p).value
        changed[p.name] = value if isinstance(value, (str, bool, int, float)) else list(value)
    return changed


# -- compare -----------------------------------------------------------------------------------


@dataclass
class ChainRun:
    """One chain of one recording: tick stamps (ns) and tip positions."""

    name: str
    topic: str
    stamps: np.ndarray
    tips: np.ndarray
    length_from: str


@dataclass
class ChainComparison:
    name: str
    matched: int
    only_a: int
    only_b: int
    rms: float
    max: float
    t_max: float
    final: float
    matching: str
    t: np.ndarray
    distance: np.ndarray
    tip_a: np.ndarray
    tip_b: np.ndarray


def load_chain_runs(path) -> Tuple[Dict[str, ChainRun], Dict[str, Any]]:
    """Every chain's tip track in a recording (ours, or any with ``segment_poses`` topics),
    and its parameters (empty if not recorded).

    Raises:
        ReplayError: unreadable, or no ``PoseArray`` topic.
    """
    from ponytail_ros.core.rotations import quat_axis_x
    path = Path(path)
    try:
        reader = BagReader(path)
        topics = reader.topics()
        metadata = reader.metadata()
    except BagError as exc:
        raise ReplayError(str(exc)) from None
    values = {}
    if PARAMETERS_METADATA in metadata:
        try:
            values = values_from_metadata(metadata[PARAMETERS_METADATA])
        except ParameterError:
            values = {}
    chains: Dict[str, str] = {}
    layout = None
    if RECORDING_METADATA in metadata:
        try:
            layout = RunLayout.from_metadata(metadata[RECORDING_METADATA])
        except (KeyError, ValueError):
            layout = None
    if layout is not None:
        chains = {c: t for c, t in zip(layout.chains, layout.pose_topics) if t in topics}
    else:
        arrays = sorted(t for t, ty in topics.items() if ty == 'geometry_msgs/msg/PoseArray')
        for t in arrays:
            parts = t.strip('/').split('/')
            if parts[-1] == 'segment_poses':
                name = (values.get('chains') or ['ponytail'])[0]
            elif len(parts) > 1 and parts[-2] == 'segment_poses':
                name = parts[-1]
            else:
                name = t
            chains[name] = t
    if not chains:
        raise ReplayError(f'{path} has no segment_poses (geometry_msgs/msg/PoseArray) topic')
    lengths = {}
    for name, topic in chains.items():
        try:
            lengths[topic] = (name, float(values[f'{name}.length']), 'parameters')
        except (KeyError, TypeError, ValueError):
            lengths[topic] = (name, None, 'joint spacing')
    tracks = {t: ([], []) for t in chains.values()}
    try:
        # Only the stamp and the tip of each message are kept (hours of run fit in memory).
        for topic, _, m, _ in reader.messages(list(chains.values())):
            if not m.poses:
                continue
            _, length, _ = lengths[topic]
            # Per message: the segment count may change during a run (a live rebuild).
            last = m.poses[-1]
            o = np.array([last.position.x, last.position.y, last.position.z])
            q = np.array([last.orientation.x, last.orientation.y, last.orientation.z,
                          last.orientation.w])
            if length is not None:
                seg = length / len(m.poses)
            elif len(m.poses) > 1:
                p = m.poses[-2].position
                seg = float(np.linalg.norm(o - np.array([p.x, p.y, p.z])))
            else:
                seg = 0.0
                lengths[topic] = (lengths[topic][0], None, 'unknown (tip = last joint)')
            tracks[topic][0].append(stamp_ns(m.header.stamp))
            tracks[topic][1].append(o + quat_axis_x(q) * seg)
    except BagError as exc:
        raise ReplayError(str(exc)) from None
    runs = {}
    for topic, (stamps, tips) in tracks.items():
        if stamps:
            name, _, length_from = lengths[topic]
            runs[name] = ChainRun(name, topic, np.array(stamps, dtype=np.int64),
                                  np.array(tips), length_from)
    return runs, values


def _match(sa: np.ndarray, sb: np.ndarray):
    """Indices of matching stamps: exact, or nearest within half a tick if few match exactly."""
    common, ia, ib = np.intersect1d(sa, sb, assume_unique=False, return_indices=True)
    if len(common) >= 0.5 * min(len(sa), len(sb)) or len(sa) < 2 or len(sb) < 2:
        return ia, ib, 'exact stamps'
    tol = 0.5 * float(np.median(np.diff(sa)))
    j = np.clip(np.searchsorted(sb, sa), 1, len(sb) - 1)
    left, right = sb[j - 1], sb[j]
    nearest = np.where(np.abs(sa - left) <= np.abs(right - sa), j - 1, j)
    ok = np.abs(sb[nearest] - sa) <= tol
    return np.nonzero(ok)[0], nearest[ok], f'nearest stamps (within {tol * 1e-6:.2f} ms)'


def compare(path_a, path_b):
    """Per chain tip distances between two runs matched by stamp.

    Returns ``(comparisons, runs_a, runs_b, values_a, values_b)``.
    """
    runs_a, values_a = load_chain_runs(path_a)
    runs_b, values_b = load_chain_runs(path_b)
    pairs = [(n, n) for n in runs_a if n in runs_b]
    if not pairs and len(runs_a) == 1 and len(runs_b) == 1:
        pairs = [(next(iter(runs_a)), next(iter(runs_b)))]
    if not pairs:
        raise ReplayError(f'{path_a} and {path_b} have no chain in common '
                          f'({", ".join(runs_a)} vs {", ".join(runs_b)})')
    out = []
    for na, nb in pairs:
        a, b = runs_a[na], runs_b[nb]
        ia, ib, how = _match(a.stamps, b.stamps)
        d = np.linalg.norm(a.tips[ia] - b.tips[ib], axis=1)
        t = a.stamps[ia]
        t0 = min(a.stamps[0], b.stamps[0])
        name = na if na == nb else f'{na} / {nb}'
        if len(d):
            k = int(np.argmax(d))
            rms, mx, t_max, final = (float(np.sqrt(np.mean(d * d))), float(d[k]),
                                     (t[k] - t0) * 1e-9, float(d[-1]))
        else:
            rms = mx = t_max = final = float('nan')
        out.append(ChainComparison(name, len(d), len(a.stamps) - len(ia), len(b.stamps) - len(ib),
                                   rms, mx, t_max, final, how, (t - t0) * 1e-9, d,
                                   a.tips[ia], b.tips[ib]))
    return out, runs_a, runs_b, values_a, values_b


def format_comparison(path_a, path_b, comparisons, values_a=None, values_b=None) -> str:
    """The comparison as text: the files, the parameters that differ, a table per chain."""
    lines = [f'A: {path_a}', f'B: {path_b}']
    stamps = [(values or {}).get('output_stamp', 'tick') for values in (values_a, values_b)]
    lines.append(f'output stamps: A {stamps[0]}, B {stamps[1]} ' + (
        '(tick: the chain simulated a delay before its stamp, root on the head at the stamp)'
        if 'tick' in stamps else '(the time of each state)'))
    if stamps[0] != stamps[1]:
        lines.append('warning: A and B stamp differently: tips matched by stamp are the chain '
                     'at times a delay apart')
    if values_a and values_b:
        diff = [k for k in sorted(set(values_a) | set(values_b))
                if k not in ('record_path',) and values_a.get(k) != values_b.get(k)]
        if diff:
            lines.append('parameters that differ (A -> B):')
            lines += [f'  {k}: {values_a.get(k, "-")} -> {values_b.get(k, "-")}' for k in diff]
        else:
            lines.append('parameters: identical')
    header = ('chain', 'matched ticks', 'RMS tip dist (mm)', 'max tip dist (mm)', 'at t (s)',
              'final (mm)')
    rows = [(c.name, f'{c.matched}', f'{1e3 * c.rms:.4g}', f'{1e3 * c.max:.4g}',
             f'{c.t_max:.3f}', f'{1e3 * c.final:.4g}') for c in comparisons]
    widths = [max(len(r[i]) for r in [header] + rows) for i in range(len(header))]
    lines.append('  '.join(h.ljust(w) if i == 0 else h.rjust(w)
                           for i, (h, w) in enumerate(zip(header, widths))))
    for r in rows:
        lines.append('  '.join(v.ljust(w) if i == 0 else v.rjust(w)
                               for i, (v, w) in enumerate(zip(r, widths))))
    for c in comparisons:
        extra = [c.matching]
        if c.only_a or c.only_b:
            extra.append(f'{c.only_a} ticks only in A, {c.only_b} only in B')
        lines.append(f'  {c.name}: {"; ".join(extra)}')
    return '\n'.join(lines)


def plot_comparison(comparisons, out_png, label_a='A', label_b='B') -> Path:
    """Tip distance over time and the tips' height (z) in both runs, one column per chain."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    n = len(comparisons)
    fig, axes = plt.subplots(2, n, figsize=(6 * n, 6), squeeze=False, sharex='col')
    for i, c in enumerate(comparisons):
        ax = axes[0, i]
        ax.plot(c.t, 1e3 * c.distance, lw=1)
        ax.set_title(f'{c.name}: tip distance A-B (RMS {1e3 * c.rms:.3g} mm)')
        ax.set_ylabel('mm')
        ax.grid(alpha=0.3)
        ax = axes[1, i]
        for k, axis in enumerate('xyz'):
            ax.plot(c.t, c.tip_a[:, k], lw=1, label=f'{label_a} {axis}')
            ax.plot(c.t, c.tip_b[:, k], lw=1, ls='--', label=f'{label_b} {axis}')
        ax.set_xlabel('time from start (s)')
        ax.set_ylabel('tip position (m)')
        ax.legend(fontsize=7, ncol=3)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    out_png = Path(out_png)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return out_png


# -- live replay -------------------------------------------------------------------------------


def live_replay(path, *, context=None, head_topic: Optional[str] = None, rate: float = 1.0,
                clock: bool = True, clock_hz: float = 100.0, restamp: bool = False,
                loop: bool = False, wait_for_subscribers: float = 2.0,
                stop: Optional[threading.Event] = None,
                warn: Optional[Callable[[str], None]] = None) -> int:
    """Publish a recording's head poses into the ROS graph at the recorded pace.

    ``rclpy`` must be initialised (``context``: the context to use). Publishes the head topic
    (reliable, depth 10; same type as recorded), the recorded node's frame topics likewise
    (``frames``, in file order with the head poses), and, with ``clock``, ``/clock`` from the
    recorded times (before each pose and at ``clock_hz`` in between), for ``use_sim_time``
    nodes. ``rate`` scales the pace; ``restamp`` rewrites the header stamps with this process's
    clock (for nodes on the system clock); ``loop`` starts again at the end with the times
    shifted forward so the clock never goes back. Waits up to ``wait_for_subscribers`` s for a
    subscriber of the head topic first. Returns the number of head poses published.

    Raises:
        ReplayError: bad input (as the offline replay).
    """
    import rclpy
    from builtin_interfaces.msg import Time
    from rclpy.qos import QoSProfile
    from rosgraph_msgs.msg import Clock
    from .bag import _message_class

    warn = warn or (lambda text: None)
    if not rate > 0.0:
        raise ReplayError(f'--rate must be positive, not {rate}')
    inp = ReplayInput(path, head_topic)
    if inp.note:
        warn(inp.note)
    if inp.truncated:
        warn(inp.truncated_warning().replace('replaying', 'playing'))
    topics = {inp.head_topic: inp.head_type}
    if inp.layout is not None:
        topics.update({t: inp.topics[t] for t in inp.layout.frame_topics
                       if inp.topics.get(t) in HEAD_TYPES})
    try:
        samples = [(topic, msg, log_ns, stamp_ns(msg.header.stamp)) for topic, _, msg, log_ns
                   in inp.messages(topics)]
    except BagError as exc:
        raise ReplayError(str(exc)) from None
    if not any(topic == inp.head_topic for topic, *_ in samples):
        raise ReplayError(f'{inp.path}: no message on {inp.head_topic} could be read')
    node = rclpy.create_node('ponytail_replay', context=context)
    try:
        pubs = {topic: node.create_publisher(_message_class(type_name), topic,
                                             QoSProfile(depth=10))
                for topic, type_name in topics.items()}
        pub = pubs[inp.head_topic]
        clock_pub = node.create_publisher(Clock, '/clock', QoSProfile(depth=10)) if clock else None
        deadline = time.monotonic() + wait_for_subscribers
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        stop = stop or threading.Event()
        l0 = samples[0][2]
        duration = max(ns for _, _, ns, _ in samples) - l0
        period = int(1e9 / clock_hz) if clock_hz > 0 else None
        offset = 0
        clock_ns = -1
        sent = 0

        def send_clock(ns):
            nonlocal clock_ns
            if clock_pub is None or ns <= clock_ns:
                return
            clock_ns = ns
            clock_pub.publish(Clock(clock=Time(sec=ns // 1_000_000_000,
                                               nanosec=ns % 1_000_000_000)))

        while True:
            wall0 = time.monotonic()
            for topic, msg, log_ns, recorded_stamp_ns in samples:
                target = wall0 + (log_ns - l0) * 1e-9 / rate
                while True:
                    now = time.monotonic()
                    if stop.is_set() or not node.context.ok():
                        return sent
                    if now >= target:
                        break
                    if clock_pub is not None and period is not None:
                        send_clock(offset + min(l0 + int((now - wall0) * rate * 1e9), log_ns))
                        time.sleep(min(target - now, period * 1e-9))
                    else:
                        time.sleep(min(target - now, 0.05))
                send_clock(offset + log_ns)
                if restamp:
                    msg.header.stamp = node.get_clock().now().to_msg()
                elif offset:
                    ns = recorded_stamp_ns + offset
                    msg.header.stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
                pubs[topic].publish(msg)
                sent += topic == inp.head_topic
            if not loop:
                return sent
            offset += duration + (period or 10_000_000)
    finally:
        node.destroy_node()


# -- command line ------------------------------------------------------------------------------


def _parser():
    p = argparse.ArgumentParser(
        prog='ponytail_replay',
        description='Re-simulate a recording offline (-o), compare two runs (compare / '
                    '--compare), play its head poses into a running graph (--live), or repair a '
                    'cut-short or damaged recording (repair IN OUT).',
        epilog='Examples:  ponytail_replay run.mcap -o replayed.mcap --params config/ponytail.yaml'
               '   |   ponytail_replay compare run.mcap replayed.mcap --plot diff.png'
               '   |   ponytail_replay --live run.mcap'
               '   |   ponytail_replay repair killed.mcap fixed.mcap.  Exit status: 0 done, 2 bad '
               'or damaged input (one line naming the file and the problem), 1 unexpected error.')
    p.add_argument('inputs', nargs='+', metavar='INPUT.mcap',
                   help='the recording (two with --compare)')
    p.add_argument('-o', '--output', metavar='OUTPUT.mcap', help='replay: the new recording')
    p.add_argument('--params', metavar='FILE.yaml',
                   help='node parameters (default: the recorded ones, else the package config)')
    p.add_argument('--head-topic', help='head pose topic (default: the recorded node\'s, '
                                        'else /head_pose)')
    p.add_argument('--ticks', choices=('auto', 'recorded', 'nominal'), default='auto',
                   help='tick at the node\'s recorded tick times or every 1/rate s (default '
                        'auto: recorded when available and the rate is unchanged)')
    p.add_argument('--stamp-source', choices=('header', 'receive'),
                   help='time head poses by their header stamps or their log (receive) times, '
                        'over the parameters\' stamp_source (receive: stamps on another clock)')
    p.add_argument('--no-tf', action='store_true',
                   help='replay: do not record the segments as TF frames on /tf')
    p.add_argument('--tf-prefix', metavar='PREFIX',
                   help='replay: TF frames are PREFIX<chain>/<i> (default: as recorded, else '
                        'none)')
    p.add_argument('--look-ahead', action='store_true',
                   help='estimate the head from poses on both sides of each tick (no delay, '
                        'simulated-time stamps): the most accurate re-simulation of recorded '
                        'animation')
    p.add_argument('--overwrite', action='store_true', help='replace an existing OUTPUT')
    p.add_argument('-q', '--quiet', action='store_true',
                   help='no progress bar, no summary, no warnings')
    p.add_argument('--compare', action='store_true', help='compare two recordings A B')
    p.add_argument('--plot', metavar='OUT.png', help='compare: also plot (matplotlib)')
    p.add_argument('--live', action='store_true',
                   help='publish the head poses (and /clock) into the ROS graph at recorded pace')
    p.add_argument('--rate', type=float, default=1.0, help='live: pace factor (default 1)')
    p.add_argument('--no-clock', action='store_true', help='live: do not publish /clock')
    p.add_argument('--clock-rate', type=float, default=100.0, help='live: /clock Hz between '
                                                                   'poses (default 100)')
    p.add_argument('--restamp', action='store_true',
                   help='live: stamp the poses with this process\'s clock (nodes without '
                        'use_sim_time)')
    p.add_argument('--loop', action='store_true', help='live: loop (times keep increasing)')
    return p


def _repair_parser():
    p = argparse.ArgumentParser(
        prog='ponytail_replay repair',
        description='Rewrite a recording cut short (a killed writer: no summary, index or '
                    'footer) or damaged (changed bytes) as a complete, indexed MCAP file that '
                    'every reader opens (rosbags, mcap, ros2 bag), keeping every intact record '
                    'and saying what was lost.')
    p.add_argument('input', metavar='IN.mcap')
    p.add_argument('output', metavar='OUT.mcap')
    p.add_argument('--overwrite', action='store_true', help='replace an existing OUT')
    p.add_argument('-q', '--quiet', action='store_true', help='no summary')
    return p


def _check_plot_path(path) -> Optional[str]:
    """Why ``--plot`` cannot be written there, or None."""
    out = Path(path)
    if out.is_dir():
        return f'--plot {out}: is a directory, give a file name (e.g. diff.png)'
    if not out.parent.is_dir():
        return f'--plot {out}: folder {out.parent} does not exist'
    if not os.access(out.parent, os.W_OK):
        return f'--plot {out}: folder {out.parent} is not writable'
    return None


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of ``ponytail_replay``; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)

    def error(text):
        print(f'ponytail_replay: error: {text}', file=sys.stderr)
        return 2

    if argv and argv[0] == 'repair':
        return _main_repair(argv[1:], error)
    if argv and argv[0] == 'compare':
        argv = ['--compare'] + argv[1:]
    parser = _parser()
    args, ros_args = parser.parse_known_args(argv)
    if ros_args and not args.live:
        parser.error(f'unrecognized arguments: {" ".join(ros_args)}')

    def warn(text):
        if not args.quiet:
            print(f'ponytail_replay: warning: {text}', file=sys.stderr)

    modes = sum((args.compare, args.live, args.output is not None))
    if modes != 1:
        parser.error('give exactly one of -o OUTPUT (replay), --compare A B, --live INPUT')
    progress = None
    try:
        if args.compare:
            if len(args.inputs) != 2:
                parser.error('--compare takes two recordings: A B')
            if args.plot:
                problem = _check_plot_path(args.plot)
                if problem:
                    return error(problem)
            comps, *_, values_a, values_b = compare(*args.inputs)
            print(format_comparison(args.inputs[0], args.inputs[1], comps, values_a, values_b))
            if args.plot:
                try:
                    print(f'plot: {plot_comparison(comps, args.plot)}')
                except ImportError:
                    return error('--plot needs matplotlib (pip install matplotlib)')
                except (OSError, ValueError) as exc:
                    return error(f'--plot {args.plot}: cannot write it: '
                                 f'{getattr(exc, "strerror", None) or exc}')
            return 0
        if len(args.inputs) != 1:
            parser.error('give one input recording')
        if args.live:
            return _main_live(args, ros_args, warn, error)
        progress = _Progress(sys.stderr) if not args.quiet and sys.stderr.isatty() else None
        result = replay(args.inputs[0], args.output, params_file=args.params,
                        head_topic=args.head_topic, ticks=args.ticks, overwrite=args.overwrite,
                        progress=progress, warn=None if args.quiet else warn,
                        stamp_source=args.stamp_source, tf=not args.no_tf,
                        tf_prefix=args.tf_prefix, look_ahead=args.look_ahead)
        if not args.quiet:
            print(result.summary(args.inputs[0]))
        return 0
    except ReplayError as exc:
        return error(exc)
    except KeyboardInterrupt:
        return 130
    finally:
        if progress is not None:
            progress.close()


def _main_repair(argv, error) -> int:
    from .repair import RepairError, repair
    args = _repair_parser().parse_args(argv)
    try:
        result = repair(args.input, args.output, overwrite=args.overwrite)
    except RepairError as exc:
        return error(exc)
    for problem in result.damage:
        print(f'ponytail_replay: warning: {args.input}: skipped a damaged part: '
              f'{problem.describe(result.input_size)}', file=sys.stderr)
    if not args.quiet:
        print(result.summary(args.input))
    return 0


def _main_live(args, ros_args, warn, error) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    try:
        rclpy.init(args=['ponytail_replay'] + ros_args)
    except Exception as exc:  # noqa: BLE001 - malformed --ros-args
        return error(f'cannot start: {exc}')
    try:
        n = live_replay(args.inputs[0], head_topic=args.head_topic, rate=args.rate,
                        clock=not args.no_clock, clock_hz=args.clock_rate,
                        restamp=args.restamp, loop=args.loop, warn=warn)
        if not args.quiet:
            print(f'published {n} head poses from {args.inputs[0]}')
        return 0
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    except ReplayError as exc:
        return error(exc)
    except Exception:
        if rclpy.ok():
            raise
        return 0  # shut down by a signal in the middle of a publish
    finally:
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
