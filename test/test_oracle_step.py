"""The compiled step against its NumPy reference (``oracle``): every integrator, every force term.

``Simulator.advance_to`` (the compiled step, ``step``) and ``oracle.step.ReferenceStep`` (the
NumPy reference: ``oracle.integrators``, ``oracle.forces``, ``oracle.solver``,
``oracle.stabilization``) advance the same chain from the same state on the same moving head,
exact at every stage time, for one second of simulated time; they must agree to ~1e-10
(m, unit quaternion, m/s, rad/s) at every tick. The two are independent implementations of the
same equations (different operation order, LAPACK's banded Cholesky against the block
factorisation of ``chain_solve``), so only rounding separates them: a chain that is not
chaotic over the second keeps that difference near 1e-12.
"""
import numpy as np
import pytest

from ponytail_ros.core import ChainSpec, Scene, Simulator, SolverSpec, SwayYawMotion

from oracle.step import ReferenceStep

SECONDS = 1.0
TICK = 1.0 / 60.0
DT = 1.0 / 480.0
TOL = 1e-10

#: term -> (ChainSpec fields, Scene fields, SolverSpec fields, external force and torque or None)
TERMS = {
    'gravity': (dict(damping=0.0), {}, {}, None),
    'joint damping, explicit': (dict(damping=2e-5, radius=0.03), {},
                                dict(damping_method='explicit'), None),
    'joint damping, implicit': (dict(damping=2e-3), {}, dict(damping_method='implicit'), None),
    'bending stiffness': (dict(damping=0.0, stiffness=0.05), {}, {}, None),
    'drag and wind': (dict(damping=0.0, drag_linear=0.05, drag_quadratic=0.2),
                      dict(wind=(1.5, -0.5, 0.2)), {}, None),
    'external force and torque': (dict(damping=0.0), {}, {},
                                  ((0.02, 0.01, -0.03), (0.0, 1e-4, 2e-4))),
}
INTEGRATORS = ('rk4', 'symplectic_euler', 'rattle')


def _scene(term, integrator):
    chain, scene, solver, _ = TERMS[term]
    return Scene(chains=(ChainSpec(n_segments=5, **chain),),
                 solver=SolverSpec(integrator=integrator, dt=DT, **solver), **scene)


def _runs(term, integrator):
    """``(compiled, reference)`` states after every tick of ``SECONDS``: lists of ``(x, q, v,
    w)``."""
    motion = SwayYawMotion()
    sim = Simulator(_scene(term, integrator), motion)
    external = TERMS[term][3]
    if external is not None:
        n = sim.model.n
        sim.set_external(np.tile(external[0], (n, 1)), np.tile(external[1], (n, 1)))
    oracle = ReferenceStep(sim)
    state, t_base, k = sim.state.copy(), sim._t_base, sim._n_steps

    def anchor_at(t):
        return sim.anchors(motion.state_at(t))
    compiled, reference = [], []
    for tick in range(1, int(round(SECONDS / TICK)) + 1):
        report = sim.advance_to(tick * TICK, motion)
        assert report.reset_reason is None
        state = oracle.advance(state, t_base, k, report.steps, DT, anchor_at)
        k += report.steps
        compiled.append(tuple(a.copy() for a in (sim.state.x, sim.state.q, sim.state.v,
                                                 sim.state.w)))
        reference.append((state.x, state.q, state.v, state.w))
    return sim, oracle, compiled, reference


@pytest.mark.parametrize('integrator', INTEGRATORS)
@pytest.mark.parametrize('term', list(TERMS))
def test_compiled_step_matches_the_numpy_reference_over_one_second(term, integrator):
    sim, oracle, compiled, reference = _runs(term, integrator)
    worst = max(float(np.max(np.abs(a - b))) for c, r in zip(compiled, reference, strict=True)
                for a, b in zip(c, r, strict=True))
    assert worst < TOL, f'{term}, {integrator}: largest difference {worst:.3g}'
    # The chain really moved, and the term really acted (its coefficients are on).
    x0 = compiled[0][0]
    assert np.max(np.abs(compiled[-1][0] - x0)) > 1e-3
    # The joint forces the simulator keeps are the last step's, as the reference's.
    f_ref = oracle.dynamics.last_f_c
    assert np.max(np.abs(sim.constraint_forces - f_ref)) < 1e-8 * np.max(np.abs(f_ref))
