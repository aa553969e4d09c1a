"""The simulator: a scene's chains advanced in fixed internal steps, driven by kinematic heads.

Stages of one internal step (as in a physics engine's pipeline):
    1. anchor kinematics at the stage times (exact motion, or interpolated between frames);
    2. applied forces (``forces``), then constraint forces by A f_c = b (``solver``);
    3. integration (``integrators``: RK4 or symplectic Euler);
    4. stabilisation: positions and velocities put back on the joints (``stabilization``).

Time: any frame time is advanced in steps of exactly ``solver.dt`` (an accumulator), so the
result does not depend on the frame rate; the chain's time lags the requested time by less than
one step. At most ``max_steps_per_call`` steps are taken per call; the rest of the interval is
dropped (the chain skips ahead with the anchor) and reported as ``dropped_time``.

A guard checks the state after every call (finite, speeds below ``guard_max_speed``, joint gaps
below ``guard_max_gap``); a blow-up resets the chains to rest at the current head pose and is
reported, never propagated.
"""
from dataclasses import dataclass, field

import numpy as np

from .head import AnchorTrack, HeadMotion, KinematicState
from .integrators import INTEGRATOR_STEPS
from .model import Model
from .forces import applied_forces
from .rotations import (cross, quat_conjugate, quat_from_two_vectors, quat_integrate,
                        quat_multiply, quat_rotate, quat_to_matrix)
from .scene import SceneError, _check_range, _check_vector
from .solver import Dynamics
from .stabilization import project_positions, project_velocities
from .state import ChainState, half_vectors, joint_points

__all__ = ['Simulator', 'StepReport', 'TUNABLE_PARAMETERS']

