"""Many characters in one node: the crowd's params (``app/crowd.py``), every frame's pose in one
``PoseArray`` (``frames_topic``: its CDR read with ``struct``, checked, pushed, recorded and
replayed), and the head demo's crowd output."""
import dataclasses
import math
from collections import Counter
from itertools import pairwise

import numpy as np
import pytest

from ponytail_ros.app.crowd import (
    CHARACTER_PHASE,
    CHARACTER_SPACING,
    crowd_offsets,
    crowd_values,
    main as crowd_main,
)
from ponytail_ros.app.param_values import (
    complete_values,
    scene_and_settings,
    values_from_params_file,
)
from ponytail_ros.app.parameters import ParameterError
from ponytail_ros.app.wire import pose_array_fields, pose_array_layout
from ponytail_ros.resources import config_path
from ponytail_ros.testing.config import load_config

Q_ID = (0.0, 0.0, 0.0, 1.0)


# -- the crowd's parameters (ROS-free) ------------------------------------------------------------

def test_a_crowd_copies_the_character_onto_its_own_frames_and_shares_world_colliders():
    base = values_from_params_file(config_path('ponytail.yaml'))
    base.update({'colliders': ['skull', 'floor'], 'floor.kind': 'plane', 'floor.frame': 'world',
                 'floor.center': [0.0, 0.0, -2.0]})
    values = complete_values(crowd_values(base, 3))
    _, scene, _ = scene_and_settings(values)
    assert values['frames'] == ['character_1', 'character_2']
    assert values['frames_topic'] == 'frame_poses'
    assert values['chains'] == ['ponytail', 'ponytail_1', 'ponytail_2']
    assert values['colliders'] == ['skull', 'floor', 'skull_1', 'skull_2']   # one floor
    # character k's chain hangs from body k (the head is 0), its skull is fixed in body k
    assert [c.anchor_body for c in scene.chains] == [0, 1, 2]
    bodies = {name: c.body for name, c in zip(values['colliders'], scene.colliders, strict=True)}
    assert bodies == {'skull': 0, 'floor': None, 'skull_1': 1, 'skull_2': 2}   # None: static
    # every copy is the character's chain, field for field but its anchor
    first = scene.chains[0]
    for c in scene.chains[1:]:
        assert (c.n_segments, c.length, c.mass, c.radius, tuple(c.attach), c.damping,
                c.stiffness, c.drag_linear, c.drag_quadratic) == \
            (first.n_segments, first.length, first.mass, first.radius, tuple(first.attach),
             first.damping, first.stiffness, first.drag_linear, first.drag_quadratic)
    assert crowd_values(base, 1) == base


def test_a_crowd_of_a_scene_with_frames_or_of_no_character_is_refused():
    arm = values_from_params_file(config_path('ponytail_arm.yaml'))
    with pytest.raises(ValueError, match=r"extra frames \(\['left_forearm'\]\)"):
        crowd_values(arm, 4)
    with pytest.raises(ValueError, match='characters = 0'):
        crowd_values({}, 0)


def test_the_crowd_command_writes_a_params_file_the_node_reads(tmp_path, capsys):
    out = tmp_path / 'crowd.yaml'
    assert crowd_main([str(config_path('ponytail.yaml')), '100', '-o', str(out)]) == 0
    cfg = load_config(out)
    assert len(cfg.chains) == 100 and len(cfg.frames) == 99 and len(cfg.colliders) == 100
    assert set(cfg.frame_topics) == {'frame_poses'}
    assert '&' not in out.read_text() and '*id' not in out.read_text()   # no YAML aliases
    assert crowd_main([str(config_path('ponytail_arm.yaml')), '2']) == 2
    assert 'extra frames' in capsys.readouterr().err
    with pytest.raises(SystemExit):
        crowd_main([str(config_path('ponytail.yaml')), '1000'])


def test_crowd_offsets_space_the_heads_along_x_and_delay_their_motion():
    offsets = crowd_offsets(4)
    assert [tuple(s) for s, _ in offsets] == [(k * CHARACTER_SPACING, 0.0, 0.0)
                                              for k in range(4)]
    assert [d for _, d in offsets] == [k * CHARACTER_PHASE for k in range(4)]


