"""What the compiled step is handed: the model of a call (``StepModel``, constant during it, like
MuJoCo's ``const mjModel*``), the anchors at its stage times (``AnchorTable``), the integrators'
records and the status codes a step returns.

Frames and units: world frame (REP 103), SI.
"""
from collections import namedtuple

__all__ = ['StepModel', 'AnchorTable', 'Integrator', 'INTEGRATORS', 'RK4', 'SYMPLECTIC_EULER',
           'RATTLE', 'OK', 'JOINT_SOLVE_FAILED', 'DAMPING_SOLVE_FAILED', 'SUBSTEPS']

RK4, SYMPLECTIC_EULER, RATTLE = 0, 1, 2
OK, JOINT_SOLVE_FAILED, DAMPING_SOLVE_FAILED, SUBSTEPS = 0, 1, 2, 3

Integrator = namedtuple('Integrator', ['name', 'id', 'order', 'solves_per_step',
                                       'rebuilds_velocities', 'explicit_gyroscopic',
                                       'damping_limit'])
Integrator.__doc__ = """What the simulator needs to know of an integrator, in one record.

``id``: the compiled step's switch; ``order``: of accuracy; ``solves_per_step``: joint solves
with A (RK4: one factorisation and solve per stage; the constrained steps: one factorisation,
reused by the next step, and two solves); ``rebuilds_velocities``: the stabilisation rebuilds
v from ω after the step (RK4; the constrained steps end with their own mass-weighted
projection, which a rebuild would undo); ``explicit_gyroscopic``: ω × Iω is integrated
explicitly, so the guard must watch the precession it can follow (RK4); ``damping_limit``: where
the step's stability region ends on the negative real axis (dt·λ for a decay rate λ): explicit
joint damping is stable while dt·λ_max stays below it (RK4: 2.785, taken as 2.78; the Euler
kicks of the constrained steps: 2)."""

INTEGRATORS = {
    'rk4': Integrator('rk4', RK4, 4, 4, True, True, 2.78),
    'symplectic_euler': Integrator('symplectic_euler', SYMPLECTIC_EULER, 1, 2, False, False,
                                   2.0),
    'rattle': Integrator('rattle', RATTLE, 2, 2, False, False, 2.0),
}

# The model's arrays and switches for one call (n segments, C chains; SI units).
StepModel = namedtuple('StepModel', [
    'length', 'half', 'mass', 'inv_mass', 'inertia', 'inv_inertia',   # (n,) ×4, (n, 3) ×2
    'chain_of', 'is_first', 'has_child',                    # (n,) int64, bool, bool
    'damping', 'stiffness', 'drag_linear', 'drag_quadratic', 'q_rest',   # (n,) ..., (n, 4)
    'gravity', 'wind',                                      # (3,)
    'axisymmetric', 'integrator', 'projection',             # bool, int, bool
    'gravity_on', 'explicit_damping', 'implicit_damping', 'stiffness_on', 'drag_on',
    'external_on', 'baumgarte_stiffness', 'baumgarte_damping',
])
# The anchors (attachment points and anchor bodies) at the stage times, (S, C, 3|4) each.
AnchorTable = namedtuple('AnchorTable', ['position', 'velocity', 'acceleration',
                                         'orientation', 'angular_velocity'])
