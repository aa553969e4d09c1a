"""The node's per-tick logic without ROS (``ChainRunner``), its parameter table and the head
script: exact counts and simulated time, fast and deterministic."""
import numpy as np
import pytest

from ponytail_ros.app.head_script import PHASES, HeadScript
from ponytail_ros.app.parameters import CHAIN_PARAMS, GLOBAL_PARAMS, ParameterError, check_values
from ponytail_ros.app.runner import START_SAMPLES, ChainRunner, RunnerSettings, structural_change
from ponytail_ros.core import ChainSpec, Scene, SwayYawMotion
from ponytail_ros.core.rotations import quat_axis_x, quat_from_rotvec, quat_rotate

ATTACH = np.array([-0.09, 0.0, 0.06])
Q_ID = (0.0, 0.0, 0.0, 1.0)


def scene(**chain):
    spec = dict(name='ponytail', n_segments=8, length=0.3, mass=0.1, radius=0.03,
                attach=tuple(ATTACH), damping=1e-3, drag_linear=0.02)
    spec.update(chain)
    return Scene(chains=(ChainSpec(**spec),))


def drive(runner, motion, t0, t1, rate=100.0, tick=120.0, frame='world', out=None,
          stamp_offset=0.0):
    """Push samples of ``motion`` at ``rate`` (stamped ``+ stamp_offset``) and tick at ``tick``
    over [t0, t1)."""
    outs = [] if out is None else out
    tp, tt = t0, t0
    while tt < t1:
        while tp <= tt:
            s = motion.state_at(tp)
            runner.push(tp + stamp_offset, s.position[0], s.orientation[0], frame)
            tp += 1.0 / rate
        o = runner.tick(tt)
        if o is not None:
            outs.append(o)
        tt += 1.0 / tick
    return outs


def check_chain(out, lengths):
    o, q = out.origins, out.orientations
    assert np.all(np.isfinite(o)) and np.all(np.isfinite(q))
    distal = o + quat_axis_x(q) * np.asarray(lengths)[:, None]
    assert np.max(np.linalg.norm(distal[:-1] - o[1:], axis=1)) < 1e-6


def attach_point(p, q):
    return np.asarray(p) + quat_rotate(np.asarray(q, dtype=float), ATTACH)


def test_nothing_before_the_first_pose_then_chain_hangs_from_the_attachment():
    r = ChainRunner(scene())
    assert r.tick(1.0) is None and r.tick(1.01) is None
    q = quat_from_rotvec(np.array([0.0, 0.0, 0.7]))
    p = np.array([1.0, 2.0, 1.5])
    for k in range(30):
        r.push(1.02 + k * 0.01, p, q, 'map')
        out = r.tick(1.02 + k * 0.01)
        if k < START_SAMPLES - 1:     # no velocity estimate yet: nothing published
            assert out is None
            continue
        check_chain(out, np.full(8, 0.3 / 8))
        assert np.linalg.norm(out.origins[0] - attach_point(p, q)) < 1e-9
    assert out.frame_id == 'map'
    assert sum(r.dropped.values()) == 0 and sum(r.resets.values()) == 0


def test_follows_a_moving_head_with_the_declared_delay():
    motion = SwayYawMotion()
    r = ChainRunner(scene(), RunnerSettings(interpolation_delay=0.01,
                                            interpolation_delay_periods=0.0,
                                            latency_compensation=False))
    outs = drive(r, motion, 0.0, 3.0, rate=100.0)
    worst = 0.0
    for o in outs[20:]:
        check_chain(o, np.full(8, 0.3 / 8))
        s = motion.state_at(o.t_head)
        ref = attach_point(s.position[0], s.orientation[0])
        worst = max(worst, np.linalg.norm(o.origins[0] - ref))
        assert o.t - o.t_head == pytest.approx(0.01)
    # The chain's time lags t_head by < one internal step (4 ms at ≤ 0.6 m/s: < 2.5 mm).
    assert worst < 4e-3
    assert r.resets['guard'] == 0


BAD = {
    'nonfinite': ((np.nan, 0.0, 1.6), Q_ID),
    'zero_quaternion': ((0.0, 0.0, 1.6), (0.0, 0.0, 0.0, 0.0)),
    'non_unit_quaternion': ((0.0, 0.0, 1.6), (0.0, 0.0, 0.0, 1.5)),
}


