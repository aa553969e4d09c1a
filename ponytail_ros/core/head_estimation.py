"""Head pose, velocity and acceleration from timestamped pose samples.

The head arrives as ``geometry_msgs/PoseStamped`` at 30–1000 Hz, irregular and jittery, but the
solver needs the head's pose *and* its linear/angular velocity and acceleration (Eq. 1–3 of
``head.py``) at the simulation tick time, which never coincides with a sample. ``HeadEstimator``
keeps a bounded window of recent samples of one kinematic body and estimates all of them by a
local weighted least-squares polynomial fit in time (LOESS: a Savitzky–Golay filter for
irregular stamps):

* position: ``p(t) ≈ Σ c_k τ^k`` per axis;
* orientation: each sample's rotation vector relative to a reference orientation, composed on the
  left (world frame), ``q_i = exp(φ_i) ⊗ q_ref``, with ``q_ref`` the stored sample nearest the
  evaluation time so that ``|φ|`` stays small; ``φ(t)`` is fitted like the position and

      q = exp(φ) ⊗ q_ref,   ω = J_l(φ) φ̇,   α = J_l(φ) φ̈ + J̇_l(φ, φ̇) φ̇

  with ``J_l`` the exact left Jacobian of SO(3), so nothing is lost to a small-angle
  approximation.

Units and frames: time in s, positions in m, quaternions scalar-last ``(x, y, z, w)`` body to
world (as ``rotations.py``), velocities in m/s and rad/s, accelerations in m/s² and rad/s², and
angular velocity/acceleration in the WORLD frame (as ``KinematicState``). The estimator does not
know about frames beyond that: feed it poses all expressed in the simulation's world frame.

Latency versus smoothness. Evaluating at the newest sample (``delay = 0``) means a one-sided fit,
extrapolated between samples up to one sample period: its derivatives have the largest noise gain
and model error. Evaluating ``delay`` seconds in the past puts samples on both sides of the
evaluation time, which cuts both, at the price of a pure latency of ``delay`` (the whole returned
state is the head's state at ``t - delay``). Widening ``window`` averages noise out (the
acceleration's noise gain falls as window^-2.5 at a given rate) but smooths real motion (a cubic's
relative acceleration bias is ≈ 0.07–0.10·(ΩW)² for motion at angular frequency Ω).
``ponytail_ros/bench/head_estimation_bench.py`` measures the trade. Relative RMS errors for a
head swaying at 1.5 Hz and yawing at 0.8 Hz, ±20 % stamp jitter, the defaults:

    rate   delay        exact samples            0.1 mm / 1 mrad noise
                    v     a     ω     α         v     a     ω     α       (%)
    30 Hz  0       8.0  34    1.3  10.5       9.6  36    7.6  37
           1 T     1.4  13    0.2   4.1       2.4  16    2.9  23
           2 T     0.9   2.9  0.2   0.9       1.3   5.2  1.3  12
    120 Hz 0       0.6   6.5  0.1   1.9       7.9  45   11   121
           1 T     0.3   4.7  0.0   1.4       4.3  30    6.1  79
           2 T     0.1   3.1  0.0   0.9       2.3  20    3.4  52
    1000Hz 0       0.5   6.2  0.1   1.8       2.3  14    3.7  41

Defaults: degree 3 (a quadratic's one-sided acceleration lags by ~half the window: 33 % at
120 Hz; a quartic amplifies noise ~3× more), ``window = 0.1 s`` (acceleration within ~5 % on
exact data at ≥ 60 Hz with a one-period delay), ``delay = 0`` (no latency unless asked for: the
node should set one or two ``sample_period`` for low-rate streams). For noisy tracker data
(mocap, VR) use ``window`` 0.15–0.2 s and a delay of 1–2 periods: at 120 Hz with 1 mrad noise
that brings α from 79 % to 18–32 %.

Look-ahead (offline, every sample known, ``ponytail_replay --look-ahead``): with samples on
both sides of the evaluation time and ``min_samples = degree + 1`` the fit interpolates the
nearest ``degree + 1`` poses, a centred finite-difference stencil of that order for the
derivatives: for exact, smooth animation poses the error falls as (Ω·period)^(degree - 1) for
the acceleration, so high degrees (the replay uses 9) recover the head's derivatives almost
exactly; on noisy or kinked poses a high degree rings and amplifies the noise (use the
smoothing defaults instead). ``ponytail_ros/bench/pose_bench.py`` measures both modes.

Time origin: stamps are float seconds on any origin, but the fit differences them, so give
them on a near origin (``ChainRunner`` passes seconds since its first integer-ns time): float
seconds since 1970 resolve only ~0.2 µs, a stamp error that an interpolating fit's
derivatives amplify by orders of magnitude (``pose_bench --epoch``).

A history restarted after a gap (or a new one) holds its oldest pose at rest before its
oldest stamp: the head held until its stream resumed.

Stale streams: between the newest sample and ``max_extrapolation`` after it the fit is
extrapolated, for the first half at full speed, then time is smoothly braked (a C² time warp) so
that velocity and acceleration decay to exactly zero at ``t_last + max_extrapolation``; later the
head is held at that pose with zero derivatives ("stale head: the last pose is held"). Pose,
velocity and acceleration stay continuous when the stream stops. From ``max_gap`` after the
newest sample (a gap: the next sample starts a new history) the held pose returns, C², over
``max_extrapolation`` to the newest sample's and is held there: across a gap the head is held
at the last pose the stream gave, not at an extrapolation of it, so that a stream resuming
where it stopped (a paused animation, a stalled publisher) resumes without a jump.

ROS-free: numpy and the core only.
"""
import math

