"""The ponytail node in-process, on the wall clock: head publisher, node and test subscriber in
one ``SingleThreadedExecutor`` on a fresh rclpy context per test, talking over DDS with
discovery off -- the public harness, ``ponytail_ros.testing.Harness``."""
import math

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from builtin_interfaces.msg import Time  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from ponytail_ros.ros.head_demo import HeadDemoNode  # noqa: E402
from ponytail_ros.testing.harness import TIMEOUT_SCALE, diagnostic_values  # noqa: E402,F401

from ros_helpers import (  # noqa: E402
    P_HEAD,
    Q_TILT,
    Harness,
    arrays,
    attach_point,
    check_geometry,
    overrides,
    pose_msg,
    stamp,
    t_of,
)


@pytest.fixture
def harness():
    made = []

    def make(*args, **kwargs):
        h = Harness(None, *args, **kwargs)
        made.append(h)
        return h
    yield make
    for h in made:
        h.close()


def still(p=P_HEAD, q=Q_TILT, frame='world'):
    return lambda t: (p, q, frame)


# -- geometry and following ------------------------------------------------------------------

def test_head_demo_drives_the_chain_which_follows_the_head(harness):
    # Enough steps per tick to catch up after any stall of a loaded test machine; and no
    # teleport reset when such a stall lets the yaw (±0.6 rad) move by more than the default
    # teleport_angle between two accepted samples (tested elsewhere).
    h = harness(overrides(interpolation_delay=0.01, interpolation_delay_periods=0.0,
                          latency_compensation=False, solver__max_steps_per_call=2400,
                          teleport_angle=3.0))
    origin = [0.5, -0.3, 1.6]
    demo = h.add(HeadDemoNode(context=h.context, parameter_overrides=[
        Parameter('motion', value='sway'), Parameter('origin', value=origin),
        Parameter('rate', value=100.0)]))
    heads = []
    h.tester.create_subscription(PoseStamped, 'head_pose',
                                 lambda m: heads.append(t_of(m.header)), 100)
    got = h.poses['segment_poses']
    errors, stamps = [], []

    def evaluate():
        # Judge only instants the head stream covered on both sides (a stall of a loaded
        # machine leaves gaps the estimator has to bridge).
        while len(stamps) < len(got):
            msg = got[len(stamps)]
            o, q = check_geometry(msg, 6, 0.3)
            assert msg.header.frame_id == 'world'
            stamps.append(t_of(msg.header))
            t_head = stamps[-1] - 0.01
            hs = np.array(heads)
            before, after = hs[hs <= t_head], hs[hs > t_head]
            if len(stamps) < 10 or not len(before) or not len(after) or \
                    t_head - before.max() > 0.012 or after.min() - t_head > 0.012:
                continue
            s = demo.motion.state_at(t_head - demo._t0)
            errors.append(np.linalg.norm(o[0] - attach_point(s.position[0],
                                                              s.orientation[0])))
        return len(errors) >= 30
    assert h.spin_until(evaluate, 10.0)
    assert np.all(np.diff(stamps) > 0)
    # Segment 1 starts at the attachment point of the head as it was interpolation_delay ago
    # (the sway moves 0.5 m/s: the < 4 ms internal-step lag and estimation stay below 5 mm).
    assert max(errors) < 5e-3
    assert h.node.runner.resets['guard'] == 0


def test_still_head_segment_one_exactly_at_attachment_and_best_effort_publisher(harness):
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    h = harness(overrides(frame_id='head_out'), head_qos=qos)
    h.head = still()
    got = h.poses['segment_poses']
    assert h.spin_until(lambda: len(got) >= 20, 5.0)
    o, q = check_geometry(got[-1], 6, 0.3)
    assert np.linalg.norm(o[0] - attach_point(P_HEAD, Q_TILT)) < 1e-6
    assert got[-1].header.frame_id == 'head_out'          # the frame_id parameter overrides


def test_zero_stamps_fall_back_to_the_receive_time(harness):
    h = harness(overrides())
    h.head = still()
    got = h.poses['segment_poses']
    h.head = None

    def publish_unstamped():
        h.head_pub.publish(pose_msg(Time(sec=0, nanosec=0)))
    h.tester.create_timer(0.01, publish_unstamped)
    assert h.spin_until(lambda: len(got) >= 10, 5.0)
    assert sum(h.node.runner.dropped.values()) == 0
    o, _ = check_geometry(got[-1], 6, 0.3)
    assert np.linalg.norm(o[0] - attach_point(P_HEAD, Q_TILT)) < 1e-6