def _crowd_poses(tick, offsets, nan, wide):
    """The head's and the 3 frames' poses at tick ``tick`` (120 Hz); one frame's position NaN
    (``nan``), another's quaternion 1.1 long (``wide``)."""
    t = tick / 120.0
    rows = []
    for k in range(4):
        x, y = offsets[k][0][0] + 0.05 * math.sin(3.0 * t + k), 0.02 * math.cos(5.0 * t)
        a = 0.3 * math.sin(2.0 * t + k)
        rows.append((x, y, 1.6, 0.0, 0.0, math.sin(a / 2), math.cos(a / 2)))
    rows = np.array(rows)
    if nan:
        rows[1 + tick % 3, 1] = np.nan
    if wide:
        rows[1 + (tick + 1) % 3, 3:] *= 1.1
    return rows[0], rows[1:]


def _push_both(batched, single, stamp, head, poses):
    """The same head pose to both runners, the frames' in one batch to one, one by one to the
    other."""
    for r in (batched, single):
        r.push(stamp, head[:3], head[3:], 'world')
    batched.push_frames(stamp, poses, 'world')
    for i, row in enumerate(poses):
        single.push_frame(i, stamp, row[:3], row[3:], 'world')


def test_one_pose_array_of_every_frame_is_taken_as_each_frames_own_pose():
    """``ChainRunner.push_frames`` (every frame's pose at one stamp, added in one compiled call)
    and ``push_frame`` per frame leave the same runner: the same chain state bit for bit, the
    same histories, drops per reason and accept counts, through NaN and non-unit poses, a
    repeated stamp, a stream restart after a pause and a batch of the wrong count."""
    from ponytail_ros.app.runner import ChainRunner
    values = complete_values(crowd_values(values_from_params_file(config_path('ponytail.yaml')),
                                          4))
    _, scene, settings = scene_and_settings(values)
    frames = values['frames']
    batched, single = (ChainRunner(scene, settings, frames=frames) for _ in range(2))
    offsets = crowd_offsets(4)

    def paused(tick):                  # no input at all for 50 ticks (0.42 s: every input stale)
        return 150 <= tick < 200

    nan_ticks = [k for k in range(300) if k % 37 == 5 and not paused(k)]
    wide_ticks = [k for k in range(300) if k % 41 == 7 and not paused(k)]

    outs = []
    for tick in range(300):
        t = tick / 120.0
        if not paused(tick):
            stamp = t - (0.5 if tick >= 200 else 0.0)    # after the pause an earlier time base
            head, poses = _crowd_poses(tick, offsets, tick in nan_ticks, tick in wide_ticks)
            for _ in range(2 if tick == 50 else 1):     # tick 50: the same stamp twice
                _push_both(batched, single, stamp, head, poses)
            if tick == 60:
                batched.push_frames(stamp, poses[:2], 'world')
                single.drop_frames('frames_count', stamp)
        a, b = batched.tick(t + 0.5 / 120.0), single.tick(t + 0.5 / 120.0)
        assert (a is None) == (b is None)
        if a is not None:
            assert np.array_equal(a.origins, b.origins) and \
                np.array_equal(a.orientations, b.orientations)
            outs.append(a)
    assert len(outs) > 250
    assert batched.dropped == single.dropped
    assert batched.dropped['nonfinite'] == len(nan_ticks)
    assert batched.dropped['non_unit_quaternion'] == len(wide_ticks)
    assert batched.dropped['stamp_repeated'] == 1 + 3 and batched.dropped['frames_count'] == 1
    assert batched.frame_accepted_total == single.frame_accepted_total
    assert batched.history_restarts == single.history_restarts == 1 + 3   # the head, the frames
    for e, f in zip(batched.frame_estimators, single.frame_estimators, strict=True):
        n = len(e)
        assert len(f) == n and np.array_equal(e._t[:n], f._t[:n])
        assert np.array_equal(e._p[:n], f._p[:n]) and np.array_equal(e._q[:n], f._q[:n])
    assert batched.target_delay() == single.target_delay()


