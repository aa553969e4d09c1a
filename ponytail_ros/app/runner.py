"""What the ponytail node does on each timer tick, without ROS: head pose samples in, chain out.

``ChainRunner`` owns the ``HeadEstimator`` (the head's velocity and acceleration from the pose
samples), one more per extra kinematic frame (``frames``: a forearm carrying a collider, ...),
and the ``Simulator``. The node only converts messages: its subscription callbacks call ``push``
/ ``push_frame`` (O(1): the sample is queued), its timer callback calls ``tick(t)`` with the
clock's time and publishes what comes back. Keeping this ROS-free makes it testable and
benchmarkable in simulated time.

Per tick, at node clock time ``t``:

1. the queued samples (at most ``max_queue`` per input; a flood overflows the queue, oldest
   first, and is counted as ``'queue_overflow'``) are checked in arrival order, the head's
   first, then each frame's in the order of ``frames``: frame, teleport (the head only), then
   ``HeadEstimator.add`` (NaN/inf, zero or non-unit quaternion, stamps backwards or repeated);
   every dropped sample is counted per reason in ``dropped`` (one counter for all inputs);
2. pending parameter changes are applied: tunable ones with ``Simulator.set_parameters``,
   structural ones by rebuilding the simulator at rest at the current head pose;
3. the head state (and every frame's) is estimated at ``t_head = t - delay`` and the chain
   advanced to it: ``sim.advance_frame(t_head, bodies_at(t_head))``. The elapsed time is
   whatever the clock says (late timers, skipped sim-time periods); at most
   ``solver.max_steps_per_call`` internal steps are taken, the rest is dropped and counted;
4. latency compensation (``latency_compensation``, on by default): every chain of the output is
   translated rigidly so that its root lies on the attachment point of the head estimated at
   ``t`` (extrapolating the newest samples), i.e. by the displacement of the attachment point
   over the delay (plus the < 1 internal step the chain lags behind ``t_head``): the root stays
   on the current head while the dynamics are driven by the delayed, smoother estimate. Segment
   geometry is unchanged (joints stay closed); the swing itself still lags by ``delay``.

Time: the node and the replay give times as integer ns (``seconds`` / ``tick_ns``); the runner
differences them from its origin, the first such time, before they become float seconds, so
that everything downstream (estimation, splines, anchor tables, the simulator) sees small
times and the result does not depend on the clock's epoch (float seconds since 1970 resolve
only ~0.2 µs, which a derivative estimate amplifies). ``push``/``tick`` take seconds on that
origin (the floats a caller without an ns clock passes as they are).

Sparse and broken head streams (``docs/head_input.md``): below ``SPARSE_RATE`` the head
stream is sparse (an animation exported at 5–24 Hz): said once through ``on_notice`` with the
measured rate; its pose-to-pose steps are judged as a teleport only beyond the thresholds per
``1/SPARSE_RATE`` of their interval (a speed, not a distance), the head is the cubic
interpolating the poses around ``t - delay`` (``_fit_for_rate``: a smoothing fit would change
at every new pose) and the output is the chain as simulated at ``t - delay`` (no latency
compensation: extrapolating a sparse stream by up to a period freezes the root, then jumps
it). With extra frames (one compiled fit for all) the frames follow the head's fit.

A stamp more than ``head.max_gap`` after the previous one is a gap, said through
``on_notice`` with its times: the head was held at its last pose across it (the estimator
braked, then held it) and the new history is held at its first pose before its first stamp,
so the chain resumes from the held pose without a whip.

Delay: ``delay = max(interpolation_delay, interpolation_delay_periods × input period)`` where
the input period is the median interval of the stored head samples (the longest of the head's
and those of the frames the scene uses, when there are frames): a delay of a period or two
puts samples on both sides of the evaluation time, which is what makes the velocity and
acceleration estimates smooth (``benchmarks/node_bench.py``, trade part, measures the
trade); the default, 2 periods, is 2 ms at 1 kHz, 17 ms at 120 Hz, 67 ms at 30 Hz.

Decisions (documented for the node):

* Start and resets at rest *relative to the anchor bodies*: every segment points along its rest
  direction and moves rigidly with its anchor body, with the body's estimated linear and
  angular velocity (``Simulator.reset`` with the estimated ``KinematicState``), never at rest
  in the world while the head runs. A new history (the first poses, or the history restarted
  by a teleport, a frame change or the clock going back) gives no velocity from one pose, so
  the runner waits: nothing is published until every input a chain hangs from holds
  ``START_SAMPLES`` (3) poses of its new history (2 input periods: 2 ms at 1 kHz, 67 ms at
  30 Hz) or is stale; then the chain starts at the first pose of that history (or at
  ``t - delay`` if that is later) and is advanced to ``t - delay`` in the same tick. A
  rebuild or a guard reset keeps the history, so it starts at once with the current estimate.
* Output stamp (``output_stamp``): ``tick`` labels the output with the tick time ``t`` while
  the chain is the one simulated at ``t - delay`` with its roots moved onto the head at ``t``
  (latency compensation): what a viewer should draw now. ``simulated`` labels the state with
  its own time (``TickOutput.t_state``), without compensation: what an analysis pairing
  messages by stamp (a bag comparison, a TF lookup) needs.

* Stale: no sample accepted during the last ``stale_timeout`` s of clock time (measured on the
  node clock, not by the stamps, so that it works whatever the stamps' time base).
* Frame: the frame of the first accepted pose (head or extra frame) is latched: it is the
  simulation's world frame, so every input must use it. A pose in another frame is dropped
  (``'frame_changed'``) while any input stream is live; once every input is stale a pose in a
  new frame is adopted, every input's history restarts and the chain is reset at rest there
  (reset reason ``'frame_changed'``): interleaved rogue publishers cannot poison the chain, a
  real switch recovers after ``stale_timeout``.
* Teleport: a pose farther than ``teleport_distance`` m or ``teleport_angle`` rad from the
  previous accepted one restarts the head history and resets the chain at rest at the new pose.
* Stale head: the estimator extrapolates for ``head.max_extrapolation``, braking to a stop, then
  holds the last pose; the chain keeps swinging and settles.
* Clock going backwards (a restarted ``/clock``, a looped bag): everything restarts as if new
  (reset reason ``'clock_backwards'``), the frames' histories too. A stream whose stamps went
  back for good (a publisher restarted with another time base) is re-adopted once the head is
  stale: the head history restarts, the chain carries on (counted in ``history_restarts``;
  before that, the samples are dropped as ``'stamp_backwards'``).
* A change of the delay (a setting, or the input rate) is slewed at ±50 % of the elapsed time,
  so the simulated head time never runs backwards and never jumps.

Extra frames (``frames``, kinematic bodies 1..F of the scene): each has its own queue
(``push_frame``) and ``HeadEstimator`` with the head's settings, and the same checks (dropped
samples counted in the same ``dropped`` by reason; a stream whose stamps went back for good is
re-adopted once it is stale, as the head's). A scene that uses a frame (a chain anchored to it,
a collider fixed in it) publishes nothing until that frame has a pose, as for the head; a stale
frame is extrapolated, then held, by its estimator like the head. A frame's teleport (a jump
beyond ``teleport_distance`` or ``teleport_angle``, as for the head) restarts that frame's
history and puts only the chains hanging from it at rest on its new pose
(``Simulator.reset_chains``, counted as ``'teleport'``, named in ``TickOutput.frames_reset``):
one character of a crowd respawning elsewhere does not drag its ponytail across the scene, nor
blow up and reset every other character with it. Nothing waits for new samples: the frame is
still at its new pose until its history gives it a velocity. A collider fixed in the frame
jumps with it; one that lands on other chains' segments is resolved by the contact position
stage, which pushes them out of it at most 0.25 rad per segment per pass, so a deep jump takes
several steps to clear.
"""
from collections import Counter, deque
from dataclasses import dataclass, fields, replace

