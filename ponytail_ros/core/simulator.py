"""The simulator: a scene's chains advanced in fixed internal steps, driven by kinematic heads.

Stages of one internal step (as in a physics engine's pipeline):
    1. anchor kinematics at the stage times (exact motion, or interpolated between frames);
    2. applied forces (``forces``), then constraint forces by A f_c = b (``solver``);
    3. integration (``integrators``: RK4, symplectic Euler or RATTLE);
    4. stabilisation: positions put back on the joints (``stabilization``), and for RK4 the
       velocities too (symplectic Euler's and RATTLE's steps end with their own, mass-weighted,
       projection);
    5. only if the scene has colliders or joint limits: one-sided constraints at the step's end
       (``collision``: positions, then inelastic velocities, then friction).

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
from dataclasses import dataclass, field
from typing import NamedTuple, Optional

import numpy as np

from . import collision, contact_model, lanes, step_unilateral
from . import stages
from . import step as compiled
from .head import (ANCHOR_FIELDS, STATE_FIELDS, AnchorKinematics, AnchorTrack, HeadMotion,
                   KinematicState, point_table, stack_anchors)
from .head_kernels import frame_tables
from .integrators import INTEGRATOR_STEPS
from .model import Model
from .forces import applied_forces
from .rotations import (cross, quat_conjugate, quat_from_two_vectors,
                        quat_integrate, quat_multiply, quat_normalize, quat_rotate,
                        quat_to_matrix)
from .scene import SceneError, _check_range, _check_vector
from .solver import Dynamics
from .stabilization import project_positions, project_velocities
from .state import ChainState, half_vectors, joint_points
from . import state_kernels

__all__ = ['Simulator', 'StepReport', 'Rollout', 'TUNABLE_PARAMETERS']

# Scenes with colliders or joint limits: a step in which a joint turns by more than this
# (rad, at the start of the step) is split into sub-steps, at most MAX_SUBSTEPS.
SUBSTEP_ANGLE = 0.25
MAX_SUBSTEPS = 8
# RK4 follows a thin segment's gyroscopic precession (its body-frame ω turning at ~ its axial
# spin Ω) only to dt·Ω ≈ 1 (1.04 gains energy slowly, 1.25 blows up), a swing to ~2.5 (the
# linear limit is 2.8): the guard holds the precession to guard_max_step_angle / this.
GYROSCOPIC_REACH_RATIO = 2.5

_X = np.array([1.0, 0.0, 0.0])
# Collider arguments of a scene without colliders (limits only): no bodies, no colliders.
_NO_COLLIDER_ARGS = (np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3)),
                     np.zeros((0, 3)), np.zeros(0))

# name -> (allowed range, per-chain?) of the parameters that can change between steps.
TUNABLE_PARAMETERS = {
    'damping': ((0.0, 1e3), True),
    'stiffness': ((0.0, 1e4), True),
    'drag_linear': ((0.0, 1e3), True),
    'drag_quadratic': ((0.0, 1e3), True),
    'gravity': ((-1e4, 1e4), False),
    'wind': ((-1e3, 1e3), False),
}


@dataclass
class StepReport:
    """What one ``advance`` call did.

    ``timings``: wall seconds of the call's stages, like Box2D's ``b2Profile``: ``steps``
    (the anchor table and the compiled steps, contacts and limits included) and ``guard``
    (the checks of the state after the call, and a reset if one was needed); when the
    compiled step ran, also the split of its calls' time into ``integrate`` (the chains' own
    steps: forces, joint solves, integration, projection) and ``contacts`` (the contact and
    limit stage; 0 without colliders and limits), by the CPU's cycle counter
    (``stages.PROFILE_STAGES``; where there is none, ``integrate`` holds the calls' whole time),
    and of ``contacts`` into ``contact_rows``, ``contact_positions`` and
    ``contact_velocities`` (``stages.CONTACT_STAGES``; the rest of ``contacts``: the
    colliders posed, the positions kept, the call into each chain's stages).
    """

    steps: int = 0
    dropped_time: float = 0.0
    reset_reason: Optional[str] = None
    max_gap: float = 0.0
    timings: dict = field(default_factory=dict)


class Rollout(NamedTuple):
    """What ``Simulator.rollout`` did: one ``StepReport`` per sample and the chain's state
    after it (``(T, n, 3|4)`` arrays, as ``ChainState``: centres m, unit quaternions
    ``(x, y, z, w)`` body to world, velocities m/s, angular velocities rad/s; world frame)."""

    reports: list
    x: np.ndarray
    q: np.ndarray
    v: np.ndarray
    w: np.ndarray


class Simulator:
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
        self._step = INTEGRATOR_STEPS[s.integrator]
        # RK4's joint projection rebuilds v from ω; symplectic Euler's and RATTLE's steps end
        # with their own (M-orthogonal) velocity projection, which a rebuild would undo.
        self.integrator = compiled.INTEGRATORS[s.integrator]
        self._rebuild_velocities = self.integrator.rebuilds_velocities
        # RK4 integrates the gyroscopic term explicitly (the others: ``rotation_kick``).
        self._explicit_gyroscopic = self.integrator.explicit_gyroscopic
        self.dynamics = Dynamics(self.model, s.linear_solver,
                                 (s.baumgarte_stiffness, s.baumgarte_damping))
        # The compiled step (``step``) runs every banded scene; ``linear_solver: dense`` keeps
        # the NumPy reference step (``integrators`` + ``solver``) as the cross-check.
        self._compiled = s.linear_solver == 'banded'
        self._half = 0.5 * self.model.length
        self._anchor_body = np.ascontiguousarray(self.model.anchor_body, dtype=np.int64)
        # ``_advance_between``'s points: (bodies K, body indices, points in the bodies).
        self._frame_points = (-1, None, None)
        self._zeros = np.zeros((self.model.n, 3))
        self.external = None
        self._step_model_cache = None
        # The compiled calls of the current ``advance``: the free step's wall time and the
        # contact step's (s), and the cycles of the latter's stages (``stages.PROFILE_STAGES``,
        # then its calls' total).
        self._call_wall = 0.0
        self._uni_wall = 0.0
        self._profile = np.zeros(stages.PROFILE_SIZE, dtype=np.int64)
        self.total_resets = 0
        # One-sided constraints: built only when the scene has them (otherwise never touched).
        m = self.model
        self.unilateral = (collision.Unilateral(m, self.dynamics, self.dt)
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
        self.dynamics.last_f_c = np.zeros((m.n, 3))
        if self._needs_bodies:
            bodies = _body_kinematics(head)
            self._last_bodies = (self.t, bodies)
            self._bodies_at = lambda t: bodies

    def _rest_state(self, head, anchor):
        """Every chain at rest on ``head`` (``reset``'s state), its anchors ``anchor``."""
        m = self.model
        g = m.gravity
        down = g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0.0, 0.0, -1.0])
        local = ~np.isnan(m.rest_direction[:, 0])
        # Given in the anchor frame: the twist follows the anchor; along gravity: shortest arc.
        d_local = np.where(local[:, None], m.rest_direction, 1.0)
        q_chain = np.where(
            local[:, None],
            quat_multiply(anchor.orientation,
                          quat_from_two_vectors(np.broadcast_to(_X, d_local.shape), d_local)),
            quat_from_two_vectors(_X, down)[None])
        q = q_chain[m.chain_of]
        h = half_vectors(m.length, q)
        x = project_positions(m, anchor.position, h)
        head_w = head.angular_velocity[m.anchor_body][m.chain_of]
        w = head_w.copy()
        v = project_velocities(m, anchor.velocity, w, h)
        return ChainState(x, q, v, w)

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
            (rest.x, rest.q, rest.v, rest.w), (st.x, st.q, st.v, st.w))))
        first = m.is_first & rows
        m.q_rest[first] = quat_multiply(quat_conjugate(anchor.orientation[m.chain_of[first]]),
                                        self.state.q[first])
        t_last, last = self._last_anchor
        reset_chain = np.isin(np.arange(m.n_chains), chains)[:, None]
        self._last_anchor = (t_last, AnchorKinematics(*(
            np.where(reset_chain, getattr(anchor, f), getattr(last, f)) for f in ANCHOR_FIELDS)))
        f_c = np.array(self.dynamics.last_f_c, dtype=float, copy=True)
        f_c[rows] = 0.0
        self.dynamics.last_f_c = f_c

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
                _check_range(name, float(value), lo, hi)
                checked[name] = float(value)
            else:
                checked[name] = _check_vector(name, value, max_abs=hi)
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
        impulse = _check_vector('impulse', impulse, max_abs=1e6)
        if not 0 <= segment < m.n:
            raise SceneError('segment', segment, f'an integer in [0, {m.n - 1}]')
        r = np.zeros(3) if point is None else _check_vector('point', point) - st.x[segment]
        _, _, inv_I, _ = self.dynamics.mass_terms(st.q, st.w)
        kick = np.zeros((m.n, 3))
        kick[segment] = cross(r, impulse)
        st.v[segment] += impulse * m.inv_mass[segment]
        st.w += inv_I(kick)
        dv, dw = self.dynamics.velocity_correction(st.x, st.q, st.v, st.w, self._last_anchor[1])
        st.v += dv
        st.w += dw

    # -- stepping -------------------------------------------------------------------------
    def advance_to(self, t_target, motion):
        """Advance to ``t_target`` (s) with the head given exactly at every stage time.

        ``motion``: a ``HeadMotion`` (``state_at(t) -> KinematicState``).
        """
        states_at = _memo_times(motion.states_at)       # the anchors' and bodies' tables share it
        m = self.model

        def anchor_table(times):
            return point_table(states_at(times), m.anchor_body, m.attach)

        if not self._needs_bodies:
            anchor_at = _memo_last(lambda t: self.anchors(motion.state_at(t)))
            self._anchor_at = anchor_at
            return self._advance(t_target, anchor_at, motion.state_at, anchor_table=anchor_table)
        # Colliders fixed in moving bodies: one evaluation of the motion for both.
        state_at = _memo_last(motion.state_at)
        anchor_at = _memo_last(lambda t: self.anchors(state_at(t)))
        bodies_at = _memo_last(lambda t: _body_kinematics(state_at(t)))

        def body_table(times):
            states = states_at(times)
            k = states.position.shape[1]
            return point_table(states, np.arange(k), np.zeros((k, 3)))

        self._anchor_at = anchor_at
        report = self._advance(t_target, anchor_at, motion.state_at, bodies_at,
                               anchor_table=anchor_table, body_table=body_table)
        self._bodies_at = bodies_at
        self._last_bodies = (self.t, bodies_at(self.t))
        return report

    def rollout(self, times, motion):
        """``advance_to(t, motion)`` for every ``t`` of ``times`` in turn, bit for bit, with the
        motion and the anchor table evaluated once for all the calls' stage times (one
        vectorised ``states_at``), then one compiled call per sample: the way to run a known
        motion offline (a reference, a benchmark), like MuJoCo's ``rollout``.

        ``times``: ``(T,)`` increasing sample times (s). Returns a ``Rollout``: the ``T``
        calls' ``StepReport`` and the state after each, ``(T, n, 3|4)`` arrays. Scenes with
        colliders or joint limits, the dense NumPy step and a sample interval beyond
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
        if (self.unilateral is not None or not self._compiled or np.any(counts < 0)
                or np.any(counts > self.scene.solver.max_steps_per_call)):
            for k, t in enumerate(times):
                out.reports.append(self.advance_to(t, motion))
                self._store(out, k0 + k)
            return times.size
        m = self.model
        table = self._table(point_table(motion.states_at(self._stage_times(int(counts.sum()))),
                                        m.anchor_body, m.attach))
        self._anchor_at = _memo_last(lambda t: self.anchors(motion.state_at(t)))
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
            report = self._advance(t_frame, _memo_last(track.at), lambda t: head,
                                   anchor_table=track.table)
        else:
            # Colliders fixed in kinematic bodies follow the same interpolation as anchors.
            b_new = _body_kinematics(head)
            body_track = AnchorTrack(t_prev, self._last_bodies[1], t_frame, b_new)
            report = self._advance(t_frame, _memo_last(track.at), lambda t: head,
                                   _memo_last(body_track.at), anchor_table=track.table,
                                   body_table=body_track.table)
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
        and ``_stage_times``), then the steps (the NumPy reference step, ``linear_solver:
        dense``, takes the tracks and leaves the tables)."""
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
            report = self._advance(t_frame, _memo_last(track.at), lambda t: head,
                                   anchor_table=track.table, planned=planned)
        else:
            body_ends = AnchorKinematics(*ends_b)
            body_track = AnchorTrack.from_ends(t_prev, t_frame, body_ends)
            report = self._advance(t_frame, _memo_last(track.at), lambda t: head,
                                   _memo_last(body_track.at), anchor_table=track.table,
                                   body_table=body_track.table, planned=planned)
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
        k = self._n_steps + np.arange(n_steps + 1)
        t = self._t_base + k * self.dt
        times = np.empty(2 * n_steps + 1)
        times[0::2] = t
        times[1::2] = t[:-1] + 0.5 * self.dt
        return times

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
            axisymmetric=bool(self.dynamics.axisymmetric),
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
        t0 = time.perf_counter()
        status = self._kernel(model)(model, A, n_steps, h, x, q, v, w, ext_F, ext_T, f_c)
        self._call_wall += time.perf_counter() - t0
        self.dynamics.last_f_c = f_c
        if status == compiled.JOINT_SOLVE_FAILED:
            raise np.linalg.LinAlgError('J M⁻¹ Jᵀ is not positive definite')
        if status == compiled.DAMPING_SOLVE_FAILED:
            raise np.linalg.LinAlgError('implicit damping KKT system is singular')

    def _kernel(self, model):
        """The compiled step for ``model`` (a ``StepModel``): ``lanes.advance_lanes`` for a
        crowd whose terms it covers, else ``step.advance_rk4`` or ``step.advance`` (the same
        results bit for bit; ``lanes.kernel_for``)."""
        return lanes.kernel_for(model, self._crowd)

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
        project = self.scene.solver.projection
        implicit_damping = m.implicit_damping and m.active_terms['damping']
        system = _System(self, anchor_at)
        failure = None
        self._end_row = None            # the last anchor table's end row: the anchor at self.t
        self._call_wall = self._uni_wall = 0.0
        self._profile[:] = 0
        t_start = time.perf_counter()
        try:
            if self.unilateral is not None:
                x, q, v, w = self._steps_unilateral(max(n_steps, 0), system, anchor_at, bodies_at,
                                                    x, q, v, w, anchor_table, body_table,
                                                    planned)
            elif self._compiled:
                if n_steps > 0:
                    table, _ = self._tables(n_steps, anchor_at, anchor_table, planned)
                    x, q, v, w = (np.array(a, dtype=float) for a in (x, q, v, w))
                    self._run_compiled(n_steps, self.dt, table, x, q, v, w)
                    self._n_steps += n_steps
                    self._end_row = table
            else:
                for _ in range(max(n_steps, 0)):
                    t = self._t_base + self._n_steps * self.dt
                    x, q, v, w = self._step(system, t, self.dt, x, q, v, w)
                    self._n_steps += 1
                    t1 = self._t_base + self._n_steps * self.dt
                    if implicit_damping:
                        a1 = anchor_at(t1)
                        v, w = self.dynamics.implicit_damping(x, q, v, w, a1, self.dt)
                    if project:
                        x, v = self._project(anchor_at(t1), x, q, v, w)
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

    def _split_timings(self, report):
        """``report.timings``' ``integrate`` and ``contacts`` (and the latter's parts): the
        contact step's calls' wall time split by the cycles it counted in each stage, plus the
        free step's (sub-steps after an impact) as ``integrate``."""
        if not self._compiled:
            return
        integrate, contacts, total, *parts = self._profile.tolist()
        free, uni = self._call_wall, self._uni_wall
        if total > 0:
            report.timings['integrate'] = free + uni * (integrate / total)
            report.timings['contacts'] = uni * (contacts / total)
        else:
            report.timings['integrate'] = free + uni
            report.timings['contacts'] = 0.0
        for name, cycles in zip(stages.CONTACT_STAGES, parts):
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

    def _project(self, anchor, x, q, v, w):
        """Positions (and for RK4 velocities) put back on the joints at the step's end."""
        m = self.model
        h = half_vectors(m.length, q)
        x = project_positions(m, anchor.position, h)
        if self._rebuild_velocities:
            v = project_velocities(m, anchor.velocity, w, h)
        return x, v

    def _steps_unilateral(self, n_steps, system, anchor_at, bodies_at, x, q, v, w,
                          anchor_table=None, body_table=None, planned=None):
        """``n_steps`` steps of a scene with colliders or joint limits: each is integrated as
        above, then its contacts and limits are resolved (``collision``), all in one compiled
        call (``step_unilateral.advance_unilateral``). A step in which some joint turns faster
        than ``SUBSTEP_ANGLE`` per step (a whip crack after an impact) is split into up to
        ``MAX_SUBSTEPS`` equal sub-steps, each resolved likewise: the compiled call stops
        before it, and it is taken here (the anchors at the sub-step times are evaluated for
        it), then the call goes on."""
        if not self._compiled:
            for _ in range(n_steps):
                x, q, v, w = self._substepped(system, anchor_at, bodies_at, x, q, v, w)
            return x, q, v, w
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
                x, q, v, w = self._substepped(system, anchor_at, bodies_at, x, q, v, w)
                x, q, v, w = (np.array(a, dtype=float) for a in (x, q, v, w))
                done += 1
        uni.dt = self.dt
        return x, q, v, w

    def _tables(self, n_steps, anchor_at, anchor_table, planned, moving=False, bodies_at=None,
                body_table=None):
        """The compiled ``AnchorTable``s of the anchors and of the bodies (the anchors' again
        unless the colliders are ``moving``) at the stage times of the next ``n_steps``
        steps: ``planned``'s (``_advance``) when they are its steps, else from the tables'
        functions (or the anchors and bodies at each time).

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
        times = self._stage_times(n_steps)
        A = self._table(anchor_table(times) if anchor_table else
                        stack_anchors([anchor_at(t) for t in times]))
        if not moving:
            return A, A
        return A, self._table(body_table(times) if body_table else
                              stack_anchors([bodies_at(t) for t in times]))

    def _call_unilateral(self, n_steps, A, B, moving, x, q, v, w):
        uni = self.unilateral
        ext_F, ext_T = self._external_arrays()
        f_c = np.zeros((self.model.n, 3))
        stats = uni._stats
        cols = uni.colliders
        M = self._step_model()
        static_pose = uni.static_pose
        args = (M, A, n_steps, self.dt, x, q, v, w, ext_F, ext_T, f_c, B,
                moving, cols.args if cols is not None else _NO_COLLIDER_ARGS,
                static_pose, uni.model_args, uni.detector_args, uni.split_args,
                np.ascontiguousarray(self.model.q_rest), uni.detector is not None, stats,
                SUBSTEP_ANGLE, MAX_SUBSTEPS, self._profile,
                True if self._kernel(M) is lanes.advance_lanes else None,
                self._contact_workspace(static_pose),
                None if M.integrator == compiled.RK4 else True)
        t0 = time.perf_counter()
        status, k, tables, ids = step_unilateral.advance_unilateral(*args)
        self._uni_wall += time.perf_counter() - t0
        ws = uni.workspace
        if tables.shape != ws[contact_model.WS_TABLES].shape:
            # A step's rows overflowed the tables: the grown ones are kept (``grown``).
            uni.workspace = (ws[:contact_model.WS_TABLES] + (tables, ids)
                             + ws[contact_model.WS_IDS + 1:])
        self.dynamics.last_f_c = f_c
        uni.last = {'contacts': int(stats[0]), 'limits': int(stats[1]),
                    'position_passes': int(stats[2])}
        if status == compiled.JOINT_SOLVE_FAILED:
            raise np.linalg.LinAlgError('J M⁻¹ Jᵀ is not positive definite')
        if status == compiled.DAMPING_SOLVE_FAILED:
            raise np.linalg.LinAlgError('implicit damping KKT system is singular')
        return status, k

    def _contact_workspace(self, static_pose):
        """The contact stage's workspace of this structure, built once (``Unilateral``);
        ``static_pose``: the colliders' pose arrays (their count sizes it)."""
        uni = self.unilateral
        if uni.workspace is None:
            uni.workspace = contact_model.resolve_workspace(
                uni.model_args, uni.detector_args, uni.split_args, static_pose,
                uni.detector is not None)
        return uni.workspace

    def _substepped(self, system, anchor_at, bodies_at, x, q, v, w):
        """One step split into sub-steps (``_substeps``), each integrated and resolved."""
        m, dyn, uni = self.model, self.dynamics, self.unilateral
        project = self.scene.solver.projection
        implicit_damping = m.implicit_damping and m.active_terms['damping']
        t0 = self._t_base + self._n_steps * self.dt
        n_sub = self._substeps(w - m.parent_side(anchor_at(t0).angular_velocity, w))
        h = self.dt / n_sub
        for k in range(n_sub):
            t = t0 + k * h
            t1 = t0 + (k + 1) * h if k + 1 < n_sub else \
                self._t_base + (self._n_steps + 1) * self.dt
            a1 = anchor_at(t1)
            if self._compiled:
                x, q, v, w = (np.array(a, dtype=float) for a in (x, q, v, w))
                self._run_compiled(1, h, stack_anchors([anchor_at(t), anchor_at(t + 0.5 * h),
                                                        a1]), x, q, v, w)
            else:
                x, q, v, w = self._step(system, t, h, x, q, v, w)
                if implicit_damping:
                    v, w = dyn.implicit_damping(x, q, v, w, a1, h)
                if project:
                    x, v = self._project(a1, x, q, v, w)
            pose = uni.pose(bodies_at(t1) if bodies_at else None)
            x, q, v, w = uni.resolve(x, q, v, w, a1, pose, project, h)
        self._n_steps += 1
        return x, q, v, w

    @staticmethod
    def _table(t):
        return compiled.AnchorTable(*(np.ascontiguousarray(a, dtype=float) for a in (
            t.position, t.velocity, t.acceleration, t.orientation, t.angular_velocity)))

    def _external_arrays(self):
        if self.external is None:
            return self._zeros, self._zeros
        return tuple(np.ascontiguousarray(a, dtype=float) for a in self.external)

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

    def _measures(self, anchor):
        """``state_kernels.guard_measures`` of the state with ``anchor`` (its ``MEASURES``)."""
        m, st = self.model, self.state
        out = np.empty(len(state_kernels.MEASURES))
        swing_only = not self._explicit_gyroscopic and self.dynamics.axisymmetric
        state_kernels.guard_measures(m.length, m.is_first, m.chain_of, m.inertia, _c(st.x),
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
            gyro = precession if self.dynamics.axisymmetric else float(
                np.max(self.dynamics.gyroscopic_rates(self.state.q, self.state.w)))
            limit = s.guard_max_step_angle / GYROSCOPIC_REACH_RATIO
            if h * gyro > limit:
                return (f'gyroscopic precession at {gyro:.3g} rad/s (a segment spinning about its '
                        f'axis): {h * gyro:.3g} rad per step > guard_max_step_angle / '
                        f'{GYROSCOPIC_REACH_RATIO:g} = {limit:.3g}')
        if max_gap > s.guard_max_gap:
            return f'joint gap {max_gap:.3g} m > guard_max_gap {s.guard_max_gap:g}'
        return None

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
        m, st = self.model, self.state
        anchor = self._anchor_at(float(t))
        q = quat_integrate(st.q, st.w, tau)
        h = half_vectors(m.length, q)
        return ChainState(project_positions(m, anchor.position, h), q,
                          project_velocities(m, anchor.velocity, st.w, h), st.w.copy())

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
        m, st = self.model, self.state
        R = quat_to_matrix(st.q)
        w_body = np.einsum('nji,nj->ni', R, st.w)
        ke = 0.5 * m.mass * np.sum(st.v ** 2, axis=1) + 0.5 * np.sum(m.inertia * w_body ** 2, axis=1)
        pe = -m.mass * (st.x @ m.gravity)
        per_chain = np.zeros((2, m.n_chains))
        np.add.at(per_chain[0], m.chain_of, ke)
        np.add.at(per_chain[1], m.chain_of, pe)
        return per_chain[0], per_chain[1]

    @property
    def constraint_forces(self):
        """Joint forces f_c ``(n, 3)`` on each child at the last stage solved, N."""
        return self.dynamics.last_f_c


class _System:
    """The chains' dynamics for the integrators (``integrators`` module docstring): applied
    forces and the joint solve at any time of the step, with the anchors of ``anchor_at``."""

    def __init__(self, sim, anchor_at):
        self.model, self.dynamics, self.anchor = sim.model, sim.dynamics, anchor_at
        self.external = sim.external
        self.projection = sim.scene.solver.projection

    def applied(self, t, x, q, v, w):
        """Applied forces and torques ``(n, 3)`` each (N, N·m, world) at time ``t``."""
        anchor = self.anchor(t)
        return applied_forces(self.model, x, q, v, w, anchor.orientation,
                              anchor.angular_velocity, self.external)

    def accel(self, t, x, q, v, w):
        """Accelerations ``(a, α)`` ``(n, 3)`` each (m/s², rad/s², world), joints enforced."""
        F, T = self.applied(t, x, q, v, w)
        return self.dynamics.accelerations(x, q, v, w, self.anchor(t), F, T)


def carry_with_anchors(model, a0, a1, x, q, v, w):
    """The chains' state ``(x, q, v, w)`` moved rigidly with their anchor bodies from the
    ``AnchorKinematics`` ``a0`` to ``a1``: positions and orientations transformed with the
    anchor, velocities so that the motion relative to the anchor body is kept. Joints that were
    closed (in position and velocity) stay closed; a static anchor moves nothing."""
    c = model.chain_of
    dq = quat_multiply(a1.orientation, quat_conjugate(a0.orientation))[c]
    p0, w0, w1 = a0.position[c], a0.angular_velocity[c], a1.angular_velocity[c]
    r = quat_rotate(dq, x - p0)
    v_rel = v - a0.velocity[c] - cross(w0, x - p0)         # relative to the anchor body
    return (a1.position[c] + r, quat_normalize(quat_multiply(dq, q)),
            a1.velocity[c] + cross(w1, r) + quat_rotate(dq, v_rel), w1 + quat_rotate(dq, w - w0))


def _memo_last(f, size=2):
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


def _memo_times(f):
    """Cache ``f(times)`` for the last ``times`` array (by identity): the anchor and body
    tables of one call are evaluated from one evaluation of the motion."""
    last = [None, None]

    def g(times):
        if last[0] is not times:
            last[0], last[1] = times, f(times)
        return last[1]
    return g


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