def _teleport_run(jump, batched=True, ticks=320, at=200):
    """A 4-character crowd (``config/ponytail.yaml``) at 120 Hz, frame 2 (``character_3``)
    moved ``jump`` m along +X from tick ``at`` on (a respawn); the frames' poses pushed in one
    batch each tick (``push_frames``) or one by one (``push_frame``)."""
    from ponytail_ros.app.runner import ChainRunner
    values = complete_values(crowd_values(values_from_params_file(config_path('ponytail.yaml')),
                                          4))
    _, scene, settings = scene_and_settings(values)
    runner = ChainRunner(scene, settings, frames=values['frames'])
    offsets = crowd_offsets(4)
    outs, sent = [], []
    for tick in range(ticks):
        t = tick / 120.0
        head, poses = _crowd_poses(tick, offsets, False, False)
        if tick >= at:
            poses = poses.copy()
            poses[2, 0] += jump
        sent.append(poses[2].copy())
        runner.push(t, head[:3], head[3:], 'world')
        if batched:
            runner.push_frames(t, poses, 'world')
        else:
            for i, row in enumerate(poses):
                runner.push_frame(i, t, row[:3], row[3:], 'world')
        outs.append(runner.tick(t + 0.5 / 120.0))
    return runner, outs, sent


def test_a_frames_teleport_resets_only_the_chains_hanging_from_it():
    """One character of a crowd respawning 20 m away: its history restarts and its chain alone
    is put at rest on the new pose (once, named); nothing blows up. Before, the chain was
    dragged along the anchor track across the jump (322 m/s) and the guard reset every
    character six times. The others carry on: within ten times the contact stage's position
    tolerance of the run without the jump (its position passes are counted over the whole
    scene, so a chain put at rest changes how far the others' shallow contacts are pushed
    out, below that tolerance). The batched and the per-frame paths agree bit for bit."""
    from ponytail_ros.core.contact_model import POSITION_TOLERANCE
    from ponytail_ros.core.rotations import quat_rotate
    still, base, _ = _teleport_run(0.0)
    runner, outs, sent = _teleport_run(20.0)
    _, single, _ = _teleport_run(20.0, batched=False)
    assert runner.resets['teleport'] == 1 and runner.resets['guard'] == 0
    assert runner.last_reset == 'teleport: character_3'
    assert [k for k, o in enumerate(outs) if o is not None and o.frames_reset] == [200]
    assert outs[200].frames_reset == ('character_3',)
    assert all(o.reset_reason is None for o in outs[100:])
    assert still.resets == Counter({r: 0 for r in still.resets})
    m = runner.sim.model
    mine = m.chain_of == 3
    others = ~mine
    for o, b in zip(outs[200:], base[200:], strict=True):
        assert np.max(np.abs(o.origins[others] - b.origins[others])) < 10 * POSITION_TOLERANCE
    # At rest on the new pose: the root on the attachment point of the (one-sample) frame.
    attach = np.asarray(runner.scene.chains[3].attach, dtype=float)
    p, q = sent[200][:3], sent[200][3:]
    root = outs[200].origins[np.flatnonzero(mine)[0]]
    assert np.allclose(root, p + quat_rotate(q, attach), atol=1e-9)
    # ... and it follows the frame from there: no segment moves more than 2 cm a tick.
    steps = [np.max(np.linalg.norm(b.origins[mine] - a.origins[mine], axis=1))
             for a, b in pairwise(outs[200:])]
    assert max(steps) < 0.02
    for a, b in zip(outs, single, strict=True):
        assert (a is None) == (b is None)
        if a is not None:
            assert np.array_equal(a.origins, b.origins) and a.frames_reset == b.frames_reset


def test_reset_chains_puts_only_those_chains_at_rest():
    """``Simulator.reset_chains``: the chains named are what ``reset`` makes them, bit for bit;
    the others, the time and the step count are untouched; a bad index is refused, named."""
    from ponytail_ros.core import ChainSpec, Scene
    from ponytail_ros.core.head import KinematicState, SwayYawMotion
    from ponytail_ros.core.simulator import Simulator
    scene = Scene(chains=[ChainSpec(n_segments=4), ChainSpec(n_segments=3)])
    motion = SwayYawMotion()
    sim = Simulator(scene, motion.state_at(0.0))
    for k in range(1, 30):
        sim.advance_frame(k / 120.0, motion.state_at(k / 120.0))
    before, t, n = sim.state.copy(), sim.t, sim._n_steps
    q_rest = sim.model.q_rest.copy()
    head = KinematicState.still((1.0, 2.0, 3.0))
    sim.reset_chains([1], head)
    rest = Simulator(scene, head)
    rows = sim.model.chain_of == 1
    for f in ('x', 'q', 'v', 'w'):
        assert np.array_equal(getattr(sim.state, f)[rows], getattr(rest.state, f)[rows])
        assert np.array_equal(getattr(sim.state, f)[~rows], getattr(before, f)[~rows])
    assert np.array_equal(sim.model.q_rest[rows], rest.model.q_rest[rows])
    assert np.array_equal(sim.model.q_rest[~rows], q_rest[~rows])
    assert (sim.t, sim._n_steps) == (t, n)
    with pytest.raises(ValueError, match=r'chains \[2\]: indices must be in \[0, 2\)'):
        sim.reset_chains([2], head)


