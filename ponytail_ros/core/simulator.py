"""The simulator: a scene's chains advanced in fixed internal steps, driven by kinematic heads.

Stages of one internal step (as in a physics engine's pipeline):
    1. anchor kinematics at the stage times (exact motion, or interpolated between frames),
       one table per call (``head``, ``head_kernels``);
    2. the compiled step (``step``; a crowd of equal chains in SIMD lanes, ``lanes``): applied
       forces, constraint forces by A f_c = b (``chain_solve``), integration (RK4, symplectic
       Euler or RATTLE), implicit joint damping, and the joints closed again (positions, and
       for RK4 the velocities; symplectic Euler's and RATTLE's steps end with their own,
       mass-weighted, projection);
    3. only if the scene has colliders or joint limits: one-sided constraints at the step's end
       (``collision``, ``step_unilateral``: positions, then inelastic velocities, then
       friction).

Time: any frame time is advanced in steps of exactly ``solver.dt`` (an accumulator), so the
result does not depend on the frame rate; the chain's time lags the requested time by less than
one step. At most ``max_steps_per_call`` steps are taken per call; the rest of the interval is
dropped and reported as ``dropped_time``: the chains skip ahead carried rigidly by their
anchors (``carry_with_anchors``), their motion relative to the anchor kept.

A guard checks the state after every call: finite, the joint solve did not fail ('solver
failure: ...'), speeds below ``guard_max_speed``, no joint turning more than
``guard_max_step_angle`` per step (for RK4 also no segment's gyroscopic precession beyond
``guard_max_step_angle / GYROSCOPIC_REACH_RATIO``), joint gaps below ``guard_max_gap``; a
blow-up resets the chains to rest at the current head pose and is reported, never propagated.
"""
import math
import time

import numpy as np

from . import chain_ops, collision, lanes, stages, state_kernels, step as compiled
from .chain_ops import carry_with_anchors
from .contact_steps import MAX_SUBSTEPS, SUBSTEP_ANGLE, ContactSteps
from .direct_call import DirectCall
from .guard import GYROSCOPIC_REACH_RATIO, Guard
from .head import (
    ANCHOR_FIELDS,
    STATE_FIELDS,
    AnchorKinematics,
    AnchorTrack,
    HeadMotion,
    KinematicState,
    point_table,
    stack_anchors,
    stage_times,
)
from .head_kernels import frame_tables
from .model import Model
from .report import Rollout, StepReport
from .rollout import RolloutSteps, memo_last
from .rotations import quat_conjugate, quat_multiply
from .scene import SceneError, check_range, check_vector
from .state import ChainState, joint_points

__all__ = ['Simulator', 'StepReport', 'Rollout', 'TUNABLE_PARAMETERS', 'SUBSTEP_ANGLE',
           'MAX_SUBSTEPS', 'GYROSCOPIC_REACH_RATIO', 'carry_with_anchors']

# name -> (allowed range, per-chain?) of the parameters that can change between steps.
TUNABLE_PARAMETERS = {
    'damping': ((0.0, 1e3), True),
    'stiffness': ((0.0, 1e4), True),
    'drag_linear': ((0.0, 1e3), True),
    'drag_quadratic': ((0.0, 1e3), True),
    'gravity': ((-1e4, 1e4), False),
    'wind': ((-1e3, 1e3), False),
}