@pytest.mark.parametrize('reason', sorted(BAD) + ['inf_quaternion', 'stamp_backwards',
                                                   'stamp_repeated', 'frame_changed'])
def test_each_bad_input_is_dropped_and_counted(reason):
    r = ChainRunner(scene(), RunnerSettings(stale_timeout=0.5))
    motion = SwayYawMotion()
    outs = drive(r, motion, 0.0, 0.5)
    t = 0.5
    for _ in range(3):
        s = motion.state_at(t)
        p, q, stamp, frame = s.position[0], s.orientation[0], t, 'world'
        if reason in BAD:
            p, q = BAD[reason]
        elif reason == 'inf_quaternion':
            q = (np.inf, 0.0, 0.0, 1.0)
        elif reason == 'stamp_backwards':
            stamp = t - 0.2
        elif reason == 'stamp_repeated':
            stamp = r.newest_stamp
        elif reason == 'frame_changed':
            frame = 'odom'
        r.push(stamp, p, q, frame)
        outs.append(r.tick(t))
        t += 0.005
    drive(r, motion, t, t + 0.3, out=outs)
    key = 'nonfinite' if reason == 'inf_quaternion' else reason
    assert r.dropped[key] == 3
    assert sum(r.dropped.values()) == 3
    assert sum(r.resets.values()) == 0
    for o in outs:
        check_chain(o, np.full(8, 0.3 / 8))
    assert outs[-1].frame_id == 'world'


def test_near_unit_quaternion_is_normalised_and_accepted():
    r = ChainRunner(scene())
    q = np.array([0.0, 0.0, 0.0, 1.0 + 5e-4])
    for k in range(5):
        r.push(k * 0.01, (0.0, 0.0, 1.6), q, 'world')
        out = r.tick(k * 0.01)
    assert sum(r.dropped.values()) == 0
    assert np.allclose(np.linalg.norm(out.orientations, axis=1), 1.0)


def test_flood_is_bounded_per_tick_and_counted():
    r = ChainRunner(scene(), RunnerSettings(max_queue=16))
    for k in range(5000):
        r.push(k * 1e-4, (0.0, 0.0, 1.6), Q_ID, 'world')
    out = r.tick(0.5)
    assert r.dropped['queue_overflow'] == 5000 - 16
    assert out.accepted == 16
    check_chain(out, np.full(8, 0.3 / 8))


def test_frame_switch_adopted_only_once_the_head_is_stale():
    r = ChainRunner(scene(), RunnerSettings(stale_timeout=0.2))
    still = SwayYawMotion(amplitude=0.0, yaw_amplitude=0.0)
    drive(r, still, 0.0, 0.5, frame='world')
    # Interleaved with a live stream: dropped.
    outs = drive(r, still, 0.5, 0.6, frame='odom')
    assert r.dropped['frame_changed'] > 0 and outs[-1].frame_id == 'world'
    # The 'world' stream stops; 'odom' alone goes on: adopted after stale_timeout, chain reset.
    outs = drive(r, still, 0.6, 1.2, frame='odom')
    assert outs[-1].frame_id == 'odom'
    assert r.resets['frame_changed'] == 1


def test_teleport_resets_the_chain_at_rest_at_the_new_pose():
    r = ChainRunner(scene(), RunnerSettings(teleport_distance=0.5, teleport_angle=1.0))
    drive(r, SwayYawMotion(), 0.0, 1.0)
    p_new = np.array([5.0, 0.0, 1.6])

    def hold(t, q):
        """The new pose held at 100 Hz: nothing until its history has START_SAMPLES poses."""
        outs = []
        for k in range(START_SAMPLES):
            r.push(t + 0.01 * k, p_new, q, 'world')
            outs.append(r.tick(t + 0.01 * k))
        assert all(o is None for o in outs[:-1])
        return outs[-1]
    out = hold(1.0, Q_ID)
    assert out.reset_reason == 'teleport' and r.resets['teleport'] == 1
    assert np.linalg.norm(out.origins[0] - attach_point(p_new, Q_ID)) < 1e-9
    # At rest along gravity: every segment points straight down.
    assert np.allclose(quat_axis_x(out.orientations), [0.0, 0.0, -1.0], atol=1e-9)
    # A pure rotation beyond teleport_angle also counts.
    assert hold(1.1, quat_from_rotvec(np.array([0.0, 0.0, 1.5]))).reset_reason == 'teleport'