def test_two_chains_own_topics_parameters_and_markers(harness):
    h = harness(overrides(chains=('left', 'right'), left__attach=[0.0, 0.08, 0.0],
                          right__attach=[0.0, -0.08, 0.0], right__n_segments=4,
                          markers__rate=1000.0),
                topics=('segment_poses/left', 'segment_poses/right'))
    h.head = still()
    left, right = h.poses['segment_poses/left'], h.poses['segment_poses/right']
    assert h.spin_until(lambda: len(left) >= 10 and len(right) >= 10 and h.markers, 5.0)
    lo, _ = check_geometry(left[-1], 6, 0.3)
    ro, _ = check_geometry(right[-1], 4, 0.3)
    assert np.linalg.norm(lo[0] - attach_point(P_HEAD, Q_TILT, [0.0, 0.08, 0.0])) < 1e-6
    assert np.linalg.norm(ro[0] - attach_point(P_HEAD, Q_TILT, [0.0, -0.08, 0.0])) < 1e-6
    # Capsules: per chain a sphere list (id 0) and one cylinder per segment; first a DELETEALL.
    first = h.markers[0].markers
    assert first[0].action == Marker.DELETEALL
    last = h.markers[-1].markers
    by_ns = {}
    for m in last:
        by_ns.setdefault(m.ns, []).append(m)
    assert len(by_ns['left']) == 1 + 6 and len(by_ns['right']) == 1 + 4
    cyl = [m for m in by_ns['left'] if m.type == Marker.CYLINDER]
    assert all(m.header.frame_id == 'world' for m in last)
    assert cyl[0].scale.z == pytest.approx(0.05)
    # Switch to line strips live: DELETEALL, then sphere list + line strip per chain.
    n = len(h.markers)
    ok = h.node.set_parameters([Parameter('markers.style', value='line')])[0]
    assert ok.successful

    def line_style():
        return {m.type for m in h.markers[-1].markers} == {Marker.SPHERE_LIST, Marker.LINE_STRIP}
    assert h.spin_until(line_style, 3.0)
    switched = [m for arr in h.markers[n:] for m in arr.markers]
    assert any(m.action == Marker.DELETEALL for m in switched)
    assert len(h.markers[-1].markers) == 4


# -- bad input -------------------------------------------------------------------------------

def test_every_bad_input_is_dropped_counted_and_harmless(harness):
    h = harness(overrides(stale_timeout=2.0))
    h.head = still()
    got = h.poses['segment_poses']
    assert h.spin_until(lambda: len(got) >= 5, 5.0)
    r = h.node.runner
    h.head = None            # pause the good stream so that "newest" stays the newest
    # Every good pose sent has been taken in by a tick (a loaded machine may lag).
    assert h.spin_until(lambda: r.newest_stamp is not None
                        and abs(r.newest_stamp - h.last_sent) < 1e-5, 3.0)
    newest = r.newest_stamp
    bad = {
        'nonfinite': [pose_msg(h.now(), p=(math.nan, 0.0, 1.0)),
                      pose_msg(h.now(), q=(0.0, math.inf, 0.0, 1.0))],
        'zero_quaternion': [pose_msg(h.now(), q=(0.0, 0.0, 0.0, 0.0))],
        'non_unit_quaternion': [pose_msg(h.now(), q=(0.0, 0.0, 0.0, 1.3))],
        'stamp_backwards': [pose_msg(newest - 0.5)],
        'stamp_repeated': [pose_msg(stamp(newest))],
        'frame_changed': [pose_msg(h.now(), frame='odom')],
    }
    for msgs in bad.values():
        for m in msgs:
            h.head_pub.publish(m)
        h.spin_for(0.02)
    # A near-unit quaternion is normalised and accepted, not dropped.
    h.head_pub.publish(pose_msg(h.now(), q=Q_TILT * (1.0 + 5e-4)))
    h.head = still()
    expected = {k: len(v) for k, v in bad.items()}
    assert h.spin_until(lambda: all(r.dropped[k] == n for k, n in expected.items()), 3.0), \
        dict(r.dropped)
    assert sum(r.dropped.values()) == sum(expected.values())
    d = h.fresh_diagnostics(3.0)
    for k, n in expected.items():
        assert d[f'dropped inputs: {k}'] == str(n)
    assert d['resets'] == '0' and d['head'] == 'ok'
    # The window's tick times: 0 < p99 <= max (ms), as measured by the node itself.
    assert 0.0 < float(d['tick time p99 (ms)']) <= float(d['tick time max (ms)'])
    n = len(got)
    assert h.spin_until(lambda: len(got) >= n + 10, 3.0)      # still publishing
    for msg in got:
        o, q = check_geometry(msg, 6, 0.3)
        assert np.linalg.norm(o[0] - attach_point(P_HEAD, Q_TILT)) < 1e-6
        assert msg.header.frame_id == 'world'


