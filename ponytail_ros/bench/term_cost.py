"""What each term of a scene costs: CPU time per simulated second, term by term.

A 20-segment ponytail on the reference moving head (``SwayYawMotion``: ±5 cm at 1.5 Hz, ±0.6 rad
of yaw at 0.8 Hz), default solver (RK4, dt = 1/240 s), stepped through ``seconds`` of
simulated time; each configuration adds one thing to the previous one:

    nothing            no gravity, no force term (damping 0), no collider, no limit
    gravity            + gravity
    + damping          + joint damping 2e-4 N·m·s/rad (implicit at this step: stiff axially)
    + stiffness        + bending stiffness 2e-3 N·m/rad
    + drag             + linear and quadratic air drag 0.05
    + far floor        + a floor plane 10 m down, never reached: the detection alone
    + 1 sphere         + the head as a sphere collider (r = 0.1 m, on the head) instead; the
                       ponytail rests on it and its root is on it: in contact all the time
    + 1 capsule        + a shoulder capsule (world) instead of the sphere, touched at times
    + 3 colliders      + the head sphere, the shoulder capsule and a floor plane (world)
    + swing limit      + a swing (cone, 0.6 rad) limit at every joint, no colliders
    + limits           + swing (0.6 rad) and twist (0.3 rad) limits at every joint, and the
                       three colliders

and then the same scene with features present but switched off, which must cost what the
scene without them costs:

    gravity, zero terms      gravity, with stiffness = drag = 0 and no limits given explicitly
    gravity, colliders off   gravity, three colliders in the scene but ``collide=False``

Then the ready-made scenes (``config/*.yaml``, as the node builds them) on the scripted head
of ``ponytail_head_demo``, each with what it enables.

Run: ``ponytail_bench terms`` (tables in ``docs/bench/terms.*``), or
``python -m ponytail_ros.bench.term_cost [--segments N] [--seconds S] [--repeats R]``.
"""
import argparse
import time
from dataclasses import replace

from ponytail_ros.core.head import SwayYawMotion
from ponytail_ros.core.scene import ChainSpec, ColliderSpec, Scene, SolverSpec
from ponytail_ros.core.simulator import Simulator

__all__ = ['bench_terms', 'term_scenes', 'main']

HEAD = ColliderSpec.sphere(center=(0.0, 0.0, 0.0), radius=0.1, body=0)
SHOULDER = ColliderSpec.capsule(center=(-0.05, 0.0, 1.32), axis=(0.0, 1.0, 0.0), half_length=0.2,
                                radius=0.06, body=None)
FLOOR = ColliderSpec.plane(point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0), body=None)
FAR_FLOOR = ColliderSpec.plane(point=(0.0, 0.0, -10.0), normal=(0.0, 0.0, 1.0), body=None)


def term_scenes(n_segments=20):
    """``[(label, Scene)]`` in the order of the module docstring."""
    solver = SolverSpec(max_steps_per_call=10 ** 6)
    base = dict(name='ponytail', n_segments=n_segments, length=0.4, mass=0.1, radius=0.01,
                attach=(-0.10, 0.0, 0.05), damping=0.0)
    steps = [
        ('nothing', dict(), (), (0.0, 0.0, 0.0)),
        ('gravity', dict(), (), None),
        ('+ damping', dict(damping=2e-4), (), None),
        ('+ stiffness', dict(damping=2e-4, stiffness=2e-3), (), None),
        ('+ drag', dict(damping=2e-4, stiffness=2e-3, drag_linear=0.05, drag_quadratic=0.05),
         (), None),
        ('+ far floor', dict(damping=2e-4, stiffness=2e-3, drag_linear=0.05, drag_quadratic=0.05),
         (FAR_FLOOR,), None),
        ('+ 1 sphere', dict(damping=2e-4, stiffness=2e-3, drag_linear=0.05, drag_quadratic=0.05),
         (HEAD,), None),
        ('+ 1 capsule', dict(damping=2e-4, stiffness=2e-3, drag_linear=0.05, drag_quadratic=0.05),
         (SHOULDER,), None),
        ('+ 3 colliders', dict(damping=2e-4, stiffness=2e-3, drag_linear=0.05,
                               drag_quadratic=0.05), (HEAD, SHOULDER, FLOOR), None),
        ('+ swing limit', dict(damping=2e-4, stiffness=2e-3, drag_linear=0.05,
                               drag_quadratic=0.05, swing_limit=0.6), (), None),
        ('+ limits', dict(damping=2e-4, stiffness=2e-3, drag_linear=0.05, drag_quadratic=0.05,
                          swing_limit=0.6, twist_limit=0.3), (HEAD, SHOULDER, FLOOR), None),
        ('gravity, zero terms', dict(stiffness=0.0, drag_linear=0.0, drag_quadratic=0.0,
                                     swing_limit=None, twist_limit=None), (), None),
        ('gravity, colliders off', dict(collide=False), (HEAD, SHOULDER, FLOOR), None),
    ]
    out = []
    for label, chain, colliders, gravity in steps:
        kw = {} if gravity is None else dict(gravity=gravity)
        out.append((label, Scene(chains=(ChainSpec(**{**base, **chain}),), colliders=colliders,
                                 solver=solver, **kw)))
    return out