def _crowd_heads(n):
    """The heads of ``n`` characters as ``crowd_offsets`` places them (each the
    ``SwayYawMotion`` delayed and shifted, as the head demo publishes them): ``heads(t)``."""
    from ponytail_ros.core.head import KinematicState, SwayYawMotion
    motion = SwayYawMotion()

    def heads(t):
        states = [motion.state_at(t - delay) for _, delay in crowd_offsets(n)]
        state = KinematicState(*(np.concatenate([getattr(st, f) for st in states])
                                 for f in ('position', 'orientation', 'linear_velocity',
                                           'angular_velocity', 'linear_acceleration',
                                           'angular_acceleration')))
        return dataclasses.replace(state, position=state.position + np.array(
            [shift for shift, _ in crowd_offsets(n)]))
    return heads


@pytest.mark.parametrize('characters', [3, 20])
def test_a_character_in_a_crowd_moves_exactly_as_alone(characters):
    """Chains do not touch one another, so what one character's hair touches must not change
    another's step: the contact stage resolves each chain on its own
    (``contact_stage.resolve_chains_into``). The first of three characters (placed by
    ``crowd_offsets``) moves bit for bit as the same character alone, over 2 s of touching
    its skull (a stage that pooled the chains' skin, passes and re-projection differed by
    0.025 mm here). Of twenty, too: their chains step in SIMD lanes (``lanes``) and the broad
    phase sweeps the colliders (``SWEEP_COLLIDERS``), keeping each chain's one skull of
    twenty."""
    from ponytail_ros.core import broad_phase, lanes
    from ponytail_ros.core.simulator import Simulator
    base = values_from_params_file(config_path('ponytail.yaml'))
    (_, crowd, _), (_, alone, _) = (scene_and_settings(complete_values(crowd_values(base, n)))
                                    for n in (characters, 1))
    h3, h1 = _crowd_heads(characters), _crowd_heads(1)
    a, b = Simulator(crowd, h3(0.0)), Simulator(alone, h1(0.0))
    if characters > 3:                  # (the premises: the sweep, the lanes)
        assert len(crowd.colliders) >= broad_phase.SWEEP_COLLIDERS
        assert a._kernel(a._step_model()).kernel is lanes.advance_lanes
    contacts = 0
    for k in range(1, 241):
        a.advance_frame(k / 120, h3(k / 120))
        b.advance_frame(k / 120, h1(k / 120))
        contacts += b.unilateral.last['contacts']
    assert contacts > 100                      # the character did touch its skull
    n = b.state.x.shape[0]
    for got, alone_value in zip((a.state.x, a.state.q, a.state.v, a.state.w),
                                (b.state.x, b.state.q, b.state.v, b.state.w), strict=True):
        assert np.array_equal(got[:n], alone_value)


def test_frames_topic_must_be_a_topic_other_than_the_heads():
    base = {'frames': ['a', 'b'], 'chains': ['ponytail'], 'ponytail.anchor': 'a'}
    for bad in ('head_pose', 'not a topic'):
        with pytest.raises(ParameterError, match=r'frames_topic = .* is not allowed'):
            complete_values({**base, 'frames_topic': bad})
    # with it set, the frames' own topics do not matter (they may even be equal)
    values = complete_values({**base, 'frames_topic': 'crowd', 'a.topic': 'x', 'b.topic': 'x'})
    assert load_config(None, {**base, 'frames_topic': 'crowd'}).frame_topics == ['crowd'] * 2
    assert values['frames_topic'] == 'crowd'


# -- the PoseArray's bytes ------------------------------------------------------------------------