def test_flood_of_head_poses_bounded_work_per_tick(harness):
    h = harness(overrides(input_queue_size=1))
    h.head = still()
    got = h.poses['segment_poses']
    assert h.spin_until(lambda: len(got) >= 3, 5.0)
    r = h.node.runner
    t = h.now()
    for burst in range(5):
        # A burst between two ticks (the timer held, so that a loaded machine cannot interleave
        # ticks): the subscription keeps the newest 5 (sensor-data QoS), the node's queue 1.
        h.node._timer.cancel()
        for k in range(200):
            h.head_pub.publish(pose_msg(t + 1e-5 * k + 0.01 * burst))
        h.spin_for(0.05)
        h.node._timer.reset()
        h.spin_for(0.02)
    assert h.spin_until(lambda: r.dropped['queue_overflow'] > 0, 3.0)
    assert int(h.fresh_diagnostics(3.0)['dropped inputs: queue_overflow']) > 0
    n = len(got)
    h.spin_for(0.2)
    assert len(got) > n
    check_geometry(got[-1], 6, 0.3)
    assert r.resets['guard'] == 0


def test_frame_change_dropped_while_live_then_adopted_with_reset(harness):
    h = harness(overrides(stale_timeout=0.2))
    h.head = still(frame='world')
    got = h.poses['segment_poses']
    assert h.spin_until(lambda: len(got) >= 5, 5.0)
    h.head_pub.publish(pose_msg(h.now() + 0.002, frame='map'))
    r = h.node.runner
    assert h.spin_until(lambda: r.dropped['frame_changed'] == 1, 2.0)
    h.head = still(frame='map')           # the publisher switched for good
    assert h.spin_until(lambda: got[-1].header.frame_id == 'map', 3.0)
    assert r.resets['frame_changed'] == 1
    d = h.fresh_diagnostics(3.0)
    assert int(d['dropped inputs: frame_changed']) >= 1 and d['resets: frame_changed'] == '1'
    assert d['head frame'] == 'map'


def test_stale_head_keeps_publishing_then_teleport_resets(harness):
    h = harness(overrides(stale_timeout=0.15, teleport_distance=0.5))
    h.head = lambda t: (P_HEAD + [0.05 * math.sin(8.0 * t), 0.0, 0.0], Q_TILT, 'world')
    got = h.poses['segment_poses']
    assert h.spin_until(lambda: len(got) >= 30, 5.0)
    h.head = None                                   # the head stops publishing
    d = h.fresh_diagnostics(3.0)
    d = h.fresh_diagnostics(3.0)
    assert d['head'] == 'stale'
    n = len(got)
    assert h.spin_until(lambda: len(got) > n + 10, 2.0)
    o1, _ = check_geometry(got[-1], 6, 0.3)
    o0, _ = check_geometry(got[-5], 6, 0.3)
    assert np.linalg.norm(o1[0] - o0[0]) < 1e-9     # the head is held ...
    assert h.node.runner.resets['guard'] == 0
    # ... until it reappears 3 m away: a teleport, the chain reset at rest at the new pose.
    p_new = P_HEAD + [3.0, 0.0, 0.0]
    h.head = still(p=p_new)
    r = h.node.runner
    assert h.spin_until(lambda: r.resets['teleport'] == 1, 3.0)
    n = len(got)
    assert h.spin_until(lambda: len(got) > n + 2, 2.0)
    o, q = check_geometry(got[-1], 6, 0.3)
    assert np.linalg.norm(o[0] - attach_point(p_new, Q_TILT)) < 1e-6
    assert h.fresh_diagnostics(3.0)['resets: teleport'] == '1'


# -- parameters ------------------------------------------------------------------------------