import numpy as np

from .head import KinematicState
from .head_kernels import (
    ACCEPTED,
    FIT_SIZE,
    add_samples,
    fit_time as kernel_fit_time,
    fits_at,
    loess_fit,
    longest_median_interval,
    median_interval,
    states_fit,
)

__all__ = ['HeadEstimator', 'HeadEstimatorBank', 'REJECT_REASONS', 'ACCEPTED', 'RESTARTED',
           'fit_state', 'MEMO_SIZE']

#: ``HeadEstimator.state_at``'s memo: the states of the last few times asked (or prefetched).
MEMO_SIZE = 4

#: ``HeadEstimatorBank.add_poses``' outcome of a sample accepted as the first of a restarted
#: history (``ACCEPTED``: accepted).
RESTARTED = -2

#: Every reason code ``HeadEstimator.add`` may return.
REJECT_REASONS = (
    'malformed',            # not convertible to float arrays of shape (3,) / (4,) and a scalar
    'nonfinite',            # NaN or inf in the stamp, position or orientation
    'zero_quaternion',      # |q| below 1e-9 (e.g. an uninitialised message)
    'non_unit_quaternion',  # | |q| - 1 | above ``quat_tolerance``
    'stamp_backwards',      # older than the newest accepted sample
    'stamp_repeated',       # within ``min_interval`` of the newest accepted sample
)