@pytest.mark.parametrize('frame_id', ['', 'w', 'wo', 'wor', 'world', 'map_frame_with_a_long_name'])
@pytest.mark.parametrize('n', [0, 1, 3])
def test_pose_array_fields_invert_the_layout_and_read_rclpy_bytes(frame_id, n):
    rng = np.random.default_rng(n + len(frame_id))
    block = rng.normal(size=(n, 7))
    data = pose_array_layout(frame_id, n).encode(12, 345, block)
    sec, nanosec, got_frame, poses = pose_array_fields(data)
    assert (sec, nanosec, got_frame) == (12, 345, frame_id)
    assert np.array_equal(poses, block)
    assert pose_array_fields(data[:len(data) - 8]) is None if n else True   # cut short
    assert pose_array_fields(b'\x01' + data[1:]) is None                     # big endian
    rclpy = pytest.importorskip('rclpy')   # noqa: F841 - rclpy's own bytes
    from geometry_msgs.msg import PoseArray
    from rclpy.serialization import deserialize_message, serialize_message
    msg = deserialize_message(data, PoseArray)
    assert msg.header.frame_id == frame_id and len(msg.poses) == n
    theirs = pose_array_fields(serialize_message(msg))
    assert theirs[:3] == (12, 345, frame_id) and np.array_equal(theirs[3], block)


# -- in a node, recorded and replayed -------------------------------------------------------------

rclpy = pytest.importorskip('rclpy')
from ponytail_ros.recording.bag import BagReader  # noqa: E402
from ponytail_ros.recording.offline import replay  # noqa: E402
from ponytail_ros.recording.recorder import RECORDING_METADATA, RunLayout  # noqa: E402
from ponytail_ros.testing import Harness  # noqa: E402
from ponytail_ros.testing.harness import pose_array_msg  # noqa: E402

HEADS = np.array([[0.0, 0.0, 1.5], [1.0, 0.0, 1.5], [2.0, 0.0, 1.5]])
ATTACH = np.array([-0.09, 0.0, 0.06])


def crowd_overrides(**values):
    """Three small characters (4 segments, a skull each), 60 Hz ticks, 1/240 s steps."""
    base = {'rate': 60.0, 'solver.dt': 1.0 / 240.0, 'diagnostics_period': 0.2,
            'chains': ['ponytail'], 'colliders': ['skull'],
            'ponytail.n_segments': 4, 'ponytail.length': 0.2, 'ponytail.mass': 0.05,
            'ponytail.radius': 0.02, 'ponytail.attach': ATTACH.tolist(),
            'ponytail.damping': 1e-3, 'skull.kind': 'sphere', 'skull.radius': 0.09}
    out = crowd_values(base, 3)
    out.update(values)
    return out


def head_at(k, t):
    """Character k's head: a small sway along Y, each with its own phase."""
    return HEADS[k] + [0.0, 0.02 * math.sin(3.0 * t + k), 0.0]


def test_a_node_takes_every_characters_frame_from_one_pose_array_and_drops_bad_ones():
    """Three characters, heads 1 m apart, the second and third on frames_topic: every chain
    stays rooted on its own head (the attachment point, to the step's rounding) and no segment
    enters its skull; a PoseArray of another length is dropped whole (frames_count), a NaN pose
    drops that frame's pose alone (nonfinite), and the chains stay finite."""
    h = Harness(None, crowd_overrides())
    try:
        assert h.frames_pub is not None and h.frame_pubs == []
        duration = 1.0
        trace = h.run(lambda t: (head_at(0, t), Q_ID), duration,
                      frames={f'character_{k}': (lambda t, k=k: (head_at(k, t), Q_ID))
                              for k in (1, 2)})
        assert trace.n_ticks > 0.5 * duration * 60.0
        runner = h.node.runner
        assert sum(runner.dropped.values()) == 0 and runner.resets['guard'] == 0
        t_end = h.now()
        for k, chain in enumerate(['ponytail', 'ponytail_1', 'ponytail_2']):
            msg = h.poses[f'segment_poses/{chain}'][-1]
            root = np.array([msg.poses[0].position.x, msg.poses[0].position.y,
                             msg.poses[0].position.z])
            # On its own head (the root follows the current head's estimate: latency
            # compensation; the neighbours are 1 m away).
            assert np.linalg.norm(root - (head_at(k, t_end) + ATTACH)) < 1e-4, chain
        assert float(runner.sim.contact_depths().max()) < 2e-5

        # One pose for two frames: dropped whole, at once, counted. (Stamped between the
        # run's last pose sent, 0.99 s, and its next, 1.0 s.)
        t = h.now() - 0.005
        h.frames_pub.publish(pose_array_msg(t, HEADS[1:2], [Q_ID]))
        assert h.spin_until(lambda: runner.dropped['frames_count'] == 1, 5.0)
        # A NaN in the second frame's pose: that pose alone is dropped (at the next tick).
        bad = np.array([head_at(1, t), head_at(2, t)])
        bad[1, 0] = math.nan
        h.frames_pub.publish(pose_array_msg(t, bad, [Q_ID, Q_ID]))
        assert h.spin_until(lambda: h._received >= h._sent + 2, 5.0)
        h.run(lambda t: (head_at(0, t), Q_ID), 0.3,
              frames={f'character_{k}': (lambda t, k=k: (head_at(k, t), Q_ID)) for k in (1, 2)})
        assert runner.dropped['nonfinite'] == 1 and runner.dropped['frames_count'] == 1
        assert sum(runner.dropped.values()) == 2 and runner.resets['guard'] == 0
        assert np.all(np.isfinite(runner.sim.state.x))
        d = h.fresh_diagnostics(3.0)
        assert d['dropped inputs: frames_count'] == '1'
        assert d['frame character_1'] == 'ok' and d['frame character_2'] == 'ok'
        assert h.node._input_topics['frames'] == '/frame_poses'
    finally:
        h.close()


