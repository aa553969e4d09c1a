"""The step report's stage timings (``StepReport.timings``, like Box2D's ``b2Profile``): the
compiled calls' time split into the chains' own steps and the contact stage by the kernel's
cycle counter."""
import numpy as np
import pytest

from ponytail_ros.core import stages
from ponytail_ros.core.head import SwayYawMotion
from ponytail_ros.core.scene import ChainSpec, ColliderSpec, Scene, SolverSpec
from ponytail_ros.core.simulator import Simulator

SOLVER = SolverSpec(integrator='rk4', dt=1 / 960)


def _reports(scene, ticks=30):
    motion = SwayYawMotion()
    sim = Simulator(scene, motion, 0.0)
    return [sim.advance_to(k / 120, motion) for k in range(1, ticks + 1)]


def test_a_free_chain_spends_its_compiled_time_integrating():
    reports = _reports(Scene(chains=[ChainSpec(n_segments=12)], solver=SOLVER))
    for r in reports:
        t = r.timings
        assert t['contacts'] == 0.0
        assert 0.0 < t['integrate'] <= t['steps']


@pytest.mark.skipif(not stages.HAS_CYCLE_COUNTER, reason='no cycle counter on this CPU')
def test_a_chain_on_a_collider_reports_its_contact_stage():
    """A chain rooted on a sphere it rests against: both stages take time, and together they
    are the compiled call's time, within the steps' own (anchor tables included)."""
    chain = ChainSpec(n_segments=12, length=0.35, attach=(-0.1034, 0.0, 0.0377),
                      stiffness=0.002)
    skull = ColliderSpec.sphere(center=(0.0, 0.0, 0.0), radius=0.09, body=0, friction=0.3)
    reports = _reports(Scene(chains=[chain], colliders=[skull], solver=SOLVER))
    integrate = np.array([r.timings['integrate'] for r in reports])
    contacts = np.array([r.timings['contacts'] for r in reports])
    steps = np.array([r.timings['steps'] for r in reports])
    assert np.all(integrate > 0.0) and np.all(contacts > 0.0)
    assert np.all(integrate + contacts <= steps)
    # The contact stage's parts: each is timed at every step of a chain that rests on the
    # sphere (rows built, a position check, velocities), and together they are within it
    # (the rest: the sphere posed, the positions kept, the call into the chain's stages);
    # the cycles are split in proportion, so exactly.
    parts = np.array([[r.timings[f'contact_{name}'] for name in stages.CONTACT_STAGES]
                      for r in reports])
    assert np.all(parts > 0.0)
    assert np.all(parts.sum(axis=1) <= contacts)


def test_the_contact_parts_are_zero_without_colliders_or_limits():
    reports = _reports(Scene(chains=[ChainSpec(n_segments=12)], solver=SOLVER))
    for r in reports:
        assert all(r.timings.get(f'contact_{name}', 0.0) == 0.0
                   for name in stages.CONTACT_STAGES)
