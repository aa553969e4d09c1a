"""Applied force terms against closed-form equilibria, scene validation, stabilisation options."""
import numpy as np
import pytest
from scipy.optimize import brentq

from ponytail_ros.core import (
    ChainSpec,
    KinematicState,
    Scene,
    SceneError,
    Simulator,
    SolverSpec,
    StillMotion,
    SwayYawMotion,
)

ANCHOR = np.array([0.0, 0.0, 1.0])
G = 9.81


def settle(chain, seconds=20.0, dt=1 / 480, **scene_kw):
    solver = SolverSpec(dt=dt, max_steps_per_call=1_000_000)
    scene = Scene(chains=(chain,), solver=solver, **scene_kw)
    sim = Simulator(scene, KinematicState.still(ANCHOR))
    sim.advance_to(seconds, StillMotion(ANCHOR))
    return sim


def test_bending_stiffness_holds_a_segment_at_its_static_angle():
    """Rest pose horizontal (+X); gravity pulls it down by θ with k θ = m g (l/2) cos θ."""
    m, l, k = 0.05, 0.3, 0.1
    sim = settle(ChainSpec(n_segments=1, length=l, mass=m, attach=(0, 0, 0),
                           rest_direction=(1, 0, 0), stiffness=k, damping=5e-3))
    prox, dist = sim.joint_positions()
    d = dist[0] - prox[0]
    theta = np.arctan2(-d[2], d[0])
    expected = brentq(lambda th: k * th - m * G * l / 2 * np.cos(th), 0.0, np.pi / 2)
    assert theta == pytest.approx(expected, abs=1e-4)