import numpy as np

from ponytail_ros.core.head import KinematicState
from ponytail_ros.core.head_estimation import (
    REJECT_REASONS,
    RESTARTED,
    HeadEstimator,
    HeadEstimatorBank,
)
from ponytail_ros.core.simulator import Simulator, StepReport

__all__ = ['ChainRunner', 'RunnerSettings', 'TickOutput', 'DROP_REASONS', 'RESET_REASONS',
           'TUNABLE_CHAIN_FIELDS', 'TUNABLE_SCENE_FIELDS', 'structural_change', 'SPARSE_RATE']

#: Why a head pose sample may be dropped (counted per reason).
DROP_REASONS = tuple(REJECT_REASONS) + ('frame_changed', 'queue_overflow', 'frames_count')
#: Why the chain may be put back at rest.
RESET_REASONS = ('teleport', 'frame_changed', 'clock_backwards', 'rebuild', 'guard')

TUNABLE_CHAIN_FIELDS = ('damping', 'stiffness', 'drag_linear', 'drag_quadratic')
TUNABLE_SCENE_FIELDS = ('gravity', 'wind')

#: Slew rate of the effective interpolation delay (s of delay change per s of clock time).
DELAY_SLEW = 0.5

#: Poses a new input history (the first, or one restarted by a teleport, a frame change or the
#: clock going back) must hold before the chain starts on it: with three the estimate has a
#: velocity and angular velocity (a quadratic through them), so the chain can start moving
#: with its anchor body instead of at rest in the world. A stale input starts with what it has.
START_SAMPLES = 3
#: Resets after which the head history is new (the chain waits for ``START_SAMPLES``).
HISTORY_RESETS = ('teleport', 'frame_changed')
#: Below this measured input rate (Hz, the median interval of the stored head poses) the
#: head stream is sparse (module docstring); 28 rather than 30 so that a jittered 30 Hz stream
#: stays dense.
SPARSE_RATE = 28.0
#: Poses a history must hold before its rate is judged sparse or dense.
RATE_SAMPLES = 8
#: ``output_stamp`` values: what the stamp of the published state means.
OUTPUT_STAMPS = ('tick', 'simulated')


@dataclass
class RunnerSettings:
    """Input handling settings (all may change between ticks except ``max_queue`` and
    ``max_samples``).

    Attributes:
        interpolation_delay: s; minimum delay: the chain is simulated at ``t - delay``.
        interpolation_delay_periods: the delay is at least this many input periods.
        max_delay: s; cap of the delay.
        latency_compensation: translate the output chains by their attachment point's
            displacement from ``t - delay`` to ``t``.
        teleport_distance: m; a jump of the head pose beyond this resets the chain.
        teleport_angle: rad; a rotation of the head pose beyond this resets the chain.
        stale_timeout: s; no accepted sample for this long → the head is stale.
        max_queue: samples queued between ticks (bounded work per tick).
        output_stamp: ``'tick'``: the output is the chain at ``t - delay`` with its roots moved
            onto the head at ``t`` (``latency_compensation``), labelled ``t`` (for rendering
            now); ``'simulated'``: the chain exactly as simulated, labelled with its own time
            ``TickOutput.t_state`` (for analysis: pairs with the head by stamp); no latency
            compensation.
        window, degree, max_extrapolation, max_gap, quat_tolerance, max_samples: of the
            ``HeadEstimator``; ``min_samples``: its ``min_samples`` (0: ``degree + 3``).
    """

    interpolation_delay: float = 0.0
    interpolation_delay_periods: float = 2.0
    max_delay: float = 0.5
    latency_compensation: bool = True
    teleport_distance: float = 0.5
    teleport_angle: float = 1.0
    stale_timeout: float = 0.25
    max_queue: int = 256
    window: float = 0.1
    degree: int = 3
    max_extrapolation: float = 0.1
    max_gap: float = 0.5
    quat_tolerance: float = 1e-3
    max_samples: int = 128
    min_samples: int = 0
    output_stamp: str = 'tick'

    def estimator(self):
        return HeadEstimator(window=self.window, degree=self.degree, delay=0.0,
                             max_extrapolation=self.max_extrapolation, max_gap=self.max_gap,
                             quat_tolerance=self.quat_tolerance, max_samples=self.max_samples,
                             min_samples=self.min_samples or None)


