"""Running one solver setting on one bench scene: cost, tip error, joint gap, energy drift.

Cost: CPU time (``time.process_time``, one thread: the CLI pins BLAS to one thread) of
advancing the scene, without building the simulator, median of ``repeats`` runs of
``timing_window`` simulated seconds each; reported per simulated second and per internal step.
Wall time (``perf_counter``) is kept alongside.

Error: the tip (distal end of the last segment) is compared, after every call, at the
simulator's own time ``sim.t`` (a multiple of its step, so no lag is counted as error) with the
reference trajectory interpolated there (cubic Hermite in position and velocity on the
reference's own step grid: ~1e-10 m at 1/8000 s). RMS and max over the run, in mm.

The reference is this core's RK4 at a tiny step (``reference``), checked against the
independent trajectories of ``../shared/reference/`` where the scene matches
(``check_against_shared``) and against itself at twice the step (Richardson: for a 4th-order
method its own error is ≈ the difference / 15); errors are compared only while that estimate
stays below 1e-5 m (chaotic scenes diverge from any reference after a while).
"""
import json
import math
import time
import warnings
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from ponytail_ros.core.scene import SolverSpec
from ponytail_ros.core.simulator import Simulator
from ponytail_ros.core.state import half_vectors
from ponytail_ros.core.step import INTEGRATORS

__all__ = ['Setting', 'Trajectory', 'reference', 'simulate', 'time_setting', 'run_setting',
           'load_shared', 'rest_energy', 'check_against_shared', 'fmt_dt']


def fmt_dt(dt):
    """``1/240`` for a step that is the inverse of an integer, else ``%g``."""
    r = 1.0 / dt
    return f'1/{round(r)}' if abs(r - round(r)) < 1e-6 * r else f'{dt:g}'


@dataclass(frozen=True)
class Setting:
    """One point of the sweep.

    ``tick_rate``: None = the head is exact at every integrator stage (``advance_to``, called
    every 10 ms); else the head is given only at frames of this rate (``advance_frame``: the
    anchor between frames is the quintic Hermite through both frames' position, velocity and
    acceleration).
    """

    integrator: str = 'rk4'
    dt: float = 1.0 / 240.0
    projection: bool = True
    baumgarte_stiffness: float = 0.0
    baumgarte_damping: float = 0.0
    tick_rate: float | None = None
    extra: tuple = ()       # more SolverSpec fields, as ((name, value), ...)

    def solver(self, max_steps=1_000_000, **kw):
        return SolverSpec(integrator=self.integrator, dt=self.dt, max_steps_per_call=max_steps,
                          projection=self.projection,
                          baumgarte_stiffness=self.baumgarte_stiffness,
                          baumgarte_damping=self.baumgarte_damping, **dict(self.extra), **kw)

    @property
    def label(self):
        short = {'rk4': 'RK4', 'symplectic_euler': 'SE', 'rattle': 'RATTLE'}[self.integrator]
        s = f'{short} {fmt_dt(self.dt)}'
        if not self.projection:
            s += ' noproj'
        if self.baumgarte_stiffness or self.baumgarte_damping:
            s += f' BG({self.baumgarte_stiffness:g},{self.baumgarte_damping:g})'
        if self.tick_rate:
            s += f' @{self.tick_rate:g}Hz'
        for k, v in self.extra:
            s += f' {k}={v}'
        return s

    @property
    def is_default_solver(self):
        return self == Setting()


