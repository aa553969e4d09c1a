"""Helpers shared by the test modules (ROS-free; the ROS ones are in ``ros_helpers.py``).

Test modules import these instead of importing each other: a test module is collected once per
run and its fixtures and module-level state belong to it. Fixtures shared by several modules
are in ``conftest.py``.
"""
__all__ = ['total_energy', 'PENETRATION_TOLERANCE', 'ANGLE_TOLERANCE']

#: m: the stated bound on how deep a segment's capsule may sink into a collider (the contact
#: solver stops at 1e-5 m).
PENETRATION_TOLERANCE = 2e-5
#: rad: the stated bound on a swing or twist beyond its limit.
ANGLE_TOLERANCE = 2e-5


def total_energy(sim) -> float:
    """Kinetic plus potential energy of every segment of ``sim`` (J)."""
    ke, pe = sim.energy()
    return float(ke.sum() + pe.sum())
