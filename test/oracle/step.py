"""The NumPy reference step, run as ``Simulator`` runs the compiled one.

One internal step: the integrator (``integrators``) with the applied forces (``forces``) and
the joint solve (``solver.Dynamics``) at its stage times, then the implicit joint damping (when
the model integrates it implicitly), then the joints closed (``stabilization``: positions,
and for RK4 the velocities rebuilt from ω; symplectic Euler's and RATTLE's steps end with
their own mass-weighted projection, which a rebuild would undo).
"""
import numpy as np

from ponytail_ros.core.state import ChainState, half_vectors

from .forces import applied_forces
from .integrators import INTEGRATOR_STEPS
from .solver import Dynamics
from .stabilization import project_positions, project_velocities

__all__ = ['ReferenceStep']


class _System:
    """The chains' dynamics for the integrators (``integrators`` module docstring): applied
    forces and the joint solve at any time of the step, with the anchors of ``anchor_at``."""

    def __init__(self, model, dynamics, anchor_at, external, projection):
        self.model, self.dynamics, self.anchor = model, dynamics, anchor_at
        self.external, self.projection = external, projection

    def applied(self, t, x, q, v, w):
        """Applied forces and torques ``(n, 3)`` each (N, N·m, world) at time ``t``."""
        anchor = self.anchor(t)
        return applied_forces(self.model, x, q, v, w, anchor.orientation,
                              anchor.angular_velocity, self.external)

    def accel(self, t, x, q, v, w):
        """Accelerations ``(a, α)`` ``(n, 3)`` each (m/s², rad/s², world), joints enforced."""
        F, T = self.applied(t, x, q, v, w)
        return self.dynamics.accelerations(x, q, v, w, self.anchor(t), F, T)


class ReferenceStep:
    """The NumPy reference of the free step of ``sim``'s scene (a ``Simulator``: its model,
    solver settings and held external forces, read at every ``advance``).

    ``linear_solver``: ``'banded'`` (LAPACK's banded Cholesky) or ``'dense'``.
    """

    def __init__(self, sim, linear_solver='banded'):
        s = sim.scene.solver
        self.sim, self.model = sim, sim.model
        self.dynamics = Dynamics(sim.model, linear_solver,
                                 (s.baumgarte_stiffness, s.baumgarte_damping))
        self.step = INTEGRATOR_STEPS[s.integrator]
        self.rebuild_velocities = s.integrator == 'rk4'
        self.projection = s.projection

    def advance(self, state, t_base, k0, n_steps, h, anchor_at):
        """``state`` (a ``ChainState``) after the steps ``k0 ... k0 + n_steps - 1`` of ``h`` s
        on the grid ``t_base + k h`` (s; the simulator's stage times), the anchors
        ``anchor_at(t)`` (``AnchorKinematics``); ``dynamics.last_f_c`` is the last step's
        f_c (N)."""
        m, dyn = self.model, self.dynamics
        system = _System(m, dyn, anchor_at, self.sim.external, self.projection)
        x, q, v, w = (np.array(a, dtype=float) for a in (state.x, state.q, state.v, state.w))
        implicit_damping = m.implicit_damping and m.active_terms['damping']
        for k in range(n_steps):
            t, t1 = t_base + (k0 + k) * h, t_base + (k0 + k + 1) * h
            x, q, v, w = self.step(system, t, h, x, q, v, w)
            if implicit_damping:
                v, w = dyn.implicit_damping(x, q, v, w, anchor_at(t1), h)
            if self.projection:
                anchor = anchor_at(t1)
                hv = half_vectors(m.length, q)
                x = project_positions(m, anchor.position, hv)
                if self.rebuild_velocities:
                    v = project_velocities(m, anchor.velocity, w, hv)
        return ChainState(x, q, v, w)