class Simulator(RolloutSteps, ContactSteps, Guard):
    """Chains of rigid segments on ball joints, hung from kinematic bodies.

    Args:
        scene: a validated ``Scene``.
        head: the kinematic bodies' state at ``t0`` (``KinematicState``) or a ``HeadMotion``;
            the chains start hanging at rest (see ``reset``). Default: still at the origin.
        t0: start time, s.
    """

    def __init__(self, scene, head=None, t0=0.0):
        self.scene = scene
        self.model = Model(scene)
        s = scene.solver
        self.dt = s.dt
        self.integrator = compiled.INTEGRATORS[s.integrator]
        # RK4 integrates the gyroscopic term explicitly (the others: ``step._rotation_kick``).
        self._explicit_gyroscopic = self.integrator.explicit_gyroscopic
        self.axisymmetric = chain_ops.is_axisymmetric(self.model)
        # The model's constant tuple of the compiled joint kernels (``chain_ops``).
        self._joint_args = chain_ops.joint_args(self.model)
        # Joint forces f_c (N) on each child at the last stage solved (``constraint_forces``).
        self.f_c = np.zeros((self.model.n, 3))
        self._half = 0.5 * self.model.length
        self._anchor_body = np.ascontiguousarray(self.model.anchor_body, dtype=np.int64)
        # ``_advance_between``'s points: (bodies K, body indices, points in the bodies).
        self._frame_points = (-1, None, None)
        self._zeros = np.zeros((self.model.n, 3))
        self.external = None
        self._step_model_cache = None
        self._last_kernel: tuple = (None, None)     # (StepModel, its compiled step)
        self._motion_anchors: tuple = (None, None)  # (motion, its anchors: _anchors_of)
        # ``_points_ahead``'s table: ((motion, t_base, dt), first step, end step, table).
        self._ahead: tuple = (None, 0, 0, None)
        self._measures_out = np.empty(len(state_kernels.MEASURES))
        # The compiled calls of the current ``advance``: the free step's wall time and the
        # contact step's (s), and the cycles of the latter's stages (``stages.PROFILE_STAGES``,
        # then its calls' total).
        self._call_wall = 0.0
        self._uni_wall = 0.0
        self._profile = np.zeros(stages.PROFILE_SIZE, dtype=np.int64)
        self.total_resets = 0
        # One-sided constraints: built only when the scene has them (otherwise never touched).
        m = self.model
        self.unilateral = (collision.Unilateral(m, self.dt)
                           if m.has_colliders or m.has_limits else None)
        self._needs_bodies = bool(m.has_colliders and np.any(m.collider_body >= 0))
        # A crowd of equal chains steps in SIMD lanes when its terms allow (``lanes``).
        self._crowd = lanes.crowd_layout(m)
        # The kernels this scene runs, compiled now and said (if an entry point asked).
        # (Imported here: ``python -m ponytail_ros.core.compile`` runs it as __main__.)
        from . import compile as kernels_compile
        kernels_compile.prepare(self)
        if head is None:
            head = KinematicState.still(np.zeros((scene.n_kinematic_bodies, 3)))
        if isinstance(head, HeadMotion):
            head = head.state_at(t0)
        self.reset(head, t0)

    # -- set-up ---------------------------------------------------------------------------
    def anchors(self, head):
        """``AnchorKinematics`` of every chain's attachment point for a ``KinematicState``."""
        return head.point_kinematics(self.model.anchor_body, self.model.attach)

    def reset(self, head, t=None, state=None):
        """Put the chains at rest on ``head`` (a ``KinematicState``), or in ``state``.

        At rest: every segment points along its chain's rest direction (given in the anchor
        frame, or gravity's direction), and the chain moves rigidly with its anchor body (zero
        relative angular velocity at every joint). The first joint's rest orientation, which
        the bending stiffness pulls towards, is taken from this pose.
        """
        m = self.model
        if t is not None:
            self.t = float(t)
        self._t_base, self._n_steps = self.t, 0
        anchor = self.anchors(head)
        q_anchor = anchor.orientation
        if state is None:
            state = self._rest_state(head, anchor)
        self.state = state.copy()
        m.q_rest[m.is_first] = quat_multiply(quat_conjugate(q_anchor), self.state.q[m.is_first])
        self._last_anchor = (self.t, anchor)
        self._anchor_at = lambda t: anchor          # until a motion or frame says otherwise
        self.f_c = np.zeros((m.n, 3))
        if self._needs_bodies:
            bodies = _body_kinematics(head)
            self._last_bodies = (self.t, bodies)
            self._bodies_at = lambda t: bodies

    def _rest_state(self, head, anchor):
        """Every chain at rest on ``head`` (``reset``'s state), its anchors ``anchor``."""
        return chain_ops.rest_state(self.model, self._joint_args, head, anchor)

    def reset_chains(self, chains, head):
        """Put only the chains ``chains`` (indices into the scene's chains) at rest on ``head``
        (a ``KinematicState``), as ``reset`` puts every chain; the other chains, the time and
        the step grid are kept. What a runner does when one character's frame teleports: that
        character's chains restart at rest on its new pose, the rest of the crowd carries on.
        The next ``advance_frame`` should be given ``head_prev`` (the anchors' track between
        the frames then starts at the new pose, not at the old one)."""
        m = self.model
        chains = np.asarray(chains, dtype=np.int64).reshape(-1)
        if chains.size and (chains.min() < 0 or chains.max() >= m.n_chains):
            raise ValueError(f'chains {chains.tolist()}: indices must be in [0, {m.n_chains})')
        rows = np.isin(m.chain_of, chains)
        if not rows.any():
            return
        anchor = self.anchors(head)
        rest, st = self._rest_state(head, anchor), self.state
        self.state = ChainState(*(np.where(rows[:, None], a, b) for a, b in zip(
            (rest.x, rest.q, rest.v, rest.w), (st.x, st.q, st.v, st.w), strict=True)))
        first = m.is_first & rows
        m.q_rest[first] = quat_multiply(quat_conjugate(anchor.orientation[m.chain_of[first]]),
                                        self.state.q[first])
        t_last, last = self._last_anchor
        reset_chain = np.isin(np.arange(m.n_chains), chains)[:, None]
        self._last_anchor = (t_last, AnchorKinematics(*(
            np.where(reset_chain, getattr(anchor, f), getattr(last, f)) for f in ANCHOR_FIELDS)))
        f_c = np.array(self.f_c, dtype=float, copy=True)
        f_c[rows] = 0.0
        self.f_c = f_c

    # -- parameters -----------------------------------------------------------------------
    def set_parameters(self, chain=None, **values):
        """Change tunable parameters (``TUNABLE_PARAMETERS``) from the next step on.

        ``chain``: index of the chain to change (per-chain terms), or ``None`` for all.
        All values are validated first; on any error nothing changes (``SceneError``).
        """
        m = self.model
        checked = {}
        for name, value in values.items():
            if name not in TUNABLE_PARAMETERS:
                raise SceneError(name, value, f'one of {sorted(TUNABLE_PARAMETERS)}')
            (lo, hi), per_chain = TUNABLE_PARAMETERS[name]
            if per_chain:
                check_range(name, float(value), lo, hi)
                checked[name] = float(value)
            else:
                checked[name] = check_vector(name, value, max_abs=hi)
        if chain is not None and not 0 <= chain < m.n_chains:
            raise SceneError('chain', chain, f'an integer in [0, {m.n_chains - 1}]')
        sl = slice(None) if chain is None else m.chain_slice(chain)
        for name, value in checked.items():
            if TUNABLE_PARAMETERS[name][1]:
                getattr(m, name)[sl] = value
            else:
                setattr(m, name, value)
        m.refresh_terms()
        self._step_model_cache = None

    def set_external(self, force=None, torque=None):
        """Hold applied forces/torques ``(n, 3)`` (N, N·m) at the centres until cleared (None)."""
        n = self.model.n
        self._step_model_cache = None
        if force is None and torque is None:
            self.external = None
            return
        f = np.zeros((n, 3)) if force is None else np.asarray(force, dtype=float).reshape(n, 3)
        tq = np.zeros((n, 3)) if torque is None else np.asarray(torque, dtype=float).reshape(n, 3)
        self.external = (f, tq)

    def apply_impulse(self, segment, impulse, point=None):
        """Apply an impulse (N·s, world) to one segment at a world point (default: its centre).

        The chain responds as a whole: the joint impulses are solved at velocity level
        (J M⁻¹ Jᵀ λ = -J u) with the same O(n) factorisation, so the joints stay closed.
        """
        m, st = self.model, self.state
        impulse = check_vector('impulse', impulse, max_abs=1e6)
        if not 0 <= segment < m.n:
            raise SceneError('segment', segment, f'an integer in [0, {m.n - 1}]')
        r = np.zeros(3) if point is None else check_vector('point', point) - st.x[segment]
        if not chain_ops.apply_impulse(m, self._joint_args, st, self._last_anchor[1], segment,
                                       impulse, r):
            raise np.linalg.LinAlgError('J M⁻¹ Jᵀ is not positive definite')

    # -- stepping -------------------------------------------------------------------------
    def advance_to(self, t_target, motion):
        """Advance to ``t_target`` (s) with the head given exactly at every stage time.

        ``motion``: a ``HeadMotion`` (``state_at(t) -> KinematicState``); the anchors at the
        call's stage times are its ``stage_points``, evaluated once per call.
        """
        m = self.model
        if not self._needs_bodies:
            anchor_at = self._anchors_of(motion)
            self._anchor_at = anchor_at
            if self.unilateral is None:
                n_steps = self._steps_to(t_target)
                if 0 < n_steps <= self.scene.solver.max_steps_per_call:
                    return self._free_steps(n_steps, motion, anchor_at)

            def anchor_points(k0, n_steps):
                return motion.stage_points(self._t_base, k0, n_steps, self.dt,
                                           self._anchor_body, m.attach)
            return self._advance(t_target, anchor_at, motion.state_at, anchor_table=anchor_points)
        # Colliders fixed in moving bodies: one evaluation of the motion for both, at every
        # time and for the anchors' and the bodies' tables.
        state_at = memo_last(motion.state_at)
        anchor_at = memo_last(lambda t: self.anchors(state_at(t)))
        bodies_at = memo_last(lambda t: _body_kinematics(state_at(t)))
        states = memo_last(lambda steps: motion.states_at(
            stage_times(self._t_base, steps[0], steps[1], self.dt)), 1)

        def anchor_table(k0, n_steps):
            return point_table(states((k0, n_steps)), m.anchor_body, m.attach)

        def body_table(k0, n_steps):
            at = states((k0, n_steps))
            k = at.position.shape[1]
            return point_table(at, np.arange(k), np.zeros((k, 3)))

        self._anchor_at = anchor_at
        report = self._advance(t_target, anchor_at, motion.state_at, bodies_at,
                               anchor_table=anchor_table, body_table=body_table)
        self._bodies_at = bodies_at
        self._last_bodies = (self.t, bodies_at(self.t))
        return report

    def _anchors_of(self, motion):
        """The anchors of ``motion`` at a time (the last few memoised), kept across calls
        while it is the same ``fixed`` motion (one that never changes)."""
        last, anchor_at = self._motion_anchors
        if last is not motion or not motion.fixed:
            anchor_at = memo_last(lambda t: self.anchors(motion.state_at(t)))
            self._motion_anchors = (motion, anchor_at)
        return anchor_at

    def advance_frame(self, t_frame, head, head_prev=None):
        """Advance to ``t_frame`` (s) given the head only at frames (``KinematicState``).

        Between the previous frame and this one the anchor follows the quintic Hermite through
        both ends' attachment-point position, velocity and acceleration (``AnchorTrack``).

        ``head_prev``: the head at the previous frame's time *as the same estimate sees it*.
        Pass it when frames come from an estimator that refits every frame (pose samples
        extrapolated or smoothed): a C² track from the old estimate to the new one would have
        to bridge their disagreement δ within one frame, an acceleration spike ~60 δ / Δt²
        that pumps energy into the chain. With both ends from one estimate the disagreement
        only shifts the anchor kinematically at the frame boundary, which the projection
        absorbs. Default: the end of the previous frame.
        """
        t_prev, a_prev = self._last_anchor
        if head_prev is not None:
            return self._advance_between(t_prev, t_frame, head_prev, head)
        _check_head(head)
        a_new = self.anchors(head)
        track = AnchorTrack(t_prev, a_prev, t_frame, a_new)
        if not self._needs_bodies:
            report = self._advance(t_frame, memo_last(track.at), lambda t: head,
                                   anchor_table=self._track_table(track))
        else:
            # Colliders fixed in kinematic bodies follow the same interpolation as anchors.
            b_new = _body_kinematics(head)
            body_track = AnchorTrack(t_prev, self._last_bodies[1], t_frame, b_new)
            report = self._advance(t_frame, memo_last(track.at), lambda t: head,
                                   memo_last(body_track.at),
                                   anchor_table=self._track_table(track),
                                   body_table=self._track_table(body_track))
            self._bodies_at = body_track.at
            self._last_bodies = (float(t_frame), b_new)
        self._anchor_at = track.at
        self._last_anchor = (float(t_frame), a_new)
        return report

    def _advance_between(self, t_prev, t_frame, head_prev, head):
        """``advance_frame`` with ``head_prev``: the check that both states are finite, the
        ends of the anchors' track (and of the colliders' bodies', both from the one estimate)
        and their tables at the stage times of the steps this call will take, in one compiled
        call (``head_kernels.frame_tables``; bit for bit ``frame_ends``, ``AnchorTrack.table``
        and ``_stage_times``), then the steps."""
        k = head.n_bodies if self._needs_bodies else 0
        if self._frame_points[0] != k:
            m = self.model
            self._frame_points = (k, np.concatenate([self._anchor_body, np.arange(k)]),
                                  np.ascontiguousarray(np.concatenate([m.attach,
                                                                       np.zeros((k, 3))])))
        _, body, r_local = self._frame_points
        C = self._anchor_body.shape[0]
        n0, n = self._n_steps, self._planned_steps(t_frame)
        ends_a, ends_b = _anchor_tuple(2, C), _anchor_tuple(2, k)
        table_a, table_b = _anchor_tuple(2 * n + 2, C), _anchor_tuple(2 * n + 2, k)
        if not frame_tables(*(_c(getattr(head_prev, f)) for f in STATE_FIELDS),
                            *(_c(getattr(head, f)) for f in STATE_FIELDS), body, r_local, C,
                            float(t_prev), float(t_frame), self._t_base, n0, n, self.dt,
                            ends_a, ends_b, table_a, table_b):
            _check_head(head)           # raises, naming the field
            _check_head(head_prev)
        # The steps' tables, for the steps from n0 (``_steps_unilateral``, ``_advance``); their
        # last row is the anchors at the frame's end, where the chain is published.
        planned = (n0, n, compiled.AnchorTable(*(a[:-1] for a in table_a)),
                   compiled.AnchorTable(*(a[:-1] for a in table_b)))
        at_frame = AnchorKinematics(*(a[-1] for a in table_a))
        ends = AnchorKinematics(*ends_a)
        track = AnchorTrack.from_ends(t_prev, t_frame, ends)
        if not self._needs_bodies:
            report = self._advance(t_frame, memo_last(track.at), lambda t: head,
                                   anchor_table=self._track_table(track), planned=planned)
        else:
            body_ends = AnchorKinematics(*ends_b)
            body_track = AnchorTrack.from_ends(t_prev, t_frame, body_ends)
            report = self._advance(t_frame, memo_last(track.at), lambda t: head,
                                   memo_last(body_track.at),
                                   anchor_table=self._track_table(track),
                                   body_table=self._track_table(body_track), planned=planned)
            self._bodies_at = body_track.at
            self._last_bodies = (float(t_frame), body_ends.row(1))
        t_frame = float(t_frame)
        self._anchor_at = lambda t: at_frame if t == t_frame else track.at(t)
        self._last_anchor = (t_frame, ends.row(1))
        return report

    def _planned_steps(self, t_target):
        """The steps a call to ``t_target`` takes from the current one, when they are all
        taken (none beyond ``max_steps_per_call``), else 0."""
        n = self._steps_to(t_target)
        return n if 0 < n <= self.scene.solver.max_steps_per_call else 0

    def _steps_to(self, t_target):
        """Internal steps from the current one to the last at or before ``t_target``."""
        return math.floor((t_target - self._t_base) / self.dt + 1e-9) - self._n_steps

    def _stage_times(self, n_steps):
        """Times ``(2 n_steps + 1,)`` of the anchor table of the next ``n_steps`` steps: row
        ``2k`` at step k's start, ``2k + 1`` at its midpoint, ``2k + 2`` at its end."""
        return stage_times(self._t_base, self._n_steps, n_steps, self.dt)

    def _track_table(self, track):
        """An ``AnchorTrack``'s table function for ``_tables``: the track at the stage times
        of ``n_steps`` steps from step ``k0``."""
        return lambda k0, n_steps: track.table(stage_times(self._t_base, k0, n_steps, self.dt))

    def _step_model(self):
        """The compiled step's ``StepModel``: the model's current arrays and switches, built
        again only after ``set_parameters`` or ``set_external`` (its arrays are the model's
        own, so values written into them in place, as ``reset`` writes ``q_rest``, need no
        rebuild)."""
        if self._step_model_cache is None:
            self._step_model_cache = self._build_step_model()
        return self._step_model_cache

    def _build_step_model(self):
        m, s = self.model, self.scene.solver
        damping = m.active_terms['damping']
        return compiled.StepModel(
            length=m.length, half=self._half, mass=m.mass, inv_mass=m.inv_mass,
            inertia=m.inertia, inv_inertia=m.inv_inertia, chain_of=m.chain_of, is_first=m.is_first,
            has_child=m.has_child, damping=m.damping, stiffness=m.stiffness,
            drag_linear=m.drag_linear, drag_quadratic=m.drag_quadratic, q_rest=m.q_rest,
            gravity=np.asarray(m.gravity, dtype=float), wind=np.asarray(m.wind, dtype=float),
            axisymmetric=self.axisymmetric,
            integrator=self.integrator.id, projection=bool(s.projection),
            gravity_on=m.active_terms['gravity'],
            explicit_damping=bool(damping and not m.implicit_damping),
            implicit_damping=bool(damping and m.implicit_damping),
            stiffness_on=m.active_terms['stiffness'], drag_on=m.active_terms['drag'],
            external_on=self.external is not None,
            baumgarte_stiffness=float(s.baumgarte_stiffness),
            baumgarte_damping=float(s.baumgarte_damping))

    def _run_compiled(self, n_steps, h, table, x, q, v, w):
        """``n_steps`` steps of ``h`` in one compiled call, the state arrays updated in place."""
        self._run_compiled_table(n_steps, h, self._table(table), x, q, v, w)

    def _run_compiled_table(self, n_steps, h, A, x, q, v, w, model=None):
        """``_run_compiled`` with the compiled ``AnchorTable`` ``A`` (and ``StepModel``)."""
        ext_F, ext_T = self._external_arrays()
        f_c = np.zeros((self.model.n, 3))
        model = self._step_model() if model is None else model
        kernel = self._kernel(model)
        t0 = time.perf_counter()
        status = kernel(model, A, n_steps, h, x, q, v, w, ext_F, ext_T, f_c)
        self._call_wall += time.perf_counter() - t0
        self.f_c = f_c
        if status == compiled.JOINT_SOLVE_FAILED:
            raise np.linalg.LinAlgError('J M⁻¹ Jᵀ is not positive definite')
        if status == compiled.DAMPING_SOLVE_FAILED:
            raise np.linalg.LinAlgError('implicit damping KKT system is singular')

    def _kernel(self, model):
        """The compiled step for ``model`` (a ``StepModel``): ``lanes.advance_lanes`` for a
        crowd whose terms it covers, else ``step.advance_rk4`` or ``step.advance`` (the same
        results bit for bit; ``lanes.kernel_for``), kept for the last ``model``."""
        last, kernel = self._last_kernel
        if model is not last:
            # Called directly after the first call (``DirectCall``): the arguments' types are
            # this model's and the simulator's own C float arrays' at every call.
            kernel = DirectCall(lanes.kernel_for(model, self._crowd))
            self._last_kernel = (model, kernel)
        return kernel

    def _advance(self, t_target, anchor_at, head_at, bodies_at=None, anchor_table=None,
                 body_table=None, planned=None):
        """``planned``: ``(k0, n, A, B)``, the ``AnchorTable`` of the anchors and of the bodies
        for the ``n`` steps from step ``k0`` (``_advance_between``), used when they are the
        steps taken."""
        report = StepReport()
        n_steps = self._steps_to(t_target)
        cap = self.scene.solver.max_steps_per_call
        m, st = self.model, self.state
        x, q, v, w = st.x, st.q, st.v, st.w
        if n_steps > cap:
            # Skip ahead: drop the time beyond the cap, keeping the step grid, and carry the
            # chains with their anchors over the skipped time (else the first step would have
            # to close the whole displacement at once: a whip, or a blow-up).
            report.dropped_time = (n_steps - cap) * self.dt
            t_from = self._t_base + self._n_steps * self.dt
            self._n_steps += n_steps - cap
            n_steps = cap
            x, q, v, w = carry_with_anchors(m, anchor_at(t_from),
                                            anchor_at(self._t_base + self._n_steps * self.dt),
                                            x, q, v, w)
        failure = None
        self._end_row = None            # the last anchor table's end row: the anchor at self.t
        self._call_wall = self._uni_wall = 0.0
        t_start = time.perf_counter()
        try:
            if self.unilateral is not None:
                self._profile[:] = 0
                x, q, v, w = self._steps_unilateral(max(n_steps, 0), anchor_at, bodies_at,
                                                    x, q, v, w, anchor_table, body_table,
                                                    planned)
            elif n_steps > 0:
                table, _ = self._tables(n_steps, anchor_at, anchor_table, planned)
                x, q = np.array(x, dtype=float), np.array(q, dtype=float)
                v, w = np.array(v, dtype=float), np.array(w, dtype=float)
                self._run_compiled_table(n_steps, self.dt, table, x, q, v, w)
                self._n_steps += n_steps
                self._end_row = table
            report.steps = max(n_steps, 0)
        except np.linalg.LinAlgError as err:
            # The state reached a configuration the joint solve cannot handle: reset, and say so.
            failure = str(err)
            x = np.full_like(x, np.nan)
        t_steps = time.perf_counter()
        self.t = self._t_base + self._n_steps * self.dt
        self.state = ChainState(x, q, v, w)
        # The table's end row is the anchor at self.t bit for bit (the same evaluation).
        end = self._end_row
        anchor = anchor_at(self.t) if end is None or failure is not None else AnchorKinematics(
            end.position[-1], end.velocity[-1], end.acceleration[-1], end.orientation[-1],
            end.angular_velocity[-1])
        self._end_call(report, anchor, failure, head_at)
        report.timings = {'steps': t_steps - t_start, 'guard': time.perf_counter() - t_steps}
        self._split_timings(report)
        return report

    def _free_steps(self, n_steps, motion, anchor_at):
        """``_advance`` to the end of the next ``n_steps`` steps (``0 < n_steps <=
        max_steps_per_call``) of a scene without colliders or limits, its anchors
        ``motion.stage_points``: the same, bit for bit, in fewer Python steps (a call's
        Python costs about what the compiled steps of a short chain do)."""
        report = StepReport(steps=n_steps)
        self._call_wall = self._uni_wall = 0.0
        t_start = time.perf_counter()
        table = self._points_ahead(motion, n_steps) if motion.fixed else self._table(
            motion.stage_points(self._t_base, self._n_steps, n_steps, self.dt,
                                self._anchor_body, self.model.attach))
        st = self.state
        x, q = np.array(st.x, dtype=float), np.array(st.q, dtype=float)
        v, w = np.array(st.v, dtype=float), np.array(st.w, dtype=float)
        failure = None
        try:
            self._run_compiled_table(n_steps, self.dt, table, x, q, v, w)
            self._n_steps += n_steps
        except np.linalg.LinAlgError as err:
            failure = str(err)
            report.steps = 0
            x = np.full_like(x, np.nan)
        t_steps = time.perf_counter()
        self.t = self._t_base + self._n_steps * self.dt
        self.state = ChainState(x, q, v, w)
        # (the table's end row is the anchor at self.t bit for bit: the same evaluation)
        ap, av, aa, ao, aw = table
        self._end_call(report, AnchorKinematics(ap[-1], av[-1], aa[-1], ao[-1], aw[-1])
                       if failure is None else anchor_at(self.t), failure, motion.state_at)
        report.timings = {'steps': t_steps - t_start, 'guard': time.perf_counter() - t_steps,
                          'integrate': self._call_wall, **_NO_CONTACTS}
        return report

    def _points_ahead(self, motion, n_steps):
        """The compiled ``AnchorTable`` of ``motion.stage_points`` of the next ``n_steps``
        steps for a ``fixed`` motion: rows of a table evaluated ahead for this call and the
        next few (``AHEAD_ROWS`` rows of anchors in all; the same values bit for bit: each
        row's time is computed from its step's index alike), evaluated again when the motion,
        the step grid or the range changes."""
        k0 = self._n_steps
        key = (motion, self._t_base, self.dt)
        last_key, first, stop, table = self._ahead
        if last_key != key or not first <= k0 or k0 + n_steps > stop:
            C = self._anchor_body.shape[0]
            first, stop = k0, k0 + max(n_steps, AHEAD_ROWS // (2 * max(C, 1)))
            table = self._table(motion.stage_points(self._t_base, first, stop - first, self.dt,
                                                    self._anchor_body, self.model.attach))
            self._ahead = (key, first, stop, table)
        row = 2 * (k0 - first)
        if row == 0 and k0 + n_steps == stop:
            return table
        rows = slice(row, row + 2 * n_steps + 1)
        p, v, a, q, w = table
        return compiled.AnchorTable(p[rows], v[rows], a[rows], q[rows], w[rows])

    def _split_timings(self, report):
        """``report.timings``' ``integrate`` and ``contacts`` (and the latter's parts): the
        contact step's calls' wall time split by the cycles it counted in each stage, plus the
        free step's (sub-steps after an impact) as ``integrate``."""
        free, uni = self._call_wall, self._uni_wall
        if uni == 0.0:                  # (no contact step ran: no cycles to split)
            report.timings['integrate'] = free
            report.timings.update(_NO_CONTACTS)
            return
        integrate, contacts, total, *parts = self._profile.tolist()
        if total > 0:
            report.timings['integrate'] = free + uni * (integrate / total)
            report.timings['contacts'] = uni * (contacts / total)
        else:
            report.timings['integrate'] = free + uni
            report.timings['contacts'] = 0.0
        for name, cycles in zip(stages.CONTACT_STAGES, parts, strict=True):
            report.timings[f'contact_{name}'] = uni * (cycles / total) if total > 0 else 0.0

    def _end_call(self, report, anchor, failure, head_at):
        """The end of a call at ``self.t`` with the anchor there: its joint gap into
        ``report``, the guard, and on a blow-up (or the solver's ``failure``) the reset at rest
        on ``head_at(self.t)``, said in ``report``. Returns the reset reason, or None."""
        self._last_anchor = (self.t, anchor)
        g = self._measures(anchor)
        report.max_gap = float(g[1]) if g[0] else np.inf
        reason = self._guard(g, failure)
        if reason is not None:
            self.total_resets += 1
            report.reset_reason = reason
            self.reset(head_at(self.t))
            report.max_gap = float(np.max(self.joint_gaps(self.anchors(head_at(self.t)))))
        return reason

    def _tables(self, n_steps, anchor_at, anchor_table, planned, moving=False, bodies_at=None,
                body_table=None):
        """The compiled ``AnchorTable``s of the anchors and of the bodies (the anchors' again
        unless the colliders are ``moving``) at the stage times of the next ``n_steps``
        steps: ``planned``'s (``_advance``) when they are its steps, else from the tables'
        functions (``anchor_table(k0, n_steps)``, ``body_table`` alike: the table of
        ``n_steps`` steps from step ``k0``), or the anchors and bodies at each time.

        After a step taken in sub-steps the call goes on from a later step: the steps left
        are the end of ``planned``'s, whose rows from that step on are theirs, bit for bit
        (the same stage times), so they are sliced, not evaluated again (in a crowd, where
        any chain's fast joint sub-steps the step, evaluating them in Python cost more than
        the compiled steps of a late tick)."""
        if planned is not None:
            k0, n_planned, A, B = planned
            skip = self._n_steps - k0
            if 0 <= skip and skip + n_steps == n_planned:
                if skip:
                    A, B = _table_rows(A, 2 * skip), _table_rows(B, 2 * skip)
                return A, B if moving else A
        k0 = self._n_steps
        A = self._table(anchor_table(k0, n_steps) if anchor_table else
                        stack_anchors([anchor_at(t) for t in self._stage_times(n_steps)]))
        if not moving:
            return A, A
        return A, self._table(body_table(k0, n_steps) if body_table else
                              stack_anchors([bodies_at(t) for t in self._stage_times(n_steps)]))

    @staticmethod
    def _table(t):
        """The compiled ``AnchorTable`` of an ``AnchorKinematics`` table (its arrays as they
        are when C-contiguous floats, as the tables' functions give them)."""
        return compiled.AnchorTable(_c(t.position), _c(t.velocity), _c(t.acceleration),
                                    _c(t.orientation), _c(t.angular_velocity))

    def _external_arrays(self):
        if self.external is None:
            return self._zeros, self._zeros
        return tuple(np.ascontiguousarray(a, dtype=float) for a in self.external)

    # -- observation ----------------------------------------------------------------------
    def state_at(self, t):
        """The chain at time ``t`` (s), up to one step past the last internal step (not stored).

        The accumulator leaves the chain up to ``dt`` behind the requested time; reporting that
        state as "now" would lag by ``v·dt``. Instead every segment's orientation is carried
        forward by its ω over the remainder τ = t - self.t (q ← exp(ωτ) q, error O(α τ²)) and
        positions and velocities are rebuilt from the anchor at ``t`` (joints exactly closed).
        """
        tau = float(t) - self.t
        if tau <= 0.0:
            return self.state.copy()
        return chain_ops.state_ahead(self.model, self._joint_args, self.state,
                                     self._anchor_at(float(t)), tau)

    def contact_depths(self, t=None):
        """Deepest penetration of every segment into any collider, ``(n,)``, m (≤ 0: clear,
        -inf: the segment does not collide or the scene has no colliders), as the collision
        solver measures it (a chain's first segment rooted on a round collider: on its outer
        half; a plane: the deeper end).

        ``t``: of the chain reported at that time (``state_at``); default the last step.
        """
        m = self.model
        if not m.has_colliders:
            return np.full(m.n, -np.inf)
        t = self.t if t is None else float(t)
        state = self.state if t == self.t else self.state_at(t)
        bodies = self._bodies_at(t) if self._needs_bodies else None
        return collision.segment_depths(m, state.x, state.q, self._anchor_at(t).position, bodies)

    def joint_angles(self, t=None):
        """Swing and twist angle of every joint, ``(n,)`` each, rad (as the limits see them)."""
        from .limits import joint_angles
        t = self.t if t is None else float(t)
        state = self.state if t == self.t else self.state_at(t)
        return joint_angles(self.model, state.q, self._anchor_at(t).orientation)

    def joint_gaps(self, anchor=None):
        """Distance ``(n,)`` between the two sides of every joint, m."""
        m = self.model
        if anchor is None:
            anchor = self._last_anchor[1]
        prox, dist = joint_points(m, self.state)
        parent = np.where(m.is_first[:, None], anchor.position[m.chain_of],
                          np.roll(dist, 1, axis=0))
        return np.linalg.norm(parent - prox, axis=1)

    def joint_positions(self, t=None):
        """World positions of every segment's proximal and distal joint, ``(n, 3)`` each.

        ``t``: report the chain at that time (``state_at``) rather than at the last step.
        """
        return joint_points(self.model, self.state if t is None else self.state_at(t))

    def segment_poses(self, t=None):
        """Per segment: origin at the proximal joint and orientation (+X along the segment),
        ``(n, 3)`` m and ``(n, 4)``; ``t``: of the chain at that time, as ``state_at`` reports
        it (``state_kernels.segment_poses``)."""
        m, st = self.model, self.state
        tau = 0.0 if t is None else float(t) - self.t
        anchor = self._anchor_at(float(t)).position if tau > 0.0 else self._zeros[:0]
        origins, quats = np.empty((m.n, 3)), np.empty((m.n, 4))
        state_kernels.segment_poses(m.length, m.is_first, m.chain_of, _c(st.x), _c(st.q),
                                    _c(st.w), tau, _c(anchor), origins, quats)
        return origins, quats

    def energy(self):
        """Kinetic and gravitational potential energy of every chain, ``(C,)`` each, J."""
        return chain_ops.energy(self.model, self.state)

    @property
    def constraint_forces(self):
        """Joint forces f_c ``(n, 3)`` on each child at the last stage solved, N."""
        return self.f_c


#: Rows of anchors (rows of the table times chains) a simulator evaluates ahead for a fixed
#: motion (``HeadMotion.fixed``): a few calls' worth for a few chains, one call's for a crowd.
AHEAD_ROWS = 128
#: ``StepReport.timings``' contact entries of a call without the contact step.
_NO_CONTACTS = {'contacts': 0.0, **{f'contact_{name}': 0.0 for name in stages.CONTACT_STAGES}}


def _body_kinematics(head):
    """``AnchorKinematics`` of the origins of all kinematic bodies of a ``KinematicState``."""
    k = head.n_bodies
    return head.point_kinematics(np.arange(k), np.zeros((k, 3)))


def _c(a):
    return np.ascontiguousarray(a, dtype=float)


def _table_rows(table, row):
    """A compiled ``AnchorTable``'s rows from ``row`` on (views: a slice of rows of a
    C-contiguous array is C-contiguous, the type the compiled step already has)."""
    return compiled.AnchorTable(*(a[row:] for a in table))


def _anchor_tuple(S, C):
    """Empty arrays of an ``AnchorKinematics`` table of ``S`` rows of ``C`` points."""
    return (np.empty((S, C, 3)), np.empty((S, C, 3)), np.empty((S, C, 3)), np.empty((S, C, 4)),
            np.empty((S, C, 3)))


def _check_head(head):
    """Refuse a non-finite head state, naming the field: it must never reach the chain."""
    if np.isfinite(np.concatenate([getattr(head, name).ravel() for name in STATE_FIELDS])).all():
        return                          # (one check for all six; the field is named below)
    for name in STATE_FIELDS:
        if not np.isfinite(getattr(head, name)).all():
            raise SceneError(f'head.{name}', getattr(head, name).tolist(), 'finite numbers')