def test_parameters_rejected_with_reason_and_running_value_stays(harness):
    h = harness(overrides())
    h.head = still()
    assert h.spin_until(lambda: len(h.poses['segment_poses']) >= 3, 5.0)
    client = AsyncParameterClient(h.tester, 'ponytail')
    assert client.wait_for_services(timeout_sec=3.0)

    def set_remote(**kw):
        fut = client.set_parameters([Parameter(k.replace('__', '.'), value=v)
                                     for k, v in kw.items()])
        assert h.spin_until(fut.done, 3.0)
        return fut.result().results[0]

    cases = [
        ({'rate': 5000.0}, 'rate'),
        ({'ponytail__attach': [0.1, 0.2]}, 'ponytail.attach'),
        ({'ponytail__length': -1.0}, 'ponytail.length'),
        ({'solver__integrator': 'euler'}, 'solver.integrator'),
        ({'solver__max_steps_per_call': 1}, 'solver.max_steps_per_call'),
        ({'chains': ['a', 'b']}, 'chains'),                 # read-only
        ({'gravity': [0.0, 0.0, math.nan]}, 'gravity'),
    ]
    before = {p: h.node.get_parameter(p).value for p in (
        'rate', 'ponytail.attach', 'ponytail.length', 'solver.integrator',
        'solver.max_steps_per_call', 'chains', 'gravity')}
    for kw, name in cases:
        res = set_remote(**kw)
        assert not res.successful, kw
        assert name in res.reason, res.reason
    for p, v in before.items():
        now = h.node.get_parameter(p).value
        assert list(now) == list(v) if isinstance(v, (list, tuple)) or hasattr(v, 'tolist') \
            else now == v
    assert h.node.runner.scene.chains[0].length == pytest.approx(0.3)
    # Descriptions and ranges are declared.
    d = h.node.describe_parameter('ponytail.length')
    assert d.description and d.floating_point_range[0].from_value == pytest.approx(1e-4)
    d = h.node.describe_parameter('solver.max_steps_per_call')
    assert d.integer_range[0].from_value == 1 and not d.read_only
    assert h.node.describe_parameter('chains').read_only
    # An int for a double is accepted (no ".0" needed).
    assert set_remote(ponytail__drag_quadratic=1).successful
    assert h.node.get_parameter('ponytail.drag_quadratic').value == 1.0


def test_live_tuning_applies_on_next_tick_and_structural_change_rebuilds(harness):
    h = harness(overrides())
    h.head = still()
    got = h.poses['segment_poses']
    assert h.spin_until(lambda: len(got) >= 3, 5.0)
    node = h.node
    sim = node.runner.sim
    res = node.set_parameters([Parameter('ponytail.damping', value=2e-3),
                               Parameter('ponytail.stiffness', value=0.01),
                               Parameter('ponytail.drag_linear', value=0.3),
                               Parameter('wind', value=[2.0, 0.0, 0.0]),
                               Parameter('gravity', value=[0.0, 0.0, -3.0])])
    assert all(r.successful for r in res)
    n = len(got)
    assert h.spin_until(lambda: len(got) > n + 2, 2.0)
    m = node.runner.sim.model
    assert node.runner.sim is sim                           # tuned, not rebuilt
    assert np.all(m.damping == 2e-3) and np.all(m.stiffness == 0.01)
    assert np.all(m.drag_linear == 0.3)
    assert list(m.wind) == [2.0, 0.0, 0.0] and list(m.gravity) == [0.0, 0.0, -3.0]
    # Wind blows the chain towards +X.
    assert h.spin_until(lambda: arrays(got[-1])[0][-1][0] > arrays(got[n])[0][-1][0] + 0.01, 3.0)
    # Structural: more segments, the chain is rebuilt at rest at the current head pose.
    assert node.set_parameters([Parameter('ponytail.n_segments', value=9)])[0].successful
    assert h.spin_until(lambda: len(got[-1].poses) == 9, 2.0)
    check_geometry(got[-1], 9, 0.3)
    assert node.runner.resets['rebuild'] == 1
    # Rate: live.
    assert node.set_parameters([Parameter('rate', value=50.0)])[0].successful
    assert node._timer.timer_period_ns == 20_000_000


# -- time ------------------------------------------------------------------------------------