def _run(scene, motion, seconds):
    """CPU time (s) of ``seconds`` simulated seconds, frame by frame at the internal step, and
    the mean number of contact and limit rows per step."""
    sim = Simulator(scene, motion)
    steps = int(round(seconds / sim.dt))
    rows = 0
    t0 = time.process_time()
    for k in range(1, steps + 1):
        sim.advance_to(k * sim.dt, motion)
        if sim.unilateral is not None:
            rows += sim.unilateral.last['contacts'] + sim.unilateral.last['limits']
    cpu = time.process_time() - t0
    if sim.total_resets or not sim.state.is_finite():
        raise RuntimeError(f'the scene blew up: {sim.total_resets} resets')
    return cpu, rows / steps


def bench_terms(n_segments=20, seconds=3.0, repeats=3, out=print):
    """Measure every configuration of ``term_scenes``; print and return a table.

    The configurations are run in turn ``repeats`` times (interleaved, so that a change of
    machine load hits all alike) and each keeps its least CPU time.
    Returns ``[(label, cpu_s_per_simulated_s, relative_to_gravity, rows_per_step)]``.
    """
    motion = SwayYawMotion()
    scenes = term_scenes(n_segments)
    best = {label: float('inf') for label, _ in scenes}
    rows = {}
    for _ in range(repeats):
        for label, scene in scenes:
            cpu, rows[label] = _run(scene, motion, seconds)
            best[label] = min(best[label], cpu)
    gravity = best['gravity']
    table = [(label, best[label] / seconds, best[label] / gravity, rows[label])
             for label, _ in scenes]
    if out is not None:
        out(f'{n_segments}-segment ponytail, reference moving head, RK4 dt = 1/240 s, '
            f'{seconds:g} s simulated, least of {repeats} interleaved runs')
        out(f'{"configuration":<24} {"CPU ms / sim s":>15} {"vs gravity":>11} {"rows/step":>10}')
        for label, per_s, rel, r in table:
            out(f'{label:<24} {1e3 * per_s:>15.1f} {rel:>10.2f}x {r:>10.2f}')
    return table


READY_MADE = ('ponytail.yaml', 'pigtails.yaml', 'rope.yaml', 'sword.yaml', 'tail.yaml')


def ready_made_scenes(names=READY_MADE):
    """``[(name, Scene, what it enables)]`` of the ready-made params files, as the node builds
    them (a world-anchored chain gets the static world body)."""
    from ponytail_ros.app.param_values import (
        complete_values,
        scene_and_settings,
        values_from_params_file,
    )
    from ponytail_ros.resources import config_path
    out = []
    for name in names:
        _, scene, _ = scene_and_settings(complete_values(values_from_params_file(
            config_path(name))))
        scene = scene.replace(solver=replace(scene.solver, max_steps_per_call=10 ** 6))
        out.append((name, scene, describe(scene)))
    return out


def describe(scene):
    """What a scene enables, e.g. ``'12 seg; damping, stiffness, drag; 1 sphere'``."""
    seg = '+'.join(str(c.n_segments) for c in scene.chains) + ' seg'
    terms = [t for t in ('damping', 'stiffness', 'drag') if any(
        (getattr(c, t) if t != 'drag' else c.drag_linear + c.drag_quadratic) > 0
        for c in scene.chains)]
    lim = [t for t in ('swing', 'twist') if any(getattr(c, t + '_limit') for c in scene.chains)]
    kinds = [k.kind for k in scene.colliders]
    cols = ', '.join(f'{kinds.count(k)} {k}' for k in dict.fromkeys(kinds))
    parts = [seg, ', '.join(terms) or 'gravity only']
    if lim:
        parts.append(' and '.join(lim) + ' limit')
    if cols:
        parts.append(cols)
    return '; '.join(parts)


def bench_ready_made(seconds=3.0, repeats=3, out=print):
    """CPU cost of each ready-made scene on the demo's scripted head (``HeadScript``).

    Returns ``[(name, what, segments, cpu_s_per_simulated_s, rows_per_step)]``.
    """
    from ponytail_ros.app.head_script import HeadScript
    from ponytail_ros.core.head import WithStaticBodies
    scenes = ready_made_scenes()
    best, rows = {}, {}
    for _ in range(repeats):
        for name, scene, _ in scenes:
            motion = WithStaticBodies(HeadScript(origin=(0.0, 0.0, 1.0)),
                                      scene.n_kinematic_bodies - 1)
            cpu, rows[name] = _run(scene, motion, seconds)
            best[name] = min(best.get(name, float('inf')), cpu)
    table = [(name, what, scene.n_segments, best[name] / seconds, rows[name])
             for name, scene, what in scenes]
    if out is not None:
        out(f'Ready-made scenes on the scripted head, as configured (RK4 dt = 1/240 s), '
            f'{seconds:g} s simulated, least of {repeats}')
        out(f'{"scene":<16} {"CPU ms / sim s":>15} {"rows/step":>10}  what it models')
        for name, what, _, per_s, r in table:
            out(f'{name:<16} {1e3 * per_s:>15.1f} {r:>10.2f}  {what}')
    return table


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--segments', type=int, default=20)
    parser.add_argument('--seconds', type=float, default=3.0)
    parser.add_argument('--repeats', type=int, default=3)
    args = parser.parse_args(argv)
    bench_terms(args.segments, args.seconds, args.repeats)
    bench_ready_made(args.seconds, args.repeats)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
