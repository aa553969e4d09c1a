"""The simulator's calls into the contact stage: a scene with colliders or joint limits steps
in one compiled call per tick (``step_unilateral.advance_unilateral``: the free step, then its
contacts and limits, ``collision``), and a step in which some joint turns faster than
``SUBSTEP_ANGLE`` is split into sub-steps here, each resolved likewise.

``ContactSteps`` is a part of ``simulator.Simulator`` (its methods use the simulator's model,
tables and compiled step).
"""
import math
import time

import numpy as np

from . import contact_model, lanes, step as compiled, step_unilateral
from .head import stack_anchors

__all__ = ['ContactSteps', 'SUBSTEP_ANGLE', 'MAX_SUBSTEPS']

# Scenes with colliders or joint limits: a step in which a joint turns by more than this
# (rad, at the start of the step) is split into sub-steps, at most MAX_SUBSTEPS.
SUBSTEP_ANGLE = 0.25
MAX_SUBSTEPS = 8
# Collider arguments of a scene without colliders (limits only): no bodies, no colliders.
_NO_COLLIDER_ARGS = (np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3)),
                     np.zeros((0, 3)), np.zeros(0))


class ContactSteps:
    """The contact stage's calls of ``Simulator`` (a part of it)."""

    def _steps_unilateral(self, n_steps, anchor_at, bodies_at, x, q, v, w,
                          anchor_table=None, body_table=None, planned=None):
        """``n_steps`` steps of a scene with colliders or joint limits: each is integrated as
        above, then its contacts and limits are resolved (``collision``), all in one compiled
        call (``step_unilateral.advance_unilateral``). A step in which some joint turns faster
        than ``SUBSTEP_ANGLE`` per step (a whip crack after an impact) is split into up to
        ``MAX_SUBSTEPS`` equal sub-steps, each resolved likewise: the compiled call stops
        before it, and it is taken here (the anchors at the sub-step times are evaluated for
        it), then the call goes on."""
        uni = self.unilateral
        cols = uni.colliders
        moving = bool(cols is not None and cols.moving.size > 0)
        x, q, v, w = (np.array(a, dtype=float) for a in (x, q, v, w))
        done = 0
        while done < n_steps:
            A, B = self._tables(n_steps - done, anchor_at, anchor_table, planned, moving,
                                bodies_at, body_table)
            self._end_row = A               # its end row is the call's end, sub-steps or not
            status, k = self._call_unilateral(n_steps - done, A, B, moving, x, q, v, w)
            done += k
            self._n_steps += k
            if status == compiled.SUBSTEPS:
                x, q, v, w = self._substepped(anchor_at, bodies_at, x, q, v, w)
                x, q, v, w = (np.array(a, dtype=float) for a in (x, q, v, w))
                done += 1
        uni.dt = self.dt
        return x, q, v, w

    def _call_unilateral(self, n_steps, A, B, moving, x, q, v, w):
        f_c = np.zeros((self.model.n, 3))
        args = self._unilateral_args(n_steps, A, B, moving, x, q, v, w, f_c)
        t0 = time.perf_counter()
        status, k, tables, ids = step_unilateral.advance_unilateral(*args)
        self._uni_wall += time.perf_counter() - t0
        self._keep_tables(tables, ids)
        self.f_c = f_c
        stats = self.unilateral._stats
        self.unilateral.last = {'contacts': int(stats[0]), 'limits': int(stats[1]),
                                'position_passes': int(stats[2])}
        if status == compiled.JOINT_SOLVE_FAILED:
            raise np.linalg.LinAlgError('J M⁻¹ Jᵀ is not positive definite')
        if status == compiled.DAMPING_SOLVE_FAILED:
            raise np.linalg.LinAlgError('implicit damping KKT system is singular')
        return status, k

    def _compile_contact_stage(self):
        """Compile (or load) the contact stage for this scene's types alone
        (``step_unilateral.compile_contact_stage``), the anchors where they are: what a cold
        compile's second process runs (``compile``)."""
        _, at = self._last_anchor
        A, B = self._tables(1, lambda _t: at, None, None)
        st = self.state
        x, q, v, w = (np.array(a, dtype=float) for a in (st.x, st.q, st.v, st.w))
        step_unilateral.compile_contact_stage(
            self._unilateral_args(1, A, B, False, x, q, v, w, np.zeros((self.model.n, 3))))

    def _keep_tables(self, tables, ids):
        ws = self.unilateral.workspace
        if tables.shape != ws[contact_model.WS_TABLES].shape:
            # A step's rows overflowed the tables: the grown ones are kept (``grown``).
            self.unilateral.workspace = (ws[:contact_model.WS_TABLES] + (tables, ids)
                                         + ws[contact_model.WS_IDS + 1:])

    def _unilateral_args(self, n_steps, A, B, moving, x, q, v, w, f_c):
        """``advance_unilateral``'s arguments."""
        uni = self.unilateral
        ext_F, ext_T = self._external_arrays()
        stats = uni._stats
        cols = uni.colliders
        M = self._step_model()
        static_pose = uni.static_pose
        args = (M, A, n_steps, self.dt, x, q, v, w, ext_F, ext_T, f_c, B,
                moving, cols.args if cols is not None else _NO_COLLIDER_ARGS,
                static_pose, uni.model_args, uni.detector_args, uni.split_args,
                np.ascontiguousarray(self.model.q_rest), uni.detector is not None, stats,
                SUBSTEP_ANGLE, MAX_SUBSTEPS, self._profile,
                True if self._kernel(M).kernel is lanes.advance_lanes else None,
                self._contact_workspace(static_pose),
                None if M.integrator == compiled.RK4 else True)
        return args

    def _contact_workspace(self, static_pose):
        """The contact stage's workspace of this structure, built once (``Unilateral``);
        ``static_pose``: the colliders' pose arrays (their count sizes it)."""
        uni = self.unilateral
        if uni.workspace is None:
            uni.workspace = contact_model.resolve_workspace(
                uni.model_args, uni.detector_args, uni.split_args, static_pose,
                uni.detector is not None)
        return uni.workspace

    def _substepped(self, anchor_at, bodies_at, x, q, v, w):
        """One step split into sub-steps (``_substeps``), each integrated and resolved."""
        m, uni = self.model, self.unilateral
        project = self.scene.solver.projection
        t0 = self._t_base + self._n_steps * self.dt
        n_sub = self._substeps(w - m.parent_side(anchor_at(t0).angular_velocity, w))
        h = self.dt / n_sub
        for k in range(n_sub):
            t = t0 + k * h
            t1 = t0 + (k + 1) * h if k + 1 < n_sub else \
                self._t_base + (self._n_steps + 1) * self.dt
            a1 = anchor_at(t1)
            x, q, v, w = (np.array(a, dtype=float) for a in (x, q, v, w))
            self._run_compiled(1, h, stack_anchors([anchor_at(t), anchor_at(t + 0.5 * h), a1]),
                               x, q, v, w)
            pose = uni.pose(bodies_at(t1) if bodies_at else None)
            x, q, v, w = uni.resolve(x, q, v, w, a1, pose, project, h)
        self._n_steps += 1
        return x, q, v, w

    def _substeps(self, w_rel):
        """Sub-steps of a step of a scene with colliders or limits, given the joints' relative
        angular velocities ``w_rel`` ``(n, 3)`` (rad/s) at its start (1 for other scenes)."""
        if self.unilateral is None:
            return 1
        return self._substeps_at(float(np.sqrt(np.max(np.einsum('ij,ij->i', w_rel, w_rel)))))

    def _substeps_at(self, rate):
        """Sub-steps of a step whose fastest joint turns at ``rate`` rad/s (1 without
        colliders or limits)."""
        if self.unilateral is None:
            return 1
        return min(MAX_SUBSTEPS, max(1, math.ceil(rate * self.dt / SUBSTEP_ANGLE)))
