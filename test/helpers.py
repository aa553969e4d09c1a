"""Helpers shared by the test modules (ROS-free; the ROS ones are in ``ros_helpers.py``).

Test modules import these instead of importing each other: a test module is collected once per
run and its fixtures and module-level state belong to it. Fixtures shared by several modules
are in ``conftest.py``.
"""
import numpy as np

from ponytail_ros.core import ChainSpec, KinematicState, Scene, Simulator, SolverSpec
from ponytail_ros.core.head import HeadMotion

__all__ = ['total_energy', 'reference_ponytail', 'chain_sim', 'PENETRATION_TOLERANCE',
           'ANGLE_TOLERANCE', 'TwoBodies']

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


class TwoBodies(HeadMotion):
    """Body 0: a still ceiling anchor; body 1: a 'shoulder' sliding back and forth under it."""

    def state_at(self, t):
        w = 2 * np.pi * 1.2
        p = np.array([[0.0, 0.0, 1.0], [0.15 * np.sin(w * t), 0.0, 0.7]])
        v = np.array([[0.0, 0.0, 0.0], [0.15 * w * np.cos(w * t), 0.0, 0.0]])
        a = np.array([[0.0, 0.0, 0.0], [-0.15 * w * w * np.sin(w * t), 0.0, 0.0]])
        yaw = 0.4 * np.sin(w * t)
        q = np.array([[0, 0, 0, 1.0], [0, 0, np.sin(yaw / 2), np.cos(yaw / 2)]])
        om = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.4 * w * np.cos(w * t)]])
        al = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -0.4 * w * w * np.sin(w * t)]])
        return KinematicState(p, q, v, om, a, al)