class HeadEstimator:
    """Pose, velocity and acceleration of one kinematic body from timestamped pose samples.

    Args:
        window: s. Samples within ``window`` of the evaluation time enter the fit (with delay 0
            that is the last ``window`` seconds). Default 0.1 s.
        degree: degree of the polynomial in time (default 3: with a one-sided fit a quadratic's
            acceleration lags by about half the window; see the benchmark).
        delay: s, ≥ 0. ``state_at(t)`` returns the state at ``t - delay`` (latency for smoother
            derivatives). Default 0.
        max_extrapolation: s. How far past the newest sample the fit may be extrapolated; the
            velocities are braked to zero over its second half, then the pose is held.
            Default 0.1 s.
        min_samples: the fit uses at least this many samples (the nearest ones, widening the
            window at low rates) when available. Default ``degree + 3``. With fewer stored
            samples the degree drops to ``n - 1`` (1 sample: that pose, zero derivatives;
            2: linear).
        max_samples: cap of the stored history (default 128, so that at 1000 Hz the whole
            ``window`` of 100 samples enters the fit; a cap of 64 shrinks it to 64 ms there:
            half the bias on exact data, twice the acceleration noise).
        max_gap: s. A sample arriving more than this after the previous one drops the older
            history (the motion across such a gap is unknown; fitting across it would invent
            velocities). Default 0.5 s.
        quat_tolerance: accepted ``| |q| - 1 |``; accepted quaternions are renormalised. Default
            1e-3 (float32-quantised quaternions pass, garbage does not).
        min_interval: s. A stamp within this of the newest sample is ``'stamp_repeated'``
            (default 1 µs; two poses closer in time carry no usable velocity).

    Weights: tricube ``(1 - |t_i - t_e|³/H³)³`` with the bandwidth ``H`` the larger of
    ``window`` and the distance to the ``(min_samples + 1)``-th nearest sample (a
    k-nearest-neighbour LOESS at low rates). Samples thus enter and leave the fit with
    zero weight: between sample arrivals the estimate is a continuous function of ``t``.
    """

    def __init__(self, window=0.1, degree=3, delay=0.0, max_extrapolation=0.1, min_samples=None,
                 max_samples=128, max_gap=0.5, quat_tolerance=1e-3, min_interval=1e-6):
        if window <= 0.0:
            raise ValueError('window must be positive')
        if degree < 0:
            raise ValueError('degree must be >= 0')
        if delay < 0.0:
            raise ValueError('delay must be >= 0')
        if max_extrapolation < 0.0:
            raise ValueError('max_extrapolation must be >= 0')
        self.window = float(window)
        self.degree = int(degree)
        self.delay = float(delay)
        self.max_extrapolation = float(max_extrapolation)
        self.min_samples = int(min_samples) if min_samples is not None else self.degree + 3
        self.max_samples = int(max(max_samples, 2, self.min_samples))
        self.quat_tolerance = float(quat_tolerance)
        self.min_interval = float(min_interval)
        self.max_gap = float(max_gap)
        self._t = np.empty(self.max_samples)
        self._p = np.empty((self.max_samples, 3))
        self._q = np.empty((self.max_samples, 4))
        self._n = 0
        # ``state_at`` of the last few times, valid while the history and settings hold: a
        # tick asks for the same instants several times (the frame, its start, the bodies).
        self._memo = {}
        self._version = 0
        self._period = (-1, 0.0)            # (version, sample_period) of the last asked
        #: Count of rejected samples per reason code (diagnostics).
        self.rejected = {r: 0 for r in REJECT_REASONS}

    # -- history -------------------------------------------------------------------------------

    def __len__(self):
        return self._n

    @property
    def last_stamp(self):
        """Stamp (s) of the newest accepted sample, ``None`` if there is none."""
        return float(self._t[self._n - 1]) if self._n else None

    @property
    def last_pose(self):
        """``(position (3,), orientation (4,))`` of the newest accepted sample, or ``None``."""
        if not self._n:
            return None
        return self._p[self._n - 1].copy(), self._q[self._n - 1].copy()

    @property
    def sample_period(self):
        """Median interval (s) of the stored samples, ``None`` with fewer than 2: a natural
        ``delay`` is one or two of these."""
        if self._n < 2:
            return None
        if self._period[0] != self._version:        # (asked every tick; new samples change it)
            self._period = (self._version, float(median_interval(self._t, self._n)))
        return self._period[1]

    def reset(self):
        """Forget the history (after a teleport): the next accepted sample starts anew."""
        self._n = 0
        self._version += 1

    def is_stale(self, t, timeout):
        """True when no sample is stored or the newest is more than ``timeout`` s before ``t``."""
        return self._n == 0 or (t - self._t[self._n - 1]) > timeout

    def _reject(self, reason):
        self.rejected[reason] += 1
        return reason

    def _check_pose(self, position, orientation):
        """``(p, q, None)`` validated and normalised, or ``(None, None, reason)``."""
        try:
            # Three and four numbers (a message's fields, a tuple, a flat array): checked as
            # floats, which costs a few NumPy calls less per sample than arrays.
            px, py, pz = position
            qx, qy, qz, qw = orientation
            v = (float(px), float(py), float(pz), float(qx), float(qy), float(qz), float(qw))
        except Exception:  # noqa: BLE001 - any other shape: the array path below decides
            v = None
        if v is not None:
            if not all(map(math.isfinite, v)):
                return None, None, 'nonfinite'
            p, q = np.array(v[:3]), np.array(v[3:])
        else:
            try:
                p = np.asarray(position, dtype=float).reshape(3)
                q = np.asarray(orientation, dtype=float).reshape(4)
            except Exception:  # noqa: BLE001 - whatever the input, never raise
                return None, None, 'malformed'
            if not (np.isfinite(p).all() and np.isfinite(q).all()):
                return None, None, 'nonfinite'
        # (|q| and the hemisphere test below term by term, as ``head_kernels.add_samples``
        # computes them: a crowd's poses added in one call give the same bits)
        qx, qy, qz, qw = q.tolist()
        norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        if norm < 1e-9:
            return None, None, 'zero_quaternion'
        if abs(norm - 1.0) > self.quat_tolerance:
            return None, None, 'non_unit_quaternion'
        return p, q / norm, None

    def add(self, t, position, orientation):
        """Validate and store a sample; ``None`` if accepted, else a reason code.

        ``t`` s, ``position`` ``(3,)`` m, ``orientation`` ``(4,)`` ``(x, y, z, w)`` body to
        world. Never raises on bad data; the codes are in ``REJECT_REASONS``. The quaternion is
        renormalised and flipped to the hemisphere of the previous sample (sign continuity).
        A stream whose clock jumps back for good (a replay loop) keeps being rejected as
        ``'stamp_backwards'``: call ``reset()``. A sample more than ``max_gap`` after the
        previous one is accepted and starts a new history.
        """
        return self.add_checked(self.check(t, position, orientation))

    def check(self, t, position, orientation):
        """A sample's values checked as ``add`` checks them, whatever the history (the stamp
        order is ``add``'s): ``(t, p, q, None)``, ``t`` a float and ``q`` normalised, or
        ``(None, None, None, reason)``. Never raises; counts nothing (``add`` counts)."""
        try:
            t = float(t)
        except Exception:  # noqa: BLE001 - whatever the input, never raise
            return None, None, None, 'malformed'
        p, q, reason = self._check_pose(position, orientation)
        if reason is None and not math.isfinite(t):
            reason = 'nonfinite'
        if reason is not None:
            return None, None, None, reason
        return t, p, q, None

    def add_checked(self, checked):
        """``add`` of a sample whose values ``check`` returned as ``checked``: a caller that
        needs them first (``jumped``) checks once."""
        t, p, q, reason = checked
        if reason is not None:
            return self._reject(reason)
        n = self._n
        if n:
            dt = t - self._t[n - 1]
            if abs(dt) <= self.min_interval:
                return self._reject('stamp_repeated')
            if dt < 0.0:
                return self._reject('stamp_backwards')
            ax, ay, az, aw = q.tolist()
            bx, by, bz, bw = self._q[n - 1].tolist()
            if ax * bx + ay * by + az * bz + aw * bw < 0.0:
                q = -q
            if dt > self.max_gap:
                n = 0
        if n == self.max_samples:
            self._t[:-1] = self._t[1:]
            self._p[:-1] = self._p[1:]
            self._q[:-1] = self._q[1:]
            n -= 1
        self._t[n], self._p[n], self._q[n] = t, p, q
        self._n = n + 1
        self._version += 1
        return None

    def detect_teleport(self, position, orientation, max_distance, max_angle):
        """True if the pose jumped from the newest accepted sample by more than ``max_distance``
        (m) or ``max_angle`` (rad). False with no history or with an invalid pose (``add`` will
        reject that one). The caller decides: typically ``reset()`` and then ``add``."""
        if not self._n:
            return False
        p, q, reason = self._check_pose(position, orientation)
        return reason is None and self.jumped(p, q, max_distance, max_angle)

    def jumped(self, p, q, max_distance, max_angle):
        """``detect_teleport`` of a pose ``check`` has accepted (``p`` ``(3,)``, ``q`` ``(4,)``
        unit)."""
        if not self._n:
            return False
        last = self._p[self._n - 1]
        if math.dist(p.tolist(), last.tolist()) > max_distance:
            return True
        d = min(abs(float(q @ self._q[self._n - 1])), 1.0)
        return 2.0 * math.acos(d) > max_angle

    # -- estimation ----------------------------------------------------------------------------

    def state_at(self, t):
        """The ``KinematicState`` (K = 1) of the body at ``t - delay`` (world frame, SI).

        Within the history the fit interpolates; before the oldest sample the oldest pose is
        held, at rest (zero derivatives: the head held across a gap until its stream resumed);
        past the newest it extrapolates and brakes (see the module docstring).
        Raises ``LookupError`` when no sample has been accepted yet (check ``last_stamp``) and
        ``ValueError`` for a non-finite ``t``.
        """
        if not math.isfinite(t):
            raise ValueError(f'state_at({t!r}): time must be finite')
        key = self._key(t)
        state = self._memo.get(key)
        if state is None:
            state = self._keep(key, self._state_at(t))
        return state

    def prefetch(self, times):
        """Fit ``state_at`` of each of ``times`` (finite, at most ``MEMO_SIZE``) in one
        compiled call (``head_kernels.fits_at``) and keep them, so that asking for them next
        costs a look-up: a tick asks for three instants (the frame, its start, the clock's).
        The same states bit for bit; nothing is done with fewer than two samples."""
        if self._n < 2:
            return
        keys = {self._key(t): float(t) for t in times}
        missing = [k for k in keys if k not in self._memo]
        if not missing:
            return
        out = np.empty((len(missing), FIT_SIZE))
        fits_at(self._t, self._p, self._q, self._n, np.array([keys[k] for k in missing]),
                self.delay, self.max_extrapolation, self.max_gap, self.window, self.degree,
                self.min_samples, out)
        for r, key in enumerate(missing):
            self._keep(key, fit_state(out[r:r + 1]))

    def _key(self, t):
        """The memo's key of ``state_at(t)``: the time, the history's version, the settings."""
        return (float(t), self._version, self.delay, self.window, self.degree, self.min_samples,
                self.max_extrapolation, self.max_gap)

    def _keep(self, key, state):
        """``state`` kept under ``key``, the oldest of ``MEMO_SIZE`` dropped; returns it."""
        if len(self._memo) >= MEMO_SIZE:
            self._memo.pop(next(iter(self._memo)))
        self._memo[key] = state
        return state

    def _state_at(self, t):
        n = self._n
        if n == 0:
            raise LookupError('HeadEstimator has no sample yet')
        if n == 1:
            return KinematicState.still(self._p[0], self._q[0])
        te, rate, rate_d = self.fit_time(t)
        out = np.empty((1, FIT_SIZE))
        loess_fit(self._t, self._p, self._q, n, te, self.window, self.degree, self.min_samples,
                  rate, rate_d, out[0])
        return fit_state(out)

    def fit_time(self, t):
        """``(te, rate, rate_d)``: where ``state_at(t)``'s fit is evaluated (``t - delay``,
        within the history; past the newest sample, warped: full-speed extrapolation, then a
        C² brake) and the warp's ``dt_warped/dt`` and derivative (1, 0 inside). Needs two
        samples or more (``head_kernels.fit_time``)."""
        return kernel_fit_time(self._t, self._n, float(t), self.delay, self.max_extrapolation,
                               self.max_gap)

    def use_storage(self, t, p, q):
        """Keep the history in the given arrays ``(max_samples,)``, ``(max_samples, 3)``,
        ``(max_samples, 4)`` (rows of a ``HeadEstimatorBank``'s), the samples so far copied
        in."""
        m = self.max_samples
        if t.shape != (m,) or p.shape != (m, 3) or q.shape != (m, 4):
            raise ValueError(f'storage of {m} samples expected')
        t[:], p[:], q[:] = self._t, self._p, self._q
        self._t, self._p, self._q = t, p, q