@dataclass
class TickOutput:
    """What one tick produced (arrays are fresh copies).

    Attributes:
        t: tick time (node clock), s: runner time (from ``ChainRunner.origin_ns``, as every
            time here; ``ChainRunner.clock_seconds`` gives the clock's).
        t_head: head time the chain was advanced to, ``t - delay``, s.
        t_state: time of the chain state in ``origins``/``orientations`` before latency
            compensation, s: ``t_head``, or the previous frame's time when this tick was merged
            into the next (closer than one internal step). The honest stamp
            (``output_stamp: simulated``).
        frame_id: the head pose's frame (the simulation's world frame).
        origins: ``(n, 3)`` proximal joint of every segment, all chains concatenated (latency
            compensated if on).
        orientations: ``(n, 4)`` ``(x, y, z, w)``, local +X along the segment.
        report: the simulator's ``StepReport`` for this tick (steps, dropped time, max gap,
            guard reset reason).
        reset_reason: why the chain was put at rest this tick (``RESET_REASONS``) or None.
        head_stale: no sample accepted during the ``stale_timeout`` s before ``t``.
        newest_stamp: stamp of the newest accepted sample, s (runner time, as ``t``).
        accepted: samples accepted this tick.
        frames_reset: the frames that teleported this tick, whose chains alone were put at
            rest on their new poses (the others carried on), in the order of ``frames``.
    """

    t: float
    t_head: float
    frame_id: str
    origins: np.ndarray
    orientations: np.ndarray
    report: StepReport
    reset_reason: str | None
    head_stale: bool
    newest_stamp: float
    accepted: int
    t_state: float
    frames_reset: tuple = ()


def structural_change(old, new):
    """True if ``new`` differs from ``old`` (``Scene``s) in more than the tunable parameters."""
    if len(old.chains) != len(new.chains):
        return True
    strip_c = {f: 0.0 for f in TUNABLE_CHAIN_FIELDS}
    if any(replace(a, **strip_c) != replace(b, **strip_c)
           for a, b in zip(old.chains, new.chains, strict=True)):
        return True
    return (old.n_kinematic_bodies != new.n_kinematic_bodies or old.solver != new.solver
            or old.colliders != new.colliders)


