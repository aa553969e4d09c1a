"""The simulator's guard: after every call, whether the state is a blow-up (a reset reason).

Checked: finite, the joint solve did not fail, speeds below ``guard_max_speed``, no joint
turning more than ``guard_max_step_angle`` per (sub-)step (for RK4 also no segment's
gyroscopic precession beyond ``guard_max_step_angle / GYROSCOPIC_REACH_RATIO``), joint gaps
below ``guard_max_gap``; the measures in one compiled call (``state_kernels.guard_measures``).
``Guard`` is a part of ``simulator.Simulator``.
"""
import numpy as np

from . import chain_ops, state_kernels
from .direct_call import DirectCall

__all__ = ['Guard', 'GYROSCOPIC_REACH_RATIO']

# The measures' kernel called directly after its first call (``DirectCall``): its arguments
# are always a ``Model``'s arrays, C float64 state arrays (``_c``), a bool and a float64 row.
_GUARD_MEASURES = DirectCall(state_kernels.guard_measures)

# RK4 follows a thin segment's gyroscopic precession (its body-frame ω turning at ~ its axial
# spin Ω) only to dt·Ω ≈ 1 (1.04 gains energy slowly, 1.25 blows up), a swing to ~2.5 (the
# linear limit is 2.8): the guard holds the precession to guard_max_step_angle / this.
GYROSCOPIC_REACH_RATIO = 2.5


def _c(a):
    return np.ascontiguousarray(a, dtype=float)


class Guard:
    """The guard's checks of ``Simulator`` (a part of it; its ``_measures_out``: an array of
    ``len(state_kernels.MEASURES)``, the measures' output, read at once)."""

    _measures_out: np.ndarray

    def _measures(self, anchor):
        """``state_kernels.guard_measures`` of the state with ``anchor`` (its ``MEASURES``)."""
        m, st = self.model, self.state
        out = self._measures_out
        swing_only = not self._explicit_gyroscopic and self.axisymmetric
        _GUARD_MEASURES(m.length, m.is_first, m.chain_of, m.inertia, _c(st.x),
                                     _c(st.q), _c(st.v), _c(st.w), _c(anchor.position),
                                     _c(anchor.angular_velocity), swing_only, out)
        return out

    def _guard(self, g, failure=None):
        """Why the state after a call is a blow-up (a reset reason), or None; ``g``: its
        ``_measures``."""
        s = self.scene.solver
        if failure is not None:
            return f'solver failure: {failure}'
        if not g[0]:
            return 'non-finite state'
        _, max_gap, speed, rate, checked, precession = g.tolist()
        if speed > s.guard_max_speed:
            return f'speed {speed:.3g} m/s > guard_max_speed {s.guard_max_speed:g}'
        # Rotations faster than the integrator follows within one (sub-)step: a spin-up the
        # speed check misses when the segment is short (a thin segment's spurious spin).
        # Symplectic Euler and RATTLE turn a segment about its own axis exactly, at any rate:
        # for them only the rates that swing the axes count (``checked``).
        h = self.dt / self._substeps_at(rate)
        if h * checked > s.guard_max_step_angle:
            return (f'joint angular speed {checked:.3g} rad/s: {h * checked:.3g} rad per step > '
                    f'guard_max_step_angle {s.guard_max_step_angle:g}')
        if self._explicit_gyroscopic:
            gyro = precession if self.axisymmetric else float(np.max(
                chain_ops.gyroscopic_rates(self.model, self.state.q, self.state.w)))
            limit = s.guard_max_step_angle / GYROSCOPIC_REACH_RATIO
            if h * gyro > limit:
                return (f'gyroscopic precession at {gyro:.3g} rad/s (a segment spinning about its '
                        f'axis): {h * gyro:.3g} rad per step > guard_max_step_angle / '
                        f'{GYROSCOPIC_REACH_RATIO:g} = {limit:.3g}')
        if max_gap > s.guard_max_gap:
            return f'joint gap {max_gap:.3g} m > guard_max_gap {s.guard_max_gap:g}'
        return None
