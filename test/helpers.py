"""Helpers shared by the test modules (ROS-free; the ROS ones are in ``ros_helpers.py``).

Test modules import these instead of importing each other: a test module is collected once per
run and its fixtures and module-level state belong to it. Fixtures shared by several modules
are in ``conftest.py``.
"""
from ponytail_ros.core import ChainSpec, Scene, Simulator, SolverSpec

__all__ = ['total_energy', 'reference_ponytail', 'chain_sim', 'PENETRATION_TOLERANCE',
           'ANGLE_TOLERANCE']

#: m: the stated bound on how deep a segment's capsule may sink into a collider (the contact
#: solver stops at 1e-5 m).
PENETRATION_TOLERANCE = 2e-5
#: rad: the stated bound on a swing or twist beyond its limit.
ANGLE_TOLERANCE = 2e-5


def reference_ponytail(n=10, length=0.4, mass=0.1, radius=0.01, **kw) -> ChainSpec:
    """The reference ponytail's geometry (``../shared/reference/``), undamped unless
    ``damping`` is given."""
    kw.setdefault('damping', 0.0)
    return ChainSpec(n_segments=n, length=length, mass=mass, radius=radius,
                     attach=(-0.10, 0.0, 0.05), **kw)


def chain_sim(chain, motion, integrator, dt, gravity=(0.0, 0.0, -9.81), **solver) -> Simulator:
    """A simulator of the one chain ``chain`` driven by ``motion`` from t = 0; no step budget
    (``max_steps_per_call`` 10⁶ unless given), so that long advances are never cut short."""
    solver.setdefault('max_steps_per_call', 1_000_000)
    scene = Scene(chains=(chain,), gravity=gravity,
                  solver=SolverSpec(integrator=integrator, dt=dt, **solver))
    return Simulator(scene, motion, 0.0)


def total_energy(sim) -> float:
    """Kinetic plus potential energy of every segment of ``sim`` (J)."""
    ke, pe = sim.energy()
    return float(ke.sum() + pe.sum())