@dataclass
class Trajectory:
    """Tip positions (and velocities) at times ``t``; ``energy`` total E (J) or None."""

    t: np.ndarray
    tip: np.ndarray
    tip_vel: np.ndarray | None = None
    energy: np.ndarray | None = None
    gap: np.ndarray | None = None
    resets: list | None = None

    def at(self, t):
        """Tip position at times ``t`` (cubic Hermite; linear if no velocities)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        i = np.clip(np.searchsorted(self.t, t, side='right') - 1, 0, len(self.t) - 2)
        t0, t1 = self.t[i], self.t[i + 1]
        h = (t1 - t0)[:, None]
        s = ((t - t0) / (t1 - t0))[:, None]
        p0, p1 = self.tip[i], self.tip[i + 1]
        if self.tip_vel is None:
            return p0 + s * (p1 - p0)
        m0, m1 = self.tip_vel[i] * h, self.tip_vel[i + 1] * h
        s2, s3 = s * s, s * s * s
        return ((2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * m0 + (-2 * s3 + 3 * s2) * p1
                + (s3 - s2) * m1)


def _tip(sim):
    c = sim.model.chain_end[0] - 1
    st = sim.state
    h = half_vectors(sim.model.length[c:c + 1], st.q[c:c + 1])[0]
    return st.x[c] + h, st.v[c] + np.cross(st.w[c], h)


def _energy(sim):
    ke, pe = sim.energy()
    return float(ke[0] + pe[0])


def rest_energy(bench):
    """Energy of the chain hanging at rest along gravity on the still head (J)."""
    chain = replace(bench.scene.chains[0], rest_direction=None)
    sim = Simulator(bench.scene.replace(chains=(chain,)), bench.motion, 0.0)
    return _energy(sim)


def simulate(bench, setting, sample_dt=0.01, duration=None, every_step=False):
    """Run ``bench`` with ``setting``; returns a ``Trajectory`` sampled after every call.

    Calls: every ``sample_dt`` s with the exact head (``advance_to``), every frame with
    ``tick_rate``, or every internal step with ``every_step`` (the reference).
    """
    duration = bench.duration if duration is None else duration
    sim = Simulator(bench.scene.replace(solver=setting.solver()), bench.motion, 0.0)
    if every_step:
        n = int(round(duration / setting.dt))
        times = (np.arange(1, n + 1) * setting.dt)
    elif setting.tick_rate:
        n = int(math.floor(duration * setting.tick_rate + 1e-9))
        times = np.arange(1, n + 1) / setting.tick_rate
    else:
        n = int(math.floor(duration / sample_dt + 1e-9))
        times = np.arange(1, n + 1) * sample_dt
    ts, tips, vels, es, gaps, resets = [0.0], [], [], [], [], []
    p, v = _tip(sim)
    tips.append(p)
    vels.append(v)
    es.append(_energy(sim))
    gaps.append(float(np.max(sim.joint_gaps())))
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)    # a blow-up is reported by the guard
        for t in times:
            if setting.tick_rate and not every_step:
                r = sim.advance_frame(t, bench.motion.state_at(t))
            else:
                r = sim.advance_to(t, bench.motion)
            if r.reset_reason:
                resets.append((float(sim.t), r.reset_reason))
            ts.append(sim.t)
            p, v = _tip(sim)
            tips.append(p)
            vels.append(v)
            es.append(_energy(sim))
            gaps.append(r.max_gap)
    return Trajectory(np.array(ts), np.array(tips), np.array(vels), np.array(es),
                      np.array(gaps), resets)


_REF_CACHE: dict[tuple, Any] = {}


def reference(bench, dt_ref=1.0 / 8000.0, duration=None, check=True, tol=1e-5):
    """This core's RK4 at ``dt_ref``, recorded at every step (the converged reference).

    ``check``: also run at ``2 dt_ref`` and estimate the reference's own error by Richardson
    (RK4: error(h) ≈ |x(2h) - x(h)| / 15). ``valid_until`` is the time up to which that
    estimate stays below ``tol`` (m): chaotic scenes (the release, the shake) lose their
    trajectory there, and tip errors are only compared inside that window (like the shared
    files' ``convergence.valid_until``). ``self_error`` is the estimate's max in the window.
    Cached per (scene, segments, duration, step).
    """
    duration = bench.duration if duration is None else duration
    key = (bench.name, bench.n_segments, repr(bench.scene), float(duration), float(dt_ref), check,
           tol)
    if key in _REF_CACHE:
        return _REF_CACHE[key]
    ref = simulate(bench, Setting('rk4', dt_ref), duration=duration, every_step=True)
    ref.valid_until, ref.self_error, ref.self_error_all = float(ref.t[-1]), None, None
    if check:
        coarse = simulate(bench, Setting('rk4', 2.0 * dt_ref), duration=duration, every_step=True)
        est = np.linalg.norm(coarse.tip - ref.at(coarse.t), axis=1) / 15.0
        bad = np.nonzero(est > tol)[0]
        ref.valid_until = float(coarse.t[bad[0] - 1]) if bad.size else float(ref.t[-1])
        inside = coarse.t <= ref.valid_until
        ref.self_error = float(est[inside].max())
        ref.self_error_all = float(est.max())
    _REF_CACHE[key] = ref
    return ref


def time_setting(bench, setting, window, repeats=3, sample_dt=0.01):
    """CPU and wall seconds (lists, one per repeat) to advance ``window`` simulated seconds:
    with the exact head, ``Simulator.rollout`` through every ``sample_dt`` s (what
    ``simulate`` computes call by call, equal bit for bit); with ``tick_rate``,
    ``advance_frame`` every frame."""
    cpu, wall = [], []
    for _ in range(repeats):
        sim = Simulator(bench.scene.replace(solver=setting.solver()), bench.motion, 0.0)
        if setting.tick_rate:
            n_ticks = int(math.floor(window * setting.tick_rate + 1e-9))
            times = np.arange(1, n_ticks + 1) / setting.tick_rate
            states = [bench.motion.state_at(t) for t in times]
        else:
            times = np.arange(1, int(math.floor(window / sample_dt + 1e-9)) + 1) * sample_dt
            states = None
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', RuntimeWarning)
            c0, w0 = time.process_time(), time.perf_counter()
            if states is None:
                # (``advance_to`` at every sample, bit for bit: the motion evaluated once)
                sim.rollout(times, bench.motion)
            else:
                for t, s in zip(times, states, strict=True):
                    sim.advance_frame(t, s)
            cpu.append(time.process_time() - c0)
            wall.append(time.perf_counter() - w0)
    return cpu, wall


def run_setting(bench, setting, ref, repeats=3, timing_window=1.0, sample_dt=0.01, e_rest=None):
    """One row of the trade table (a dict)."""
    traj = simulate(bench, setting, sample_dt)
    t_end = traj.t[-1]
    valid = min(bench.duration, getattr(ref, 'valid_until', bench.duration))
    ok = (traj.t > 0.0) & (traj.t <= valid + 1e-9)
    err = np.linalg.norm(traj.tip[ok] - ref.at(traj.t[ok]), axis=1)
    window = min(timing_window, bench.duration)
    cpu, wall = time_setting(bench, setting, window, repeats, sample_dt)
    steps_per_s = 1.0 / setting.dt
    cpu_med = float(np.median(cpu)) / window
    row = dict(
        scene=bench.name, n_segments=bench.n_segments, setting=setting.label,
        **{k: v for k, v in asdict(setting).items() if k != 'extra'},
        dt_label=fmt_dt(setting.dt), steps_per_sim_s=steps_per_s,
        solves_per_sim_s=steps_per_s * INTEGRATORS[setting.integrator].solves_per_step,
        cpu_s_per_sim_s=cpu_med,
        cpu_s_per_sim_s_min=float(np.min(cpu)) / window,
        wall_s_per_sim_s=float(np.median(wall)) / window,
        cpu_us_per_step=cpu_med / steps_per_s * 1e6,
        repeats=repeats, timing_window_s=window,
        tip_rms_mm=float(np.sqrt(np.mean(err ** 2))) * 1e3 if err.size else float('nan'),
        tip_max_mm=float(np.max(err)) * 1e3 if err.size else float('nan'),
        tip_final_mm=float(err[-1]) * 1e3 if err.size else float('nan'),
        max_gap_m=float(np.max(traj.gap)),
        resets=len(traj.resets), first_reset=(f'{traj.resets[0][0]:.3f}s: {traj.resets[0][1]}'
                                              if traj.resets else ''),
        simulated_s=float(t_end), error_window_s=float(valid),
    )
    if bench.still:
        e_rest = rest_energy(bench) if e_rest is None else e_rest
        scale = traj.energy[0] - e_rest
        de = (traj.energy - traj.energy[0]) / scale
        row.update(energy_drift_max=float(np.max(np.abs(de))), energy_drift_final=float(de[-1]),
                   energy_growth_max=float(np.max(de)))
    else:
        row.update(energy_drift_max=float('nan'), energy_drift_final=float('nan'),
                   energy_growth_max=float('nan'))
    row['stable'] = row['resets'] == 0 and bool(np.isfinite(row['tip_rms_mm']))
    return row


def load_shared(name, reference_dir):
    import os
    path = os.path.join(reference_dir, name + '.json')
    if not os.path.exists(path):
        return None
    with open(path) as f:
        return json.load(f)


def check_against_shared(ref, shared, n_segments):
    """Max and RMS tip error (m) of ``ref`` against a shared reference file, over its valid window.

    The shared file samples every 10 ms; the comparison is at those times (``ref`` interpolated).
    """
    t = np.asarray(shared['t'])
    valid = float(shared['convergence']['valid_until']['1e-6'])
    tip = np.asarray(shared['points'])[n_segments - 1]
    ok = (t <= min(valid, ref.t[-1]) + 1e-9)
    err = np.linalg.norm(ref.at(t[ok]) - tip[ok], axis=1)
    return dict(max_m=float(err.max()), rms_m=float(np.sqrt(np.mean(err ** 2))),
                window_s=float(t[ok][-1]), valid_until_1e6=valid)
