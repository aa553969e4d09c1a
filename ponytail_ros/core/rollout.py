"""``Simulator.rollout``: a known motion run offline through many sample times, the motion
and its anchor table evaluated once for all of them (like MuJoCo's ``rollout``)."""
import time

import numpy as np

from . import step as compiled
from .head import AnchorKinematics
from .report import Rollout, StepReport
from .state import ChainState

__all__ = ['RolloutSteps', 'memo_last']


def memo_last(f, size=2):
    """Cache ``f(t)`` for the last few ``t``: RK4 evaluates the anchor twice at t + h/2, and the
    step's end again for the projection and the next step's start."""
    cache = {}

    def g(t):
        v = cache.get(t)
        if v is None:
            if len(cache) >= size:
                cache.pop(next(iter(cache)))
            v = cache[t] = f(t)
        return v
    return g


class RolloutSteps:
    """The rollout of ``Simulator`` (a mixin: it runs on the simulator's own state)."""

    def rollout(self, times, motion):
        """``advance_to(t, motion)`` for every ``t`` of ``times`` in turn, bit for bit, with the
        motion and the anchor table evaluated once for all the calls' stage times (one
        vectorised ``states_at``), then one compiled call per sample: the way to run a known
        motion offline (a reference, a benchmark), like MuJoCo's ``rollout``.

        ``times``: ``(T,)`` increasing sample times (s). Returns a ``Rollout``: the ``T``
        calls' ``StepReport`` and the state after each, ``(T, n, 3|4)`` arrays. Scenes with
        colliders or joint limits and a sample interval beyond
        ``max_steps_per_call`` go through ``advance_to`` itself.
        """
        times = np.asarray(times, dtype=float).reshape(-1)
        n = self.model.n
        out = Rollout([], np.empty((times.size, n, 3)), np.empty((times.size, n, 4)),
                      np.empty((times.size, n, 3)), np.empty((times.size, n, 3)))
        done = 0
        while done < times.size:        # a guard reset ends a stretch; the next starts there
            done += self._rollout_stretch(times[done:], motion, out, done)
        return out

    def _rollout_stretch(self, times, motion, out, k0):
        """Samples ``times`` into ``out`` from row ``k0`` until the first guard reset; how
        many were taken."""
        n_targets = np.floor((times - self._t_base) / self.dt + 1e-9).astype(np.int64)
        counts = np.diff(n_targets, prepend=self._n_steps)
        if (self.unilateral is not None or np.any(counts < 0)
                or np.any(counts > self.scene.solver.max_steps_per_call)):
            for k, t in enumerate(times):
                out.reports.append(self.advance_to(t, motion))
                self._store(out, k0 + k)
            return times.size
        m = self.model
        table = self._table(motion.stage_points(self._t_base, self._n_steps, int(counts.sum()),
                                                self.dt, self._anchor_body, m.attach))
        self._anchor_at = memo_last(lambda t: self.anchors(motion.state_at(t)))
        model = self._step_model()
        st = self.state                 # the working arrays, stepped in place
        x, q, v, w = (np.array(a, dtype=float) for a in (st.x, st.q, st.v, st.w))
        self.state = ChainState(x, q, v, w)
        row = 0                         # the table row of the next step's start
        for k, n_steps in enumerate(counts):
            report = StepReport(steps=int(n_steps))
            t_start = time.perf_counter()
            failure = None
            self._call_wall = self._uni_wall = 0.0
            if n_steps > 0:
                A = compiled.AnchorTable(*(a[row:row + 2 * n_steps + 1] for a in table))
                try:
                    self._run_compiled_table(n_steps, self.dt, A, x, q, v, w, model)
                    self._n_steps += int(n_steps)
                    row += 2 * int(n_steps)
                except np.linalg.LinAlgError as err:      # (the time does not advance)
                    failure = str(err)
                    report.steps = 0
                    x[:] = np.nan
            self.t = self._t_base + self._n_steps * self.dt
            t_steps = time.perf_counter()
            # The anchor at self.t: the table's row there (advance_to's end row, or for a call
            # without steps its own evaluation at the same time: equal bit for bit).
            anchor = AnchorKinematics(*(a[row] for a in table))
            reason = self._end_call(report, anchor, failure, motion.state_at)
            report.timings = {'steps': t_steps - t_start, 'guard': time.perf_counter() - t_steps}
            self._profile[:] = 0            # (the free step: its whole call is integrate)
            self._split_timings(report)
            out.reports.append(report)
            self._store(out, k0 + k)
            if reason is not None:
                return k + 1
        return times.size

    def _store(self, out, k):
        st = self.state
        out.x[k], out.q[k], out.v[k], out.w[k] = st.x, st.q, st.v, st.w