def test_atan_nonneg_is_within_two_ulps_of_atan2():
    """The stiffness's arctangent (``limit_kernels.atan_nonneg``, Cephes' ``atan``) against
    libm's ``atan2`` over the quadrant: each reduction branch, their boundaries, ratios at
    every magnitude and the edges (zero, subnormal, huge); and ``qto_rotvec`` over random
    rotations (q and -q) against the angle and axis it must give."""
    import math

    from numba import njit

    from ponytail_ros.core.vec import atan_nonneg, qto_rotvec

    @njit
    def atan_rows(s, c, out):
        for i in range(s.shape[0]):
            out[i] = atan_nonneg(s[i], c[i])

    rng = np.random.default_rng(3)
    t = np.concatenate([rng.random(200_000) ** 4, 0.66 + rng.normal(0, 1e-6, 1000),
                        2.41421356237309504880 + rng.normal(0, 1e-6, 1000),
                        10 ** rng.uniform(-150, 150, 20_000),
                        [0.0, 0.66, 1.0, 2.4142135623730951]])
    scale = 10 ** rng.uniform(-150, 150, t.size)
    s = np.concatenate([t * scale, [1.0, 5e-324, 1e300, 1.0, 0.0]])
    c = np.concatenate([scale, [0.0, 1.0, 1e-300, 5e-324, 1.0]])
    got = np.empty(s.size)
    atan_rows(s, c, got)
    want = np.array([math.atan2(a, b) for a, b in zip(s, c, strict=True)])
    ulps = np.abs(got - want) / np.spacing(np.maximum(want, 5e-324))
    assert ulps.max() <= 2.0
    assert got[-5:].tolist() == [math.pi / 2, 5e-324, math.pi / 2, math.pi / 2, 0.0]

    axes = rng.normal(size=(2000, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    theta = np.concatenate([rng.uniform(0.0, np.pi, 1990), [0.0, 1e-9, 1e-7, np.pi,
                                                             np.pi - 1e-9, 1.0, 2.0, 3.0,
                                                             0.5, 1e-3]])
    for axis, th, sign in zip(axes, theta, rng.choice([-1.0, 1.0], 2000), strict=True):
        q = sign * np.append(axis * np.sin(th / 2), np.cos(th / 2))
        assert np.allclose(qto_rotvec(tuple(q)), axis * th, rtol=0, atol=1e-14)


@pytest.mark.parametrize('c1, c2', [(0.05, 0.0), (0.0, 0.05), (0.03, 0.02)])
def test_wind_holds_a_segment_at_its_drag_angle(c1, c2):
    """Still segment in wind u along +X: drag f = (c1 + c2|u|) u per metre at the centre.

    Torque balance about the joint: tan θ = (c1 + c2 |u|) u l / (m g).
    """
    m, l, u = 0.05, 0.3, 2.0
    sim = settle(ChainSpec(n_segments=1, length=l, mass=m, attach=(0, 0, 0), damping=5e-3,
                           drag_linear=c1, drag_quadratic=c2), wind=(u, 0.0, 0.0))
    prox, dist = sim.joint_positions()
    d = dist[0] - prox[0]
    theta = np.arctan2(d[0], -d[2])
    assert theta == pytest.approx(np.arctan((c1 + c2 * u) * u * l / (m * G)), abs=1e-4)


def test_switched_off_terms_are_never_evaluated():
    """A scene without stiffness or drag never runs their code (so they cost nothing): the
    compiled step branches on the switches the model hands it, and a term is switched on by
    a live change only."""
    sim = Simulator(Scene(chains=(ChainSpec(n_segments=4, damping=1e-3),)), SwayYawMotion())
    sim.advance_to(0.1, SwayYawMotion())
    M = sim._step_model()
    assert M.gravity_on and not M.stiffness_on and not M.drag_on and not M.external_on
    assert M.explicit_damping != M.implicit_damping
    sim.set_parameters(stiffness=0.01)
    assert sim._step_model().stiffness_on and not sim._step_model().drag_on
    sim.set_parameters(stiffness=0.0, drag_linear=0.1)
    assert not sim._step_model().stiffness_on and sim._step_model().drag_on


def test_baumgarte_without_projection_bounds_the_drift():
    """Symplectic Euler with no projection drifts apart; Baumgarte terms hold the joints."""
    motion = SwayYawMotion()

    def worst_gap(**solver):
        spec = SolverSpec(integrator='symplectic_euler', dt=1 / 240, projection=False,
                          guard_max_gap=10.0, **solver)
        scene = Scene(chains=(ChainSpec(n_segments=10, damping=2e-4),), solver=spec)
        sim = Simulator(scene, motion)
        worst = 0.0
        for k in range(1, 1201):
            report = sim.advance_to(k / 120, motion)
            assert report.reset_reason is None
            worst = max(worst, report.max_gap)
        return worst
    free = worst_gap()
    stabilised = worst_gap(baumgarte_stiffness=1e4, baumgarte_damping=200.0)
    assert free > 0.1                     # drift is real without stabilisation
    assert stabilised < free / 30


@pytest.mark.parametrize('field, value, fragment', [
    ('n_segments', 0, '[1, 4096]'),
    ('n_segments', 2.5, 'integer'),
    ('length', -1.0, '[0.0001, 1000.0]'),
    ('mass', float('nan'), 'mass = nan'),
    ('radius', 0.0, 'radius'),
    ('damping', -0.1, '[0.0, 1000.0]'),
    ('attach', (1, 2), '3 finite numbers'),
    ('rest_direction', (0, 0, 0), 'non-zero'),
    ('segment_lengths', (0.1, -0.1), 'positive'),
    ('anchor_body', 3, '[0, 0]'),
])
def test_chain_fields_are_validated_with_name_value_and_range(field, value, fragment):
    with pytest.raises(SceneError) as err:
        Scene(chains=(ChainSpec(**{'n_segments': 2, field: value}),))
    assert err.value.field == f'chains[0].{field}'
    assert fragment in str(err.value)


@pytest.mark.parametrize('field, value, fragment', [
    ('integrator', 'euler', "one of ('rk4', 'symplectic_euler', 'rattle')"),
    ('dt', 0.5, '[1e-06, 0.1]'),
    ('max_steps_per_call', 0, '[1, 1000000]'),
    ('linear_solver', 'banded', 'was removed'),
])
def test_solver_fields_are_validated(field, value, fragment):
    with pytest.raises(SceneError) as err:
        Scene(solver=SolverSpec(**{field: value}))
    assert err.value.field == f'solver.{field}' and fragment in str(err.value)


def test_a_removed_parameter_is_refused_by_name_in_a_params_file(tmp_path):
    """A params file that still sets ``solver.linear_solver`` gets an error naming it and
    saying it was removed; a node warns that it ignores it; an older recording that holds it
    replays (the compiled step it ran with 'banded' is what runs)."""
    from ponytail_ros.app.param_values import (
        complete_values,
        metadata_from_values,
        unknown_parameter_warning,
        values_from_metadata,
        values_from_params_file,
    )
    from ponytail_ros.app.parameters import ParameterError
    path = tmp_path / 'params.yaml'
    path.write_text('/**:\n  ros__parameters:\n    solver:\n      linear_solver: dense\n')
    with pytest.raises(ParameterError) as err:
        complete_values(values_from_params_file(path))
    assert err.value.names == ('solver.linear_solver',)
    assert 'solver.linear_solver' in str(err.value) and 'was removed' in str(err.value)
    assert 'was removed' in unknown_parameter_warning('solver.linear_solver', {})
    recorded = metadata_from_values(complete_values({}))
    recorded['solver.linear_solver'] = '"banded"'
    assert complete_values(values_from_metadata(recorded)) == complete_values({})


def test_scene_fields_are_validated():
    with pytest.raises(SceneError, match='gravity'):
        Scene(gravity=(0, 0, float('inf')))
    with pytest.raises(SceneError, match='chains'):
        Scene(chains=())


@pytest.mark.parametrize('field', ['position', 'orientation', 'linear_acceleration',
                                   'angular_velocity'])
def test_non_finite_head_frame_is_refused_and_the_chain_untouched(field):
    sim = Simulator(Scene(chains=(ChainSpec(n_segments=5),)), KinematicState.still(ANCHOR))
    sim.advance_frame(0.05, KinematicState.still(ANCHOR))
    before = sim.state.copy()
    bad = KinematicState.still(ANCHOR)
    getattr(bad, field)[0, 0] = np.nan
    with pytest.raises(SceneError, match=f'head.{field}'):
        sim.advance_frame(0.1, bad)
    assert np.array_equal(sim.state.x, before.x) and sim.t == pytest.approx(0.05, abs=1 / 240)
    sim.advance_frame(0.2, KinematicState.still(ANCHOR))
    assert sim.state.is_finite() and sim.joint_gaps().max() < 1e-12


def test_a_colliding_chain_is_refused_past_the_segments_its_contacts_can_be_solved_for():
    """``MAX_COLLIDING_SEGMENTS``: a chain that collides is refused beyond it (the error names
    the field and both ranges); the same chain with ``collide: false``, or with no collider
    in the scene, takes the full range and simply runs."""
    from ponytail_ros.core.scene import MAX_COLLIDING_SEGMENTS, MAX_SEGMENTS, ColliderSpec
    skull = ColliderSpec.sphere(center=(0.0, 0.0, 0.0), radius=0.09)
    with pytest.raises(SceneError) as err:
        Scene(chains=[ChainSpec(n_segments=MAX_COLLIDING_SEGMENTS + 1)], colliders=[skull])
    assert err.value.field == 'chains[0].n_segments'
    assert f'[1, {MAX_COLLIDING_SEGMENTS}]' in str(err.value)
    assert f'up to {MAX_SEGMENTS} with collide: false' in str(err.value)
    Scene(chains=[ChainSpec(n_segments=MAX_COLLIDING_SEGMENTS)], colliders=[skull])
    Scene(chains=[ChainSpec(n_segments=MAX_SEGMENTS, collide=False)], colliders=[skull])
    free = Simulator(Scene(chains=[ChainSpec(n_segments=MAX_SEGMENTS, length=0.35)],
                           solver=SolverSpec(dt=1 / 960)), KinematicState.still())
    report = free.advance_frame(1 / 120, KinematicState.still())
    assert report.reset_reason is None and report.steps == 8
    assert report.max_gap < 1e-9
