"""Look-ahead head estimation: one global interpolating spline through every stored sample.

``HeadEstimator`` (``head_estimation.py``) fits a local polynomial around each instant. Offline
(``ponytail_replay --look-ahead``) every pose on both sides of an instant is known, and for
exact, smooth animation poses a global interpolating spline of odd degree ``k`` through all the
stored samples is more accurate at low rates: it has no window whose edges move as the
evaluation time crosses a sample (the local fit switches between interpolants there, a small
jump in the derivatives at every sample), and its error constant is much smaller than a local
polynomial's of the same order (a cardinal spline tends to band-limited interpolation).

``SplineHeadEstimator`` is a ``HeadEstimator`` (same history, checks, resets, braking past the
newest sample) whose estimate within the history is that spline:

* position: ``p(t)`` per axis, a degree-``k`` interpolating spline (``scipy``'s
  ``make_interp_spline``, not-a-knot ends) in centred, scaled time;
* orientation: the four quaternion components (sign-continuous: ``add`` flips each sample to
  its predecessor's hemisphere), splined like the position; with ``s(t)`` the spline
  (not exactly unit), ``q = s/|s|`` and, exactly for the normalised ``q``,

      ω = 2 vec(ṡ ⊗ s*) / |s|²,    α = 2 vec(s̈ ⊗ s*) / |s|² − 2 (s·ṡ)/|s|² ω

  (world frame: ``ω = 2 vec(q̇ ⊗ q*)``). No reference orientation, no wrap of a rotation
  vector however far the history turns.

Only where the poses are sparse: at an instant with more than ``min_samples`` poses within
``window`` of it the local fit is a least-squares smoothing (more samples than coefficients),
which averages float and stamp rounding out where an interpolating spline amplifies it (at
1 kHz with ±20 % jitter and ns-rounded stamps the spline's p̈ error is ~1000× the fit's,
``pose_bench``), so the base class's fit is used there. With the look-ahead settings (window
0.05 s, 10 samples) that is the spline below ~100 Hz and near the ends of the history, the
local fit above.

The spline changes (slightly, with weights decaying geometrically per sample) as samples are
added; the look-ahead replay evaluates it only ``LOOK_AHEAD_SAMPLES`` poses behind the newest
one. Before the oldest sample the oldest pose is held, at rest (the base class); past the
newest the base class's
local fit extrapolates and brakes (the spline is not extrapolated). With fewer than ``k + 1``
samples the base class's fit is used.

Meant for exact animation poses, like the high-degree local fit it replaces: on noisy poses an
interpolating spline follows the noise. ROS-free: numpy, scipy and the core only.
"""
import math

import numpy as np

from .head import KinematicState
from .head_estimation import HeadEstimator

__all__ = ['SplineHeadEstimator', 'SPLINE_DEGREE']

#: Default spline degree (odd).
SPLINE_DEGREE = 11


def _qmul(a, b):
    """Quaternion products ``a ⊗ b`` of ``(..., 4)`` arrays, scalar last."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def _conj(q):
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


class SplineHeadEstimator(HeadEstimator):
    """``HeadEstimator`` whose estimate within the history is a global degree-``k``
    interpolating spline through every stored sample (module docstring).

    Args:
        spline_degree: odd degree ``k`` of the spline (default ``SPLINE_DEGREE``).
        Others: as ``HeadEstimator`` (used for the checks, the history, and the fit past the
        newest sample or with fewer than ``k + 1`` samples).
    """

    def __init__(self, *args, spline_degree=SPLINE_DEGREE, **kwargs):
        super().__init__(*args, **kwargs)
        if spline_degree < 1 or spline_degree % 2 == 0:
            raise ValueError('spline_degree must be odd and >= 1')
        self.spline_degree = int(spline_degree)
        self._spline = None
        self._spline_version = None

    def _fit(self):
        """``(t_mid, scale, p_mean, spline of 7 columns)`` of the current history (cached)."""
        if self._spline_version != self._version:
            from scipy.interpolate import make_interp_spline
            n = self._n
            ts = self._t[:n]
            t_mid = 0.5 * (ts[0] + ts[-1])
            scale = max(0.5 * (ts[-1] - ts[0]), 1e-9)
            p_mean = self._p[:n].mean(axis=0)
            Y = np.concatenate([self._p[:n] - p_mean, self._q[:n]], axis=1)
            spline = make_interp_spline((ts - t_mid) / scale, Y, k=self.spline_degree)
            self._spline = (t_mid, scale, p_mean, spline)
            self._spline_version = self._version
        return self._spline

    def _state_at(self, t):
        n = self._n
        te = float(t) - self.delay
        if n < self.spline_degree + 1 or te > self._t[n - 1]:
            return super()._state_at(t)
        held = te < self._t[0]          # (before the oldest: held there, at rest)
        te = max(te, self._t[0])
        ts = self._t[:n]
        inside = (int(np.searchsorted(ts, te + self.window, 'left'))
                  - int(np.searchsorted(ts, te - self.window, 'right')))
        if inside > self.min_samples or held:
            # Dense poses: the local least-squares fit smooths over more samples than it has
            # coefficients (float and stamp rounding averaged out), which an interpolating
            # spline would amplify instead.
            return super()._state_at(t)
        t_mid, scale, p_mean, spline = self._fit()
        x = (te - t_mid) / scale
        y0, y1, y2 = spline(x), spline(x, 1) / scale, spline(x, 2) / (scale * scale)
        s, sd, sdd = y0[3:], y1[3:], y2[3:]
        n2 = float(s @ s)
        sc = _conj(s)
        omega = 2.0 * _qmul(sd, sc)[:3] / n2
        alpha = 2.0 * _qmul(sdd, sc)[:3] / n2 - (2.0 * float(s @ sd) / n2) * omega
        q = s / math.sqrt(n2)
        return KinematicState(
            position=(y0[:3] + p_mean)[None],
            orientation=q[None],
            linear_velocity=y1[None, :3],
            angular_velocity=omega[None],
            linear_acceleration=y2[None, :3],
            angular_acceleration=alpha[None],
        )