class ChainRunner:
    """Head samples → estimator → simulator, one ``tick`` at a time (see the module docstring).

    Args:
        scene: a validated ``Scene``: kinematic body 0 is the head, bodies 1..F the extra
            ``frames``; a body F + 1, if the scene has one, is the static world (identity pose
            in the head pose's frame: chains hanging from a ceiling). A scene in which neither a
            chain nor a collider uses the head runs without any head pose (frame ``''`` until
            a pose arrives); one that uses a frame waits for that frame's first pose.
        settings: ``RunnerSettings`` (the frames' estimators use them too).
        frames: names of the extra kinematic frames (``push_frame(i, ...)`` feeds
            ``frames[i]``, body ``1 + i``); a name is only used in messages.
    """

    def __init__(self, scene, settings=None, frames=()):
        self.settings = settings or RunnerSettings()
        self.frames = tuple(str(f) for f in frames)
        self._check_bodies(scene)
        self.scene = scene
        self.estimator = self.settings.estimator()
        #: One ``HeadEstimator`` per extra frame.
        self.frame_estimators = [self.settings.estimator() for _ in self.frames]
        # With frames, all the inputs' fits at one time in one compiled call (a crowd's node).
        self._bank = (HeadEstimatorBank([self.estimator, *self.frame_estimators])
                      if self.frames else None)
        self.sim = None
        self.frame_id = None
        self._queue = deque(maxlen=max(1, int(self.settings.max_queue)))
        self._frame_queues = [deque(maxlen=self._queue.maxlen) for _ in self.frames]
        self._frames_queue = deque(maxlen=self._queue.maxlen)   # (push_frames: all at once)
        self._frame_last_accept = [None] * len(self.frames)
        # Stamp of the first sample of the current history of the head / of each frame.
        self._head_start = None
        self._frame_start = [None] * len(self.frames)
        #: Samples accepted per frame, since start.
        self.frame_accepted_total = [0] * len(self.frames)
        self._pending_scene = None
        self._pending_reset = None
        #: Frames (indices) that teleported since the last tick: their chains go to rest.
        self._pending_frame_resets = set()
        self._delay = None
        self._last_tick = None
        self._t_frame = None
        self._newest_stamp = None
        self._last_accept_tick = None
        #: Dropped samples per reason (``DROP_REASONS``), since start.
        self.dropped = Counter({r: 0 for r in DROP_REASONS})
        #: Chain resets per reason (``RESET_REASONS``), since start.
        self.resets = Counter({r: 0 for r in RESET_REASONS})
        self.accepted_total = 0
        #: Head histories restarted because the stamps went back for good (chain kept).
        self.history_restarts = 0
        self.dropped_time_total = 0.0
        self.ticks = 0
        self.last_reset = None
        #: Called as ``on_drop(reason, t_stamp, source)`` for every dropped sample (logging);
        #: ``source`` is ``'head'`` or the frame's name; ``t_stamp`` on the clock given
        #: (``clock_seconds``).
        self.on_drop = None
        #: Called as ``on_notice(key, text)`` when the head stream turns sparse (``'sparse'``,
        #: with the measured rate) or resumes after a gap (``'gap'``, with its times): said
        #: to the user (the node's terminal, the replay's warnings); the caller throttles.
        self.on_notice = None
        #: Integer ns of runner time 0 (``seconds``): the first ns time given, or None.
        self.origin_ns = None
        #: The head stream is sparse (None: not judged yet) and the gaps seen (count).
        self.head_sparse = None
        self._sparse_said = False
        self._head_period = None        # (the head's last known input period, s)
        self.gaps = 0

    # -- configuration ---------------------------------------------------------------------
    def set_scene(self, scene):
        """Use ``scene`` (validated) from the next tick: tunable differences are applied with
        ``Simulator.set_parameters``, anything else rebuilds the simulator at rest."""
        self._check_bodies(scene)
        self._pending_scene = scene

    def _check_bodies(self, scene):
        if scene.n_kinematic_bodies < 1 + len(self.frames):
            raise ValueError(f'the scene has {scene.n_kinematic_bodies} kinematic bodies; the '
                             f'head and {len(self.frames)} frames need at least '
                             f'{1 + len(self.frames)}')

    def update_settings(self, **changes):
        """Change settings live (not ``max_queue``/``max_samples``: fixed at construction)."""
        for k in ('max_queue', 'max_samples'):
            if k in changes and changes[k] != getattr(self.settings, k):
                raise ValueError(f'{k} cannot change while running')
        self.settings = replace(self.settings, **changes)
        s = self.settings
        for e in (self.estimator, *self.frame_estimators):
            e.window, e.degree = float(s.window), int(s.degree)
            e.min_samples = int(s.min_samples) or int(s.degree) + 3
            e.max_extrapolation, e.max_gap = float(s.max_extrapolation), float(s.max_gap)
            e.quat_tolerance = float(s.quat_tolerance)
        self._fit_for_rate()

    def _fit_for_rate(self):
        """The head estimator's fit for its stream's rate: the settings' (dense), or for a
        sparse stream the cubic interpolating the ``degree + 1`` poses around each instant
        (``min_samples = degree + 1``, ``window`` under a period). A smoothing fit over
        poses a period or more apart changes at every new pose, around instants the chain has
        already been simulated through; the interpolant at ``t - delay`` (two periods back)
        is fixed by poses that have all arrived. Exact animation poses assumed; the
        look-ahead spline is left alone."""
        e, s = self.estimator, self.settings
        if getattr(e, 'spline_degree', None):
            return
        e.window, e.min_samples = float(s.window), int(s.min_samples) or int(s.degree) + 3
        period = e.sample_period
        if self.head_sparse and period:
            e.window, e.min_samples = min(e.window, period), e.degree + 1

    @property
    def delay(self):
        """Effective interpolation delay (slewed towards its target), s."""
        return self.target_delay() if self._delay is None else self._delay

    def target_delay(self):
        """``max(interpolation_delay, interpolation_delay_periods × input period)``, capped; the
        input period is the head's, or the longest of it and the used frames'."""
        s = self.settings
        d = s.interpolation_delay
        period = self.estimator.sample_period
        if period is None:
            # A history restarted (a gap, a teleport) has no period yet: the stream's last.
            period = self._head_period
        else:
            self._head_period = period
        used = _used_frames(self.scene, len(self.frames))
        if self._banked():              # (a crowd's frames in one compiled call)
            periods = [self._bank.longest_sample_period([1 + i for i in used])] if used else []
        else:
            periods = [self.frame_estimators[i].sample_period for i in used]
        for p in periods:
            if p is not None and (period is None or p > period):
                period = p
        if period is not None and s.interpolation_delay_periods > 0.0:
            d = max(d, s.interpolation_delay_periods * period)
        return min(d, s.max_delay)

    @property
    def has_head(self):
        return len(self.estimator) > 0

    @property
    def needs_head(self):
        """Whether some chain or collider of the scene is fixed in the head (body 0)."""
        return 0 in _used_bodies(self.scene)

    def has_frame(self, i):
        """Whether frame ``i`` has an accepted pose."""
        return len(self.frame_estimators[i]) > 0

    def needs_frame(self, i):
        """Whether some chain or collider of the scene is fixed in frame ``i`` (body 1 + i)."""
        return 1 + i in _used_bodies(self.scene)

    def frame_stale(self, i, t):
        """No sample of frame ``i`` accepted during the last ``stale_timeout`` s before ``t``."""
        last = self._frame_last_accept[i]
        return last is None or t - last > self.settings.stale_timeout

    def stale_frames(self, t):
        """Indices of the frames the scene uses whose pose is stale at ``t`` (``frame_stale``),
        in order."""
        timeout = self.settings.stale_timeout
        last = self._frame_last_accept
        return [i for i in _used_frames(self.scene, len(self.frames))
                if last[i] is None or t - last[i] > timeout]

    def missing_inputs(self, scene=None):
        """The inputs ``scene`` (default: the current one) uses that have no pose yet:
        ``'head'`` and/or frame names. The runner publishes nothing while there is one."""
        used = _used_bodies(scene or self.scene)
        missing = ['head'] if 0 in used and not self.has_head else []
        return missing + [f for i, f in enumerate(self.frames)
                          if 1 + i in used and not self.has_frame(i)]

    def bodies_at(self, t):
        """The scene's kinematic bodies at head time ``t``: the estimated head, then each
        frame's estimate (each still at the origin while it has no pose), then the static world
        if the scene has it."""
        if self._banked():
            head = self._bank.states_at(t)
            return head.with_static_bodies(self.scene.n_kinematic_bodies - 1 - len(self.frames))
        head = (self.estimator.state_at(t) if self.has_head
                else KinematicState.still())
        if self.frames:
            states = [head] + [e.state_at(t) if len(e) else KinematicState.still()
                               for e in self.frame_estimators]
            head = KinematicState(*(np.concatenate([getattr(st, f.name) for st in states])
                                    for f in fields(KinematicState)))
        return head.with_static_bodies(self.scene.n_kinematic_bodies - 1 - len(self.frames))

    @property
    def newest_stamp(self):
        """Stamp of the newest accepted head pose on the clock given (``clock_seconds``: the
        stamp as the publisher wrote it, to ~0.2 µs at today's epoch), None without one;
        ``TickOutput.newest_stamp`` is the same in runner time."""
        return None if self._newest_stamp is None else self.clock_seconds(self._newest_stamp)

    def head_stale(self, t):
        """No sample accepted during the last ``stale_timeout`` s of clock time before ``t``."""
        return (self._last_accept_tick is None
                or t - self._last_accept_tick > self.settings.stale_timeout)

    def head_age(self, t):
        """``t`` minus the newest accepted stamp (s), None without samples."""
        return None if self._newest_stamp is None else t - self._newest_stamp

    def seconds(self, t_ns):
        """Runner time (s) of an integer-ns time: ``t_ns`` minus the origin (the first ns time
        given, ``origin_ns``), differenced as integers before it becomes a float."""
        t_ns = int(t_ns)
        if self.origin_ns is None:
            self.origin_ns = t_ns
        return (t_ns - self.origin_ns) * 1e-9

    def clock_seconds(self, t):
        """The clock's own seconds (for messages) of runner time ``t``."""
        return t if self.origin_ns is None else t + self.origin_ns * 1e-9

    def tick_ns(self, t_ns):
        """``tick`` at integer-ns clock time ``t_ns`` (``seconds``)."""
        return self.tick(self.seconds(t_ns))

    # -- input ---------------------------------------------------------------------------------
    def push(self, t, position, orientation, frame_id=''):
        """Queue a head pose sample (stamp ``t`` s, position ``(3,)``, quaternion ``(4,)``
        x, y, z, w, frame). Checked at the next tick; O(1)."""
        if len(self._queue) == self._queue.maxlen:
            self._drop('queue_overflow', self._queue[0][0])
        self._queue.append((t, position, orientation, frame_id))

    def push_frame(self, i, t, position, orientation, frame_id=''):
        """Queue a pose sample of frame ``i`` (``frames[i]``), as :meth:`push` does for the
        head; its ``frame_id`` must be the head poses' one. Checked at the next tick; O(1)."""
        queue = self._frame_queues[i]
        if len(queue) == queue.maxlen:
            self._drop('queue_overflow', queue[0][0], self.frames[i])
        queue.append((t, position, orientation, frame_id))

    def push_frames(self, t, poses, frame_id=''):
        """Queue one pose sample of every frame at stamp ``t`` (s): ``poses`` ``(F, 7)`` (x, y,
        z, qx, qy, qz, qw), row ``i`` that of ``frames[i]`` (one ``frames_topic`` message),
        each then treated as its :meth:`push_frame` would be. Another shape is dropped whole
        (``frames_count``). Checked at the next tick, all the frames in one compiled call when
        nothing but the samples' own checks is at stake (``HeadEstimatorBank.add_poses``)."""
        poses = np.array(poses, dtype=float)
        if poses.shape != (len(self.frames), 7):
            self.drop_frames('frames_count', t)
            return
        queue = self._frames_queue
        if len(queue) == queue.maxlen:
            t_old = queue[0][0]
            for name in self.frames:
                self._drop('queue_overflow', t_old, name)
        queue.append((t, poses, frame_id))

    def drop_frames(self, reason, t):
        """Count a batch of frame poses (``frames_topic``) dropped whole, e.g. for the wrong
        pose count (``frames_count``)."""
        self._drop(reason, t, 'frames')

    def _drop(self, reason, t, source='head'):
        self.dropped[reason] += 1
        if self.on_drop is not None:
            try:
                t = self.clock_seconds(float(t))
            except (TypeError, ValueError):
                pass                    # (a malformed stamp is reported as it came)
            self.on_drop(reason, t, source)

    def _notice(self, key, text):
        if self.on_notice is not None:
            self.on_notice(key, text)

    def head_rate(self):
        """The head's measured input rate (Hz, 1 / the median interval of its stored poses),
        None with fewer than two."""
        period = self.estimator.sample_period
        return None if not period else 1.0 / period

    def _judge_rate(self):
        """``head_sparse`` from the head history (from ``START_SAMPLES`` poses: the first
        output knows it); the turn to sparse said (``on_notice``) once the history holds
        ``RATE_SAMPLES`` poses, once per turn (back above ``SPARSE_RATE`` re-arms it)."""
        n = len(self.estimator)
        if n < START_SAMPLES:
            return
        rate = self.head_rate()
        sparse = rate < SPARSE_RATE
        if sparse != self.head_sparse or sparse:
            self.head_sparse = sparse
            self._fit_for_rate()
        if not sparse:
            if n >= RATE_SAMPLES:
                self._sparse_said = False
            return
        if n >= RATE_SAMPLES and not self._sparse_said:
            self._sparse_said = True
            head = f'Head poses arrive at {rate:.1f} Hz, below {SPARSE_RATE:g} Hz: a sparse stream'
            if getattr(self.estimator, 'spline_degree', None):      # (the look-ahead replay)
                text = (f'{head}; look-ahead splines the head through them (fine for exact '
                        f'animation poses); pose-to-pose steps are not teleports.')
            else:
                text = (f'{head}. Live, the head is the cubic through the poses around '
                        f'each instant, {1e3 / rate:.0f} ms apart (its velocity and '
                        f'acceleration are coarse), and the output is the chain at t - '
                        f'{self.target_delay():.3f} s (no latency compensation); pose-to-pose '
                        f'steps are not teleports. For exact animation poses replay offline '
                        f'with --look-ahead (a spline through them), or publish at 30 Hz or '
                        f'more.')
            self._notice('sparse', text)

    def _teleport_scale(self, t):
        """The teleport thresholds' factor for a pose at stamp ``t``: 1 on a dense stream; on
        a sparse one (or one not judged yet: its first poses), for an interval from the newest
        pose between ``1/SPARSE_RATE`` and ``max_gap``, the interval in units of
        ``1/SPARSE_RATE`` (a sparse stream's steps are judged as a speed). A dense stream's
        pause is no sparse step: a jump across it is judged as any."""
        last = self.estimator.last_stamp
        if last is None or self.head_sparse is False:
            return 1.0
        dt = t - last
        if dt * SPARSE_RATE <= 1.0 or dt > self.settings.max_gap:
            return 1.0
        return dt * SPARSE_RATE

    def _restart(self, reason):
        """Forget the head and the frames (histories, frame) and the chain; the next sample
        starts anew."""
        self.estimator.reset()
        self._reset_frames()
        self.sim = None
        self.frame_id = None
        self._newest_stamp = None
        self._last_accept_tick = None
        self._pending_reset = None
        self.resets[reason] += 1
        self.last_reset = reason

    def _reset_frames(self):
        for e in self.frame_estimators:
            e.reset()
        self._frame_last_accept = [None] * len(self.frames)
        self._pending_frame_resets.clear()      # (a reset of every chain follows)

    def _all_quiet(self, t_tick):
        """No input (head or frame) accepted a sample in the last ``stale_timeout`` s."""
        timeout = self.settings.stale_timeout
        return all(last is None or t_tick - last > timeout
                   for last in (self._last_accept_tick, *self._frame_last_accept))

    def _banked(self):
        """Whether the frames' estimators are the bank's (a replay may swap some out)."""
        return self._bank is not None and self._bank.holds([self.estimator,
                                                            *self.frame_estimators])

    def _drain(self, t_tick):
        accepted = self._drain_head(t_tick)
        self._drain_frames(t_tick)
        for i in range(len(self.frames)):
            self._drain_frame(i, t_tick)
        return accepted

    def _drain_frames(self, t_tick):
        """The queued ``push_frames`` batches, in order: a batch in the frame the runner is
        in goes through ``HeadEstimatorBank.add_poses`` (one call, the per-sample checks and
        stream restarts as :meth:`_take_frame_sample`'s); any other (the first, a frame
        change) row by row through :meth:`_take_frame_sample`."""
        queue = self._frames_queue
        while queue:
            t, poses, frame = queue.popleft()
            if self.frame_id is None or frame != self.frame_id or not self._banked():
                for i, row in enumerate(poses.tolist()):
                    self._take_frame_sample(i, t, row[:3], row[3:], frame, t_tick)
                continue
            timeout = self.settings.stale_timeout
            restart = [last is None or t_tick - last > timeout
                       for last in self._frame_last_accept]
            self._frame_teleports(t, poses)
            outcome = self._bank.add_poses(1, t, poses, restart)
            for i, o in enumerate(outcome):
                if o >= 0:
                    self._drop(REJECT_REASONS[o], t, self.frames[i])
                    continue
                if o == RESTARTED:
                    self.history_restarts += 1
                if len(self.frame_estimators[i]) == 1:
                    self._frame_start[i] = t
                self._frame_last_accept[i] = t_tick
                self.frame_accepted_total[i] += 1

    def _frame_teleports(self, t, poses):
        """The frames whose row of ``poses`` ``(F, 7)`` at stamp ``t`` is a teleport from their
        newest sample (as :meth:`_take_frame_sample` tests one): their histories restart,
        their chains are reset at the next tick. A vectorised test with a 1 % margin picks
        the candidates; each is then tested exactly as one sample is."""
        s = self.settings
        ests = self.frame_estimators
        ns = np.array([e._n for e in ests], dtype=np.int64)
        if not ns.any():
            return
        rows = np.arange(len(ests))
        last = np.maximum(ns - 1, 0)
        bank = self._bank
        p_last, q_last = bank._p[1 + rows, last], bank._q[1 + rows, last]
        poses = np.asarray(poses, dtype=float)
        with np.errstate(invalid='ignore', divide='ignore'):
            dist = np.linalg.norm(poses[:, :3] - p_last, axis=1)
            q = poses[:, 3:] / np.linalg.norm(poses[:, 3:], axis=1)[:, None]
            cos = np.minimum(np.abs(np.sum(q * q_last, axis=1)), 1.0)
            angle = 2.0 * np.arccos(cos)
            near = (dist > 0.99 * s.teleport_distance) | (angle > 0.99 * s.teleport_angle)
        for i in np.flatnonzero(near & (ns > 0)).tolist():
            checked = ests[i].check(t, poses[i, :3], poses[i, 3:])
            if checked[3] is None and ests[i].jumped(checked[1], checked[2],
                                                     s.teleport_distance, s.teleport_angle):
                ests[i].reset()
                self._pending_frame_resets.add(i)

    def _drain_head(self, t_tick):
        """The head's queued samples, in arrival order; how many were accepted."""
        accepted = 0
        # Quiet: no head sample accepted for ``stale_timeout`` before this tick, so a stream
        # whose stamps went back may be adopted (until one of this tick's is accepted).
        quiet = (self._last_accept_tick is None
                 or t_tick - self._last_accept_tick > self.settings.stale_timeout)
        queue = self._queue
        while queue:
            if self._take_head_sample(*queue.popleft(), t_tick, quiet):
                accepted += 1
                quiet = False
        self.accepted_total += accepted
        if accepted:
            self._judge_rate()
        return accepted

    def _take_head_sample(self, t, p, q, frame, t_tick, quiet):
        """One head sample checked and added (or dropped, counted); True if accepted. A pose in
        another frame is adopted only while every input is quiet (the world frame changes:
        every history restarts); a teleport or a stream restart restarts the head's."""
        est = self.estimator
        checked = est.check(t, p, q)            # (the values checked once, here)
        valid = checked[3] is None
        if valid:
            t, p, q = checked[:3]
        if self.frame_id is not None and frame != self.frame_id:
            if not (valid and self._all_quiet(t_tick)):
                self._drop('frame_changed', t)
                return False
            restart = 'frame_changed'
            self._reset_frames()      # in the old frame (all stale)
        else:
            restart = self._history_break(t, p, q, quiet) if valid else None
        if restart is not None:
            self._restart_head_history(restart)
        reason = est.add_checked(checked)
        if reason is not None:
            self._drop(reason, t)
            return False
        if len(est) == 1:
            self._head_start = est.last_stamp
        self._last_accept_tick = t_tick
        if self.frame_id is None or restart == 'frame_changed':
            self.frame_id = frame
        self._newest_stamp = est.last_stamp
        return True

    def _history_break(self, t, p, q, quiet):
        """Why a valid head pose (stamp ``t``, position ``p``, unit quaternion ``q``, in the
        runner's frame) breaks the head history: ``'teleport'``, ``'stream_restart'`` or None.
        A pose resuming after a gap keeps the history; the gap is counted and said."""
        est = self.estimator
        if est.jumped(p, q, *self._teleport_thresholds(t)):
            return 'teleport'
        last = est.last_stamp
        if last is None:
            return None
        if quiet and t < last:
            # The stream restarted with an earlier time base (a publisher restarted, a bag
            # replayed without sim time): adopt it, keep the chain.
            return 'stream_restart'
        if t - last > self.settings.max_gap:
            self._gap(last, t)
        return None

    def _restart_head_history(self, restart):
        """Forget the head's history for ``restart`` (a ``_history_break`` reason or
        ``'frame_changed'``): a stream restart keeps the chain (counted in
        ``history_restarts``), the others reset it at the next tick."""
        self.estimator.reset()
        if restart == 'stream_restart':
            self.history_restarts += 1
        else:
            self._pending_reset = restart

    def _teleport_thresholds(self, t):
        """``(distance, angle)`` of the teleport test of a head pose at stamp ``t``."""
        k = self._teleport_scale(t)
        return self.settings.teleport_distance * k, self.settings.teleport_angle * k

    def _gap(self, t_last, t_next):
        """A head stream resuming at stamp ``t_next`` after its newest pose at ``t_last``,
        more than ``max_gap`` before: counted and said."""
        self.gaps += 1
        a, b = self.clock_seconds(t_last), self.clock_seconds(t_next)
        self._notice('gap', f'Head poses resumed after a gap of {t_next - t_last:.3f} s '
                            f'(stamps {a:.3f} s to {b:.3f} s, head.max_gap '
                            f'{self.settings.max_gap:g} s): the chain held the last head pose '
                            f'across it; {self.gaps} gap(s) so far')

    def _drain_frame(self, i, t_tick):
        """Frame ``i``'s queued samples, as :meth:`_drain_head` (a teleport resets only the
        chains hanging from the frame)."""
        queue = self._frame_queues[i]
        while queue:
            self._take_frame_sample(i, *queue.popleft(), t_tick)

    def _take_frame_sample(self, i, t, p, q, frame, t_tick):
        """One sample of frame ``i`` checked and added (or dropped, counted)."""
        est, name = self.frame_estimators[i], self.frames[i]
        checked = est.check(t, p, q)
        valid = checked[3] is None
        if valid:
            t = checked[0]
        adopt = False
        if self.frame_id is not None and frame != self.frame_id:
            if not (valid and self._all_quiet(t_tick)):
                self._drop('frame_changed', t, name)
                return
            # Every input stale: the world frame changes. Every history restarts (all in the
            # old frame) and the chain is reset at rest in the new one.
            adopt = True
            self.estimator.reset()
            self._reset_frames()
            self._newest_stamp = None
            self._pending_reset = 'frame_changed'
        elif valid and est.jumped(checked[1], checked[2], self.settings.teleport_distance,
                                  self.settings.teleport_angle):
            est.reset()
            self._pending_frame_resets.add(i)
        elif (valid and self.frame_stale(i, t_tick) and est.last_stamp is not None
              and t < est.last_stamp):
            est.reset()                   # the stream restarted with an earlier time base
            self.history_restarts += 1
        reason = est.add_checked(checked)
        if reason is not None:
            self._drop(reason, t, name)
            return
        if len(est) == 1:
            self._frame_start[i] = est.last_stamp
        self._frame_last_accept[i] = t_tick
        self.frame_accepted_total[i] += 1
        if self.frame_id is None or adopt:
            self.frame_id = frame

    # -- the tick ------------------------------------------------------------------------------
    def tick(self, t):
        """Advance to node clock time ``t`` (s); ``TickOutput``, or None while an input the
        scene uses (the head, a frame) has no accepted pose yet (``missing_inputs``), or, at
        a start or after a teleport or frame change, while an input a chain hangs from has
        fewer than ``START_SAMPLES`` poses of its new history (and is not stale)."""
        t = float(t)
        elapsed = self._clock_to(t)
        accepted = self._drain(t)
        starting = self.sim is None or self._pending_reset in HISTORY_RESETS
        if not self._inputs_ready(t, starting):
            return None
        self.ticks += 1
        t_head = t - self._slew_delay(elapsed)
        scene, rebuild = self._take_pending_scene()
        head = self._head_at(t_head, t)
        if self.sim is None or rebuild or self._pending_reset is not None:
            frames_reset = ()
            report, reset_reason = self._start_chain(t_head, head, scene, rebuild, starting)
        else:
            reset_reason = None
            report, frames_reset = self._carry_chain_on(t_head, head, scene)
        reset_reason = self._count_reset(report, reset_reason)
        origins, quats = self._output_poses(t, t_head, head)
        return TickOutput(
            t=t, t_head=t_head, frame_id=self.frame_id or '', origins=origins,
            orientations=quats, report=report, reset_reason=reset_reason,
            head_stale=self.head_stale(t),
            newest_stamp=self._newest_stamp, accepted=accepted, t_state=self._t_frame,
            frames_reset=frames_reset)

    def _clock_to(self, t):
        """Take the clock to ``t``; the clock time elapsed since the last tick, s (0 at the
        first). A clock going back restarts everything (``'clock_backwards'``)."""
        if self._last_tick is not None and t < self._last_tick:
            self._restart('clock_backwards')
            self._delay = None
        elapsed = 0.0 if self._last_tick is None else t - self._last_tick
        self._last_tick = t
        return elapsed

    def _inputs_ready(self, t, starting):
        """Whether the chain can be simulated at ``t``: every input the scene (the pending one,
        if any) uses has a pose, and when ``starting`` a new history, every input a chain hangs
        from holds ``START_SAMPLES`` poses of it (a velocity estimate) or is stale. While not,
        nothing is published and a pending reset or scene stays pending."""
        scene = self._pending_scene or self.scene
        if self.missing_inputs(scene):
            return False
        return not starting or self._ready(t, scene)

    def _slew_delay(self, elapsed):
        """The delay for this tick, s: the target at a (re)start, else moved towards it by at
        most ``DELAY_SLEW × elapsed`` (the simulated head time neither runs back nor jumps)."""
        target = self.target_delay()
        if self._delay is None or self.sim is None:
            self._delay = target
        else:
            step = DELAY_SLEW * elapsed
            self._delay += min(max(target - self._delay, -step), step)
        return self._delay

    def _take_pending_scene(self):
        """``(scene, rebuild)``: the scene set since the last tick (None if none) and whether it
        needs the simulator rebuilt. A structural change takes effect here, before the head is
        evaluated (it may add the world body); a tunable one is applied to the running
        simulator later."""
        scene = self._pending_scene
        self._pending_scene = None
        rebuild = scene is not None and (self.sim is None or structural_change(self.scene, scene))
        if rebuild:
            self.scene = scene
        return scene, rebuild

    def _head_at(self, t_head, t):
        """The anchor bodies at head time ``t_head`` (``bodies_at``); the head's fit at every
        instant this tick asks for (the frame, its start, the clock's) made first in one
        compiled call."""
        if self.has_head and not self._banked():
            self.estimator.prefetch((t_head, t) if self.sim is None else
                                    (t_head, self._t_frame, t))
        return self.bodies_at(t_head)

    def _start_chain(self, t_head, head, scene, rebuild, starting):
        """(Re)start the chain at rest relative to the anchor bodies, moving with their
        estimated velocity and angular velocity (after a new history, from its first pose),
        and advance it to ``t_head``; ``(report, reset reason)`` (None at the first start).
        Every chain is put at rest, so the frames' teleports pending are done with."""
        self._pending_frame_resets.clear()
        t0 = self._start_time(t_head) if starting else t_head
        head0 = head if t0 == t_head else self.bodies_at(t0)
        reset_reason = None
        if self.sim is None or rebuild:
            if self.sim is not None:
                reset_reason = 'rebuild'
            self.sim = Simulator(self.scene, head=head0, t0=t0)
        else:
            if scene is not None:
                self._apply_tunables(scene)     # not structural
            reset_reason = self._pending_reset
            self.sim.reset(head0, t0)
        self._t_frame = t0
        self._pending_reset = None
        if t_head - t0 >= self.sim.dt:
            return self._advance(t_head, head, head0), reset_reason
        return StepReport(), reset_reason

    def _carry_chain_on(self, t_head, head, scene):
        """The running chain, with a tunable ``scene`` change (or None) applied and the chains
        of the frames that teleported put at rest, advanced to ``t_head``; ``(report, names of
        those frames)``."""
        if scene is not None:
            self._apply_tunables(scene)     # not structural
        frames_reset = self._reset_teleported()
        if t_head - self._t_frame >= self.sim.dt:
            # Frames closer than one internal step are merged into the next: the core's
            # anchor track between two frames extrapolates up to a step beyond them, which
            # explodes for a vanishing frame interval.
            return self._advance(t_head, head, self.bodies_at(self._t_frame)), frames_reset
        return StepReport(), frames_reset

    def _count_reset(self, report, reset_reason):
        """The tick's reset reason, counted: ``'guard'`` if the simulator's guard reset the
        chain (the start or reset it ran after counted too); the report's ``max_gap`` and the
        dropped time total completed."""
        if report.reset_reason is not None:
            if reset_reason is not None:
                self.resets[reset_reason] += 1
            reset_reason = 'guard'
        self._pending_reset = None
        if reset_reason is not None:
            self.resets[reset_reason] += 1
            self.last_reset = (reset_reason if reset_reason != 'guard'
                               else f'guard: {report.reset_reason}')
            if report.max_gap == 0.0:
                report.max_gap = float(np.max(self.sim.joint_gaps()))
        self.dropped_time_total += report.dropped_time
        return reset_reason

    def _output_poses(self, t, t_head, head):
        """``(origins, orientations)`` of the segments to publish: the chain at the frame time
        itself (not up to one internal step behind it), latency compensated when on (a dense
        stream, ``output_stamp: tick``)."""
        origins, quats = self.sim.segment_poses(self._t_frame)
        if (self.settings.latency_compensation and self.settings.output_stamp == 'tick'
                and not self.head_sparse):
            # Each chain's root (segment 1's proximal joint, on the anchor at the chain's time)
            # moved onto the attachment point of the head estimated at t.
            m = self.sim.model
            now = self.sim.anchors(head if t_head == t else self.bodies_at(t))
            origins += (now.position - origins[m.chain_start])[m.chain_of]
        return origins, quats

    def _reset_teleported(self):
        """The chains hanging from the frames that teleported put at rest on their new poses
        (the bodies at the last frame's time: the start of this tick's anchor track); returns
        those frames' names."""
        if not self._pending_frame_resets:
            return ()
        done = sorted(self._pending_frame_resets)
        self._pending_frame_resets.clear()
        bodies = {1 + i for i in done}
        chains = [c for c, spec in enumerate(self.scene.chains) if spec.anchor_body in bodies]
        if chains:
            self.sim.reset_chains(chains, self.bodies_at(self._t_frame))
        names = tuple(self.frames[i] for i in done)
        self.resets['teleport'] += len(names)
        self.last_reset = 'teleport: ' + ', '.join(names)
        return names

    def _advance(self, t_head, head, head_prev):
        """``sim.advance_frame`` to ``t_head``; both ends of the frame from this tick's
        estimate (``head_prev``: the bodies at the previous frame's time): the refit estimate
        disagrees slightly with the previous tick's, and bridging that within one frame would
        be an acceleration spike."""
        report = self.sim.advance_frame(t_head, head, head_prev=head_prev)
        self._t_frame = t_head
        return report

    def _anchor_inputs(self, scene=None):
        """``(estimator, history start, stale(t))`` of the inputs some chain of ``scene``
        (default: the current one) hangs from: the bodies whose motion the chain starts with
        (a collider's body does not enter the start)."""
        scene = scene or self.scene
        anchors = {c.anchor_body for c in scene.chains}
        out = []
        if 0 in anchors:
            out.append((self.estimator, self._head_start, self.head_stale))
        for i in range(len(self.frames)):
            if 1 + i in anchors:
                out.append((self.frame_estimators[i], self._frame_start[i],
                            lambda t, i=i: self.frame_stale(i, t)))
        return out

    def _ready(self, t, scene):
        """Every input a chain of ``scene`` hangs from holds ``START_SAMPLES`` poses, or is
        stale."""
        return all(len(e) >= START_SAMPLES or stale(t)
                   for e, _, stale in self._anchor_inputs(scene))

    def _start_time(self, t_head):
        """Where a (re)start begins: the first pose of the newest used history when it is
        before ``t_head`` (so a replay starts where its poses do), else ``t_head``."""
        starts = [s for _, s, _ in self._anchor_inputs() if s is not None]
        return min(max(starts), t_head) if starts else t_head

    def _apply_tunables(self, scene):
        old = self.scene
        if tuple(scene.gravity) != tuple(old.gravity) or tuple(scene.wind) != tuple(old.wind):
            self.sim.set_parameters(gravity=scene.gravity, wind=scene.wind)
        for i, (a, b) in enumerate(zip(old.chains, scene.chains, strict=True)):
            changed = {f: getattr(b, f) for f in TUNABLE_CHAIN_FIELDS
                       if getattr(a, f) != getattr(b, f)}
            if changed:
                self.sim.set_parameters(chain=i, **changed)
        self.scene = scene


def _used_bodies(scene):
    """Indices of the kinematic bodies some chain hangs from or some collider is fixed in
    (a frozenset; asked every tick, so kept for the last scene: a ``Scene`` is immutable)."""
    if _USED[0] is not scene:
        _USED[:] = [scene, frozenset({c.anchor_body for c in scene.chains}
                                     | {c.body for c in scene.colliders if c.body is not None})]
    return _USED[1]


_USED: list = [None, frozenset()]


def _used_frames(scene, n_frames):
    """Indices ``i`` of the extra frames (bodies ``1 + i``) the scene uses."""
    used = _used_bodies(scene)
    return [i for i in range(n_frames) if 1 + i in used]