def test_stale_head_holds_the_last_pose_and_the_chain_settles():
    r = ChainRunner(scene(drag_linear=0.2), RunnerSettings(stale_timeout=0.25))
    drive(r, SwayYawMotion(), 0.0, 2.0)
    tips, heads = [], []
    t = 2.0
    while t < 14.0:
        o = r.tick(t)
        tips.append(o.origins[-1].copy())
        heads.append(o.origins[0].copy())
        t += 1.0 / 120
    assert o.head_stale
    # Held: the estimator extrapolated for head.max_extrapolation (braking), then stopped.
    held = r.estimator.state_at(100.0)
    assert np.linalg.norm(o.origins[0] - attach_point(held.position[0], held.orientation[0])) \
        < 1e-9
    # (held from max_extrapolation after the last pose; from max_gap on, a gap, returned
    # within max_extrapolation to the last pose the stream gave, and held there)
    assert np.ptp(np.array(heads[30:58]), axis=0).max() < 1e-12
    assert np.ptp(np.array(heads[74:]), axis=0).max() < 1e-12
    tips = np.array(tips)
    speed = np.linalg.norm(np.diff(tips, axis=0), axis=1) * 120
    assert speed[:120].max() > 0.05        # still swinging right after the head stopped
    assert speed[-120:].max() < 0.2 * speed[:120].max()   # and settling
    assert r.resets['guard'] == 0


def test_clock_backwards_restarts_and_stream_restart_is_adopted():
    r = ChainRunner(scene(), RunnerSettings(stale_timeout=0.2))
    still = SwayYawMotion(amplitude=0.0, yaw_amplitude=0.0)
    drive(r, still, 10.0, 10.5)
    # The node clock jumps back (a restarted /clock): start over from the next sample.
    assert r.tick(1.0) is None
    assert r.resets['clock_backwards'] == 1
    drive(r, still, 1.0, 1.2)
    assert r.has_head
    # The publisher's stamps jump back for good while the node clock goes on: dropped until the
    # head is stale, then the stream is adopted (the chain carries on, no reset).
    outs = drive(r, still, 1.2, 1.8, stamp_offset=-100.0)
    assert r.dropped['stamp_backwards'] > 0
    assert r.history_restarts == 1
    assert not outs[-1].head_stale