def test_a_recording_of_a_crowd_replays_bit_for_bit(tmp_path):
    """The PoseArray of the frames is recorded once per message, on its own topic with its
    type, and the replay pushes it as the node did: every chain's every tick, byte for byte."""
    path = tmp_path / 'crowd.mcap'
    h = Harness(None, crowd_overrides(**{'record_path': str(path)}))
    try:
        h.run(lambda t: (head_at(0, t), Q_ID), 1.0,
              frames={f'character_{k}': (lambda t, k=k: (head_at(k, t), Q_ID)) for k in (1, 2)})
    finally:
        h.close()
    reader = BagReader(path)
    layout = RunLayout.from_metadata(reader.metadata()[RECORDING_METADATA])
    assert layout.frames == ('character_1', 'character_2')
    assert layout.frame_topics == ('/frame_poses', '/frame_poses')
    assert reader.topics()['/frame_poses'] == 'geometry_msgs/msg/PoseArray'
    frames_in = [m for t, _, m, _ in reader.messages({'/frame_poses':
                                                     'geometry_msgs/msg/PoseArray'})]
    assert len(frames_in) >= 90 and all(len(m.poses) == 2 for m in frames_in)

    out = tmp_path / 'replayed.mcap'
    result = replay(path, out)
    assert result.frame_samples == len(frames_in)
    for chain in ('ponytail', 'ponytail_1', 'ponytail_2'):
        topic = f'/segment_poses/{chain}'

        def poses(p, topic=topic):
            return [m for t, _, m, _ in BagReader(p).messages({topic:
                                                               'geometry_msgs/msg/PoseArray'})]
        live, again = poses(path), poses(out)
        assert len(live) >= 30 and again == live, chain
    again_in = [m for t, _, m, _ in BagReader(out).messages({'/frame_poses':
                                                            'geometry_msgs/msg/PoseArray'})]
    assert again_in == frames_in


def test_the_head_demo_publishes_the_other_characters_heads_in_one_pose_array(ros_context):
    from geometry_msgs.msg import PoseArray, PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from ponytail_ros.ros.head_demo import HeadDemoNode
    ctx = ros_context
    demo = HeadDemoNode(context=ctx, parameter_overrides=[
        Parameter('characters', value=4), Parameter('motion', value='still'),
        Parameter('rate', value=200.0)])
    listener = rclpy.create_node('listener', context=ctx)
    try:
        heads, crowds = [], []
        listener.create_subscription(PoseStamped, 'head_pose', heads.append, 10)
        listener.create_subscription(PoseArray, 'frame_poses', crowds.append, 10)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(demo)
        ex.add_node(listener)
        for _ in range(2000):
            ex.spin_once(timeout_sec=0.01)
            if heads and crowds:
                break
        assert heads and crowds
        msg = crowds[-1]
        assert len(msg.poses) == 3 and msg.header.frame_id == 'world'
        head = heads[-1].pose.position
        for k, pose in enumerate(msg.poses, start=1):
            assert (pose.position.x, pose.position.y, pose.position.z) == pytest.approx(
                (head.x + k * CHARACTER_SPACING, head.y, head.z), abs=1e-12)
            assert pose.orientation.w == pytest.approx(1.0)
    finally:
        demo.destroy_node()
        listener.destroy_node()