def fit_state(out):
    """The ``KinematicState`` of ``K`` fits ``out`` ``(K, FIT_SIZE)`` (views, no copies)."""
    return KinematicState(
        position=out[:, 0:3],
        orientation=out[:, 3:7],
        linear_velocity=out[:, 7:10],
        angular_velocity=out[:, 10:13],
        linear_acceleration=out[:, 13:16],
        angular_acceleration=out[:, 16:19],
    )


class HeadEstimatorBank:
    """Several bodies' ``HeadEstimator``s (same settings) whose histories share one set of
    arrays, so that all their fits at one time run in one compiled call
    (``head_kernels.states_fit``) instead of one call and one ``KinematicState`` each: a
    node with many frames (a crowd) pays per body a compiled fit, not a Python call.
    ``states_at(t)`` equals stacking every estimator's ``state_at(t)`` bit for bit (a
    body without samples: still at the origin, unrotated)."""

    def __init__(self, estimators):
        self.estimators = list(estimators)
        K, m = len(self.estimators), self.estimators[0].max_samples
        if any(type(e) is not HeadEstimator or e.max_samples != m for e in self.estimators):
            raise ValueError('a bank holds plain HeadEstimators of one max_samples')
        self._t, self._p, self._q = np.empty((K, m)), np.empty((K, m, 3)), np.empty((K, m, 4))
        for k, e in enumerate(self.estimators):
            e.use_storage(self._t[k], self._p[k], self._q[k])
        self._last = None       # (key, state) of the last states_at

    def holds(self, estimators):
        """Whether ``estimators`` are this bank's, in order (a replay may swap some out)."""
        return len(estimators) == len(self.estimators) and all(
            a is b for a, b in zip(estimators, self.estimators, strict=True))

    def add_poses(self, first, t, poses, restart):
        """``add`` of ``poses[k]`` at the one stamp ``t`` (s) to estimator ``first + k``, for
        every row of ``poses`` ``(K, 7)`` (x, y, z, qx, qy, qz, qw) in one compiled call
        (``head_kernels.add_samples``): the histories, bits and rejection counts of ``K`` calls
        of ``add``, the estimators' settings being the first's (a runner sets them together).
        ``restart`` ``(K,)`` bool: for these a stamp before the newest restarts the history
        (the stream restarted) instead of being rejected. Returns the outcome per row:
        ``ACCEPTED``, ``RESTARTED`` (accepted, the history restarted) or the reason's index
        in ``REJECT_REASONS``."""
        K = len(poses)
        ests = self.estimators[first:first + K]
        e0 = ests[0]
        ns = np.array([e._n for e in ests], dtype=np.int64)
        outcome = np.empty(K, dtype=np.int64)
        add_samples(self._t[first:first + K], self._p[first:first + K],
                    self._q[first:first + K], ns, float(t),
                    np.ascontiguousarray(poses, dtype=float), np.asarray(restart, dtype=bool),
                    e0.min_interval, e0.max_gap, e0.quat_tolerance, outcome)
        out = outcome.tolist()
        for e, n, o in zip(ests, ns.tolist(), out, strict=True):
            if o < 0:
                e._n = n
                e._version += 1
            else:
                e.rejected[REJECT_REASONS[o]] += 1
        return out

    def longest_sample_period(self, rows):
        """The largest ``sample_period`` of the estimators ``rows`` (indices), ``None`` if
        none has two samples: one compiled call, however many."""
        ns = np.array([e._n for e in self.estimators], dtype=np.int64)
        p = longest_median_interval(self._t, ns, np.asarray(rows, dtype=np.int64))
        return None if p < 0.0 else float(p)

    def states_at(self, t):
        """Every body's state at ``t - delay``: one ``KinematicState`` of ``K`` bodies."""
        if not math.isfinite(t):
            raise ValueError(f'states_at({t!r}): time must be finite')
        ests = self.estimators
        e0 = ests[0]
        # A tick asks for the same instant more than once (the frame's end, the markers'
        # colliders): the last answer holds while no history or setting changed.
        key = (float(t), [e._version for e in ests], [e.delay for e in ests],
               [e.max_extrapolation for e in ests], e0.window, e0.degree, e0.min_samples,
               e0.max_gap)
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        ns = np.array([e._n for e in ests], dtype=np.int64)
        delays = np.array(key[2], dtype=float)
        extrapolations = np.array(key[3], dtype=float)
        out = np.zeros((len(ests), FIT_SIZE))
        # (the fit times and the fits in one compiled call: bit for bit each state_at)
        states_fit(self._t, self._p, self._q, ns, float(t), delays, extrapolations, e0.max_gap,
                   e0.window, e0.degree, e0.min_samples, out)
        out.flags.writeable = False           # (shared by the callers of the same instant)
        state = fit_state(out)
        self._last = (key, state)
        return state