def test_delay_in_input_periods_and_latency_compensation_keeps_the_root_on_the_head():
    motion = SwayYawMotion()
    for rate in (30.0, 100.0):
        r = ChainRunner(scene(), RunnerSettings(interpolation_delay=0.002,
                                                interpolation_delay_periods=1.5))
        outs = drive(r, motion, 0.0, 2.0, rate=rate)
        assert r.delay == pytest.approx(1.5 / rate, rel=0.1)
        errors = []
        for o in outs[len(outs) // 2:]:
            check_chain(o, np.full(8, 0.3 / 8))
            s = motion.state_at(o.t)       # the head now, not t_head
            errors.append(np.linalg.norm(o.origins[0] - attach_point(s.position[0],
                                                                     s.orientation[0])))
        # The root follows the current head up to the extrapolation error (the sway moves
        # 0.5 m/s: uncompensated, 1.5 periods at 30 Hz would leave it 25 mm behind).
        assert max(errors) < (6e-3 if rate == 30.0 else 3e-3)


def test_delay_change_is_slewed_so_head_time_never_runs_backwards():
    r = ChainRunner(scene(), RunnerSettings(interpolation_delay=0.0,
                                            interpolation_delay_periods=0.0))
    outs = drive(r, SwayYawMotion(), 0.0, 0.5)
    r.update_settings(interpolation_delay=0.1)
    drive(r, SwayYawMotion(), 0.5, 1.0, out=outs)
    t_head = np.array([o.t_head for o in outs])
    assert np.all(np.diff(t_head) > 0.0)
    assert outs[-1].t - outs[-1].t_head == pytest.approx(0.1)


def test_tunable_change_keeps_the_chain_structural_change_rebuilds():
    r = ChainRunner(scene())
    drive(r, SwayYawMotion(), 0.0, 0.3)
    sim = r.sim
    tuned = scene(damping=2e-3, drag_linear=0.1).replace(gravity=(0.0, 0.0, -5.0))
    assert not structural_change(r.scene, tuned)
    r.set_scene(tuned)
    out = r.tick(0.31)
    assert r.sim is sim and out.reset_reason is None
    assert np.all(sim.model.damping == 2e-3) and np.all(sim.model.gravity == (0.0, 0.0, -5.0))
    bigger = scene(n_segments=12)
    assert structural_change(r.scene, bigger)
    r.set_scene(bigger)
    out = r.tick(0.32)
    assert r.sim is not sim and out.reset_reason == 'rebuild' and len(out.origins) == 12


def _values(**changes):
    vals = {p.name: p.default for p in GLOBAL_PARAMS}
    for p in CHAIN_PARAMS:
        vals[f'ponytail.{p.name}'] = p.default
    vals.update(changes)
    return vals


@pytest.mark.parametrize('changes, names', [
    ({'ponytail.attach': [0.0, 1.0]}, 'ponytail.attach'),
    ({'ponytail.rest_direction': [0.0, float('nan'), 0.0]}, 'ponytail.rest_direction'),
    ({'solver.integrator': 'euler'}, 'solver.integrator'),
    ({'solver.max_steps_per_call': 1}, 'solver.max_steps_per_call'),
    ({'ponytail.length': 0.0}, 'ponytail.length'),
    ({'gravity': [0.0, 0.0, -1e5]}, 'gravity'),
    ({'ponytail.color': [1.0, 0.0, 0.0]}, 'ponytail.color'),
    ({'ponytail.n_segments': 3, 'ponytail.segment_lengths': [0.1, 0.2]},
     'ponytail.segment_lengths'),
    ({'ponytail.segment_masses': [0.01] * 9 + [-0.01]}, 'ponytail.segment_masses'),
    ({'ponytail.segment_masses': ['heavy'] * 10}, 'ponytail.segment_masses'),
    ({'ponytail.inertia': [1e-6] * 29}, 'ponytail.inertia'),
    ({'ponytail.swing_limits': [0.5] * 10 + [0.4]}, 'ponytail.swing_limits'),
    ({'ponytail.twist_limits': [0.5] * 9 + [4.0]}, 'ponytail.twist_limits'),
])
def test_parameter_checks_name_the_offending_parameter(changes, names):
    vals = _values(**changes)
    with pytest.raises(ParameterError) as err:
        check_values(vals, ['ponytail'])
    assert names in str(err.value) and names in err.value.names


def test_default_parameters_make_a_valid_scene():
    s = check_values(_values(), ['ponytail'])
    assert s.chains[0].rest_direction is None


def test_per_segment_parameters_reach_the_scene():
    """A tapered 3-segment tail: lengths, masses, inertias and per-joint limits given per
    segment override the uniform ones; [] (the default) leaves them uniform."""
    s = check_values(_values(**{
        'ponytail.n_segments': 3, 'ponytail.segment_lengths': [0.2, 0.15, 0.1],
        'ponytail.segment_masses': [0.3, 0.2, 0.1],
        'ponytail.inertia': [1e-5, 1e-3, 1e-3, 5e-6, 4e-4, 4e-4, 1e-6, 1e-4, 1e-4],
        'ponytail.swing_limit': 1.0, 'ponytail.swing_limits': [0.3, 0.6, 0.9],
        'ponytail.twist_limits': [0.2, 0.2, 0.4]}), ['ponytail'])
    c = s.chains[0]
    assert np.allclose(c.lengths(), [0.2, 0.15, 0.1]) and np.allclose(c.masses(), [0.3, 0.2, 0.1])
    assert np.allclose(c.principal_inertia()[1], [5e-6, 4e-4, 4e-4])
    assert np.allclose(c.joint_limits('swing_limit'), [0.3, 0.6, 0.9])
    assert np.allclose(c.joint_limits('twist_limit'), [0.2, 0.2, 0.4])
    uniform = check_values(_values(**{'ponytail.swing_limit': 1.0}), ['ponytail']).chains[0]
    assert np.allclose(uniform.lengths(), 0.04)
    assert np.allclose(uniform.joint_limits('swing_limit'), 1.0)
    assert np.all(np.isinf(uniform.joint_limits('twist_limit')))


def test_head_script_is_smooth_and_loops():
    m = HeadScript()
    ts = np.arange(0.0, 2 * m.PERIOD, 1e-3)
    P = np.array([m.pose(t)[0] for t in ts])
    Q = np.array([m.pose(t)[1] for t in ts])
    assert np.max(np.linalg.norm(np.diff(P, axis=0), axis=1)) < 5e-3    # ≤ ~3 m/s
    assert np.min(np.abs(np.sum(Q[1:] * Q[:-1], axis=1))) > 1.0 - 1e-4
    p0, q0 = m.pose(0.0)
    p1, q1 = m.pose(m.PERIOD - 1e-9)
    assert np.allclose(p0, p1, atol=1e-6) and abs(abs(q0 @ q1) - 1.0) < 1e-9
    assert [p[0] for p in PHASES][:3] == ['idle_sway', 'nod', 'shake']
    assert m.phase(11.5) == 'run'
    s = m.state_at(12.0)      # cruising at 3 m/s along +Y
    assert s.linear_velocity[0] == pytest.approx([0.0, 3.0, s.linear_velocity[0][2]], abs=1e-3)
    stop = [np.linalg.norm(m.state_at(t).linear_acceleration[0, :2])
            for t in np.arange(12.6, 13.0, 0.005)]
    assert max(stop) > 20.0                 # the sharp stop: over 2 g


def test_a_live_n_segments_past_the_colliding_range_is_refused_and_the_chain_runs_on():
    """``config/ponytail.yaml`` (a ponytail colliding with its skull): a live change to
    ``n_segments: 4096`` is refused, naming the parameter and the range that runs
    (``MAX_COLLIDING_SEGMENTS``), and the running value stays; within the range it is
    accepted."""
    from ponytail_ros.app.node_core import NodeCore
    from ponytail_ros.core.scene import MAX_COLLIDING_SEGMENTS
    from ponytail_ros.resources import config_path
    from ponytail_ros.testing import load_config
    core = NodeCore(load_config(config_path('ponytail.yaml')).values)
    with pytest.raises(ParameterError) as err:
        core.check_change({'ponytail.n_segments': 4096})
    assert 'ponytail.n_segments' in err.value.names
    assert f'[1, {MAX_COLLIDING_SEGMENTS}]' in str(err.value)
    assert core.values['ponytail.n_segments'] == 12
    core.check_change({'ponytail.n_segments': MAX_COLLIDING_SEGMENTS})
    core.check_change({'ponytail.n_segments': 4096, 'ponytail.collide': False})


def test_diagnostics_say_when_the_ticks_fall_behind_the_rate():
    """A node whose tick calls come at the rate reports that rate and no overload; one whose
    calls come at half the rate (each tick longer than its period) is ``WARN``ed as
    overloaded, naming both rates; a window before any head pose (ticks called, nothing
    published) is not; a short window (a short ``diagnostics_period``) still reports the rate
    once its calls span ``MIN_RATE_PERIODS`` periods, and nothing below that."""
    from diagnostic_msgs.msg import DiagnosticStatus

    from ponytail_ros.app.node_core import OVERLOADED, NodeCore, time_msg
    from ponytail_ros.resources import config_path
    from ponytail_ros.testing import load_config
    core = NodeCore(load_config(config_path('ponytail.yaml')).values)
    period = int(round(1e9 / 120.0))
    t = 1_000_000_000

    def run(seconds, every, with_head=True):
        nonlocal t
        for _ in range(int(round(seconds * 120 / every))):
            t += every * period
            if with_head:
                core.push_head(time_msg(t), t, (0.0, 0.0, 1.6), (0.0, 0.0, 0.0, 1.0), 'world')
            core.tick(t)
        status = core.diagnostic_status(t, seconds, 'ponytail')
        return status, {kv.key: kv.value for kv in status.values}

    status, kv = run(1.0, 1, with_head=False)
    assert OVERLOADED not in status.message and float(kv['tick rate (Hz)']) == pytest.approx(120)
    status, kv = run(1.5, 1)
    assert status.level == DiagnosticStatus.OK, status.message
    assert float(kv['tick rate (Hz)']) == pytest.approx(120.0, rel=1e-6)
    status, kv = run(1.5, 2)
    assert status.level == DiagnosticStatus.WARN
    assert f'{OVERLOADED}: ticking at 60.0 Hz of rate 120 Hz' in status.message
    status, kv = run(0.1, 1)                    # 12 ticks: 11 periods, enough to say
    assert float(kv['tick rate (Hz)']) == pytest.approx(120.0, rel=1e-6)
    status, kv = run(8 / 120, 2)                # 4 ticks, 6 periods: too few to say
    assert kv['tick rate (Hz)'] == 'n/a' and OVERLOADED not in status.message