_X = np.array([1.0, 0.0, 0.0])

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
    """What one ``advance`` call did."""

    steps: int = 0
    dropped_time: float = 0.0
    reset_reason: str = None
    max_gap: float = 0.0
    resets: list = field(default_factory=list)


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
        self.dynamics = Dynamics(self.model, s.linear_solver,
                                 (s.baumgarte_stiffness, s.baumgarte_damping))
        self.external = None
        self.total_resets = 0
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
            g = m.gravity
            down = g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0.0, 0.0, -1.0])
            local = ~np.isnan(m.rest_direction[:, 0])
            # Given in the anchor frame: the twist follows the anchor; along gravity: shortest arc.
            d_local = np.where(local[:, None], m.rest_direction, 1.0)
            q_chain = np.where(
                local[:, None],
                quat_multiply(q_anchor, quat_from_two_vectors(np.broadcast_to(_X, d_local.shape),
                                                              d_local)),
                quat_from_two_vectors(_X, down)[None])
            q = q_chain[m.chain_of]
            h = half_vectors(m.length, q)
            x = project_positions(m, anchor.position, h)
            head_w = head.angular_velocity[m.anchor_body][m.chain_of]
            w = head_w.copy()
            v = project_velocities(m, anchor.velocity, w, h)
            state = ChainState(x, q, v, w)
        self.state = state.copy()
        m.q_rest[m.is_first] = quat_multiply(quat_conjugate(q_anchor), self.state.q[m.is_first])
        self._last_anchor = (self.t, anchor)
        self._anchor_at = lambda t: anchor          # until a motion or frame says otherwise
        self.dynamics.last_f_c = np.zeros((m.n, 3))

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

    def set_external(self, force=None, torque=None):
        """Hold applied forces/torques ``(n, 3)`` (N, N·m) at the centres until cleared (None)."""
        n = self.model.n
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
        anchor_at = _memo_last(lambda t: self.anchors(motion.state_at(t)))
        self._anchor_at = anchor_at
        return self._advance(t_target, anchor_at, motion.state_at)

    def advance_frame(self, t_frame, head):
        """Advance to ``t_frame`` (s) given the head only at frames (``KinematicState``).

        Between the previous frame and this one the anchor follows the quintic Hermite through
        both frames' attachment-point position, velocity and acceleration (``AnchorTrack``).
        """
        _check_head(head)
        t_prev, a_prev = self._last_anchor
        a_new = self.anchors(head)
        track = AnchorTrack(t_prev, a_prev, t_frame, a_new)
        report = self._advance(t_frame, _memo_last(track.at), lambda t: head)
        self._anchor_at = track.at
        self._last_anchor = (float(t_frame), a_new)
        return report

    def _advance(self, t_target, anchor_at, head_at):
        report = StepReport()
        n_target = int(np.floor((t_target - self._t_base) / self.dt + 1e-9))
        n_steps = n_target - self._n_steps
        cap = self.scene.solver.max_steps_per_call
        if n_steps > cap:
            # Skip ahead: drop the time beyond the cap, keeping the step grid.
            report.dropped_time = (n_steps - cap) * self.dt
            self._n_steps += n_steps - cap
            n_steps = cap
        m, st = self.model, self.state
        x, q, v, w = st.x, st.q, st.v, st.w
        project = self.scene.solver.projection
        implicit_damping = m.implicit_damping and m.active_terms['damping']
        accel = self._accel_fn(anchor_at)
        try:
            for _ in range(max(n_steps, 0)):
                t = self._t_base + self._n_steps * self.dt
                x, q, v, w = self._step(accel, t, self.dt, x, q, v, w)
                self._n_steps += 1
                t1 = self._t_base + self._n_steps * self.dt
                if implicit_damping:
                    a1 = anchor_at(t1)
                    w = self.dynamics.implicit_damping(q, w, a1.angular_velocity, self.dt)
                    dv, dw = self.dynamics.velocity_correction(x, q, v, w, a1)
                    v, w = v + dv, w + dw
                if project:
                    a1 = anchor_at(t1)
                    h = half_vectors(m.length, q)
                    x = project_positions(m, a1.position, h)
                    v = project_velocities(m, a1.velocity, w, h)
            report.steps = max(n_steps, 0)
        except np.linalg.LinAlgError:
            x = np.full_like(x, np.nan)
        self.t = self._t_base + self._n_steps * self.dt
        self.state = ChainState(x, q, v, w)
        anchor = anchor_at(self.t)
        self._last_anchor = (self.t, anchor)
        report.max_gap = float(np.max(self.joint_gaps(anchor))) if self.state.is_finite() else np.inf
        reason = self._guard(report.max_gap)
        if reason is not None:
            self.total_resets += 1
            report.reset_reason = reason
            self.reset(head_at(self.t))
            report.max_gap = float(np.max(self.joint_gaps(self.anchors(head_at(self.t)))))
        return report

    def _accel_fn(self, anchor_at):
        m, dyn = self.model, self.dynamics

        def accel(t, x, q, v, w):
            anchor = anchor_at(t)
            F, T = applied_forces(m, x, q, v, w, anchor.orientation, anchor.angular_velocity,
                                  self.external)
            return dyn.accelerations(x, q, v, w, anchor, F, T)
        return accel

    def _guard(self, max_gap):
        s = self.scene.solver
        if not self.state.is_finite():
            return 'non-finite state'
        speed = float(np.max(np.linalg.norm(self.state.v, axis=1)))
        if speed > s.guard_max_speed:
            return f'speed {speed:.3g} m/s > guard_max_speed {s.guard_max_speed:g}'
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
        """Per segment: origin at the proximal joint and orientation (+X along the segment)."""
        state = self.state if t is None else self.state_at(t)
        prox, _ = joint_points(self.model, state)
        return prox, state.q.copy()

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


def _check_head(head):
    """Refuse a non-finite head state, naming the field: it must never reach the chain."""
    for name in ('position', 'orientation', 'linear_velocity', 'angular_velocity',
                 'linear_acceleration', 'angular_acceleration'):
        if not np.all(np.isfinite(getattr(head, name))):
            raise SceneError(f'head.{name}', getattr(head, name).tolist(), 'finite numbers')