def test_use_sim_time_driven_by_clock(harness):
    h = harness(overrides(use_sim_time=True))
    clock_pub = h.clock_pub
    got = h.poses['segment_poses']
    r = h.node.runner
    h.spin_for(0.2)
    assert got == []                       # no /clock yet: no tick
    sent = []
    t = 1000.0

    def step(dt, head=True):
        nonlocal t
        t = round(t + dt, 6)
        clock_pub.publish(Clock(clock=stamp(t)))
        sent.append(t)
        if head:
            h.head_pub.publish(pose_msg(t))
        h.spin_for(0.01)
    for _ in range(60):
        step(0.01)
    assert h.spin_until(lambda: len(got) >= 20, 2.0)
    stamps = [t_of(m.header) for m in got]
    assert set(np.round(stamps, 6)) <= set(sent)        # every tick at a /clock time
    assert np.all(np.diff(stamps) > 0)
    check_geometry(got[-1], 6, 0.3)
    # /clock stops: so do the ticks.
    h.spin_for(0.1)
    n = len(got)
    h.spin_for(0.2)
    assert len(got) == n
    # A jump of 2 s: caught up to solver.max_steps_per_call (0.25 s), the rest dropped.
    assert h.spin_until(lambda: abs(r._last_tick - t) < 0.0095, 2.0)
    step(2.0)
    for _ in range(3):
        step(0.01)
    assert h.spin_until(lambda: r.dropped_time_total > 1.0, 2.0)
    assert r.dropped_time_total == pytest.approx(2.0 - 0.25, abs=0.03)
    # /clock restarts earlier (a looped bag): everything restarts, no stale history.
    # The bag plays on (up to 1 s of it) until the node ticks at its times: under load the
    # executor may take the first looped poses before the looped /clock (they are then
    # dropped as stamped backwards) and spin_for returns before every callback ran.
    t = 10.0
    for _ in range(100):
        step(0.01)
        if got and t_of(got[-1].header) < 100.0:
            break
    assert r.resets['clock_backwards'] == 1
    assert t_of(got[-1].header) < 100.0
    check_geometry(got[-1], 6, 0.3)


def test_timer_callback_receives_the_timer_info(ros_context):
    """``spin.timer_callback`` carries its signature so the executor need not rebuild it, and
    the executor still finds the ``TimerInfo`` parameter: the callback gets the timer's
    expected and actual call times (what the node's 'timer lateness' reports)."""
    import rclpy
    from rclpy.experimental import EventsExecutor
    from rclpy.timer import TimerInfo

    from ponytail_ros.ros.spin import timer_callback
    got = []
    node = rclpy.create_node('timer_info_check', context=ros_context)
    try:
        node.create_timer(0.01, timer_callback(got.append))
        executor = EventsExecutor(context=ros_context)      # the executables' executor
        executor.add_node(node)
        for _ in range(200):
            if got:
                break
            executor.spin_once(timeout_sec=0.05)
        assert got and isinstance(got[0], TimerInfo)
        assert got[0].actual_call_time.nanoseconds >= got[0].expected_call_time.nanoseconds
    finally:
        node.destroy_node()


def test_diagnostics_split_the_solve_time_into_the_compiled_stages(harness):
    """``/diagnostics`` carries the compiled step's stage means (``StepReport.timings``):
    with a skull collider both stages take time and fit within the solve time, and the
    contact stage's parts (rows, positions, velocities) within it; without colliders there
    is no contact stage."""
    from ponytail_ros.core.stages import HAS_CYCLE_COUNTER
    skull = overrides(colliders=['skull'], skull__kind='sphere', skull__radius=0.09,
                      skull__friction=0.3)
    for params, colliding in ((skull, True), (overrides(), False)):
        h = harness(params)
        h.head = still()
        assert h.spin_until(lambda h=h: len(h.poses['segment_poses']) >= 10, 5.0)
        d = h.fresh_diagnostics(3.0)
        integrate, contact = (float(d[k]) for k in ('integrate time mean (ms)',
                                                     'contact time mean (ms)'))
        parts = [float(d[f'contact {name} time mean (ms)'])
                 for name in ('rows', 'positions', 'velocities')]
        assert integrate > 0.0
        assert integrate + contact <= float(d['solve time mean (ms)'])
        # (each value is rounded to 0.001 ms: four roundings of at most 0.0005)
        assert sum(parts) <= contact + 0.002
        if not colliding:
            assert contact == 0.0 and parts == [0.0, 0.0, 0.0]
        elif HAS_CYCLE_COUNTER:
            # (positions not asserted: a resting chain may go a window without a position
            # pass, and its check alone rounds to 0.000 ms)
            assert contact > 0.0 and parts[0] > 0.0 and parts[2] > 0.0
        h.close()


def test_the_node_loads_its_scenes_kernels_before_the_first_head_pose(ros_context,
                                                                       monkeypatch):
    """The runner builds its Simulator at the first head pose; the kernels of its scene's
    stages are loaded when the node is built, so that first tick does not stall (and drop
    simulated time) loading them."""
    from ponytail_ros.core import compile as kernels
    from ponytail_ros.ros.node import PonytailNode
    monkeypatch.setattr(kernels, '_done', set())     # (as in a fresh process)
    node = PonytailNode(context=ros_context, parameter_overrides=overrides(
        colliders=['skull'], skull__kind='sphere', skull__radius=0.1))
    try:
        assert node.core.runner.sim is None                   # no head pose yet
        stages = kernels.stages_for(node.core.runner.scene)
        assert 'contact step' in stages
        assert set(stages) <= kernels._done
    finally:
        node.destroy_node()
