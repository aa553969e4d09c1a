"""The head input the ROS users' bags carry (``docs/head_input.md``): stamps at any epoch,
sparse streams, gaps. ``ChainRunner`` driven through its integer-ns entry points, as the node
and the replay drive it."""
import numpy as np
import pytest

from ponytail_ros.app.runner import SPARSE_RATE, ChainRunner, RunnerSettings
from ponytail_ros.bench.pose_bench import RunAndTurn
from ponytail_ros.core import ChainSpec, Scene, SwayYawMotion
from ponytail_ros.core.rotations import quat_axis_x

SEGMENTS, LENGTH = 8, 0.3
#: A wall-clock epoch (a bag recorded on a machine's clock) and a simulator's.
WALL_NS, SIM_NS = 1_700_000_000_000_000_000, 100_000_000_000


def scene():
    return Scene(chains=(ChainSpec(name='ponytail', n_segments=SEGMENTS, length=LENGTH,
                                   mass=0.1, radius=0.03, attach=(-0.09, 0.0, 0.06),
                                   damping=1e-3, drag_linear=0.02),))


def run(motion, rate, t_end, *, epoch_ns=SIM_NS, tick=100.0, gap=None, hold=False,
        settings=None):
    """Poses of ``motion`` at ``rate`` Hz stamped ``epoch_ns + t`` (integer ns), ticks at
    ``tick`` Hz over ``(0, t_end)``; with ``gap`` ``(a, b)`` s no pose stamped in it (or, with
    ``hold``, the last pose before it repeated at the rate: the head held). Returns the runner,
    its outputs and its notices."""
    r = ChainRunner(scene(), settings or RunnerSettings())
    notices = []
    r.on_notice = lambda key, text: notices.append((key, text))
    outs, kp, kt, held = [], 0, 1, None
    while kt / tick < t_end:
        t_tick = kt / tick
        while kp / rate <= t_tick:
            tp = kp / rate
            s = motion.state_at(tp)
            pose = (s.position[0], s.orientation[0])
            if gap is not None and gap[0] <= tp < gap[1]:
                pose = held if hold else None
            else:
                held = pose
            if pose is not None:
                r.push(r.seconds(epoch_ns + round(tp * 1e9)), *pose, 'world')
            kp += 1
        out = r.tick_ns(epoch_ns + round(t_tick * 1e9))
        if out is not None:
            outs.append(out)
        kt += 1
    return r, outs, notices


def track(outs):
    """Times (runner s), tips and roots (m) of the outputs."""
    t = np.array([o.t for o in outs])
    tips = np.array([o.origins[-1] + quat_axis_x(o.orientations[-1:])[0] * LENGTH / SEGMENTS
                     for o in outs])
    return t, tips, np.array([o.origins[0] for o in outs])


def speeds(t, x):
    return np.linalg.norm(np.diff(x, axis=0), axis=1) / np.diff(t)


@pytest.mark.parametrize('rate', [120.0, 1000.0])
def test_the_chain_is_the_same_whatever_the_epoch_of_the_stamps(rate):
    """The same motion stamped from 100 s (a simulator clock) and from 1.7e9 s (a wall clock):
    float seconds at 1.7e9 s resolve only 2.4e-7 s, which the fit's derivatives amplify; the
    runner differences the integer ns first, so the chain is the same to 1e-9 m."""
    motion = SwayYawMotion()
    _, sim, _ = run(motion, rate, 1.0, epoch_ns=SIM_NS)
    _, wall, _ = run(motion, rate, 1.0, epoch_ns=WALL_NS)
    assert len(sim) == len(wall) > 80
    worst = max(float(np.abs(a.origins - b.origins).max()) for a, b in zip(sim, wall, strict=True))
    assert worst <= 1e-9
    assert [o.t for o in sim] == [o.t for o in wall]


def test_a_sparse_stream_is_said_once_never_teleports_and_keeps_the_root_on_the_head():
    """A running head (3 m/s, turning 3 rad/s) exported at 5 Hz: 0.6 m and 0.6 rad between
    poses, beyond ``teleport_distance`` (0.5 m) per pose but far below it per 1/28 s. Said
    once with the measured rate; no reset; the published root moves with the head (no latency
    compensation extrapolating a period ahead: it would freeze, then jump)."""
    motion = RunAndTurn(speed=3.0, rate=3.0)
    r, outs, notices = run(motion, 5.0, 4.0)
    assert [k for k, _ in notices] == ['sparse']
    assert '5.0 Hz' in notices[0][1] and f'{SPARSE_RATE:g} Hz' in notices[0][1]
    assert r.head_sparse and sum(r.resets.values()) == 0
    t, _, roots = track(outs)
    # The attachment point moves at |v + ω × r| ≤ 3 + 3 · 0.108 m/s; a 5 % margin covers the
    # fit's error through poses 0.2 s apart.
    v_root = speeds(t, roots)
    assert v_root.max() <= 1.05 * (3.0 + 3.0 * np.hypot(0.09, 0.06))
    assert np.percentile(v_root, 5) > 0.5 * 3.0                 # never frozen


def test_a_real_jump_of_a_sparse_stream_is_still_a_teleport():
    motion = RunAndTurn(speed=1.0, rate=0.5, t_jump=2.0, jump=(5.0, 0.0, 0.0))
    r, _, _ = run(motion, 5.0, 3.0)
    assert r.resets['teleport'] == 1


def test_a_dense_stream_is_not_called_sparse():
    r, _, notices = run(SwayYawMotion(), 30.0, 1.0)
    assert not r.head_sparse and notices == []


@pytest.mark.parametrize('start', [2.0, 2.55])
def test_a_gap_is_said_with_its_times_and_the_chain_resumes_as_from_a_held_head(start):
    """A 10 s hole in a 120 Hz stream of the reference head (whose sway and yaw repeat every
    10 s, so the head resumes where and as it stopped). The reference is the same run with the
    last pose repeated across the hole: the head held, as a physical fact. In the 0.3 s after
    the resume (the new history's start, two input periods of delay, the chain's response)
    the tip is no faster than there (a fit extrapolated backwards before the new history's
    first stamp, or a hold at the braked extrapolation instead of the last pose, whipped it
    beyond that). Margin 10 %: before the resume the two runs differ by the braking and the
    return in the hole's first 0.6 s, whose swing has not died out after 10 s of this light
    damping: the tip still moves at a few tenths of a m/s, differently in the two runs, a
    tenth of the resumed peak."""
    motion = SwayYawMotion()
    gap = (start, start + 10.0)
    r, outs, notices = run(motion, 120.0, start + 11.0, gap=gap, epoch_ns=WALL_NS)
    _, held, _ = run(motion, 120.0, start + 11.0, gap=gap, hold=True, epoch_ns=WALL_NS)
    assert [k for k, _ in notices] == ['gap'] and r.gaps == 1
    stamps = [k / 120.0 for k in range(int(14 * 120))]
    last = max(t for t in stamps if t < gap[0])
    first = min(t for t in stamps if t >= gap[1])
    text = notices[0][1]
    for t in (last, first):
        assert f'{WALL_NS * 1e-9 + round(t * 1e9) * 1e-9:.3f} s' in text, text
    assert f'gap of {first - last:.3f} s' in text
    assert sum(r.resets.values()) == 0
    after = []
    for o in (outs, held):
        t, tips, _ = track(o)
        v = speeds(t, tips)
        after.append(v[(t[1:] > first) & (t[1:] <= first + 0.3)].max())
    assert after[0] <= 1.1 * after[1]


def test_the_node_says_a_sparse_stream_once_and_gaps_with_their_stamps_throttled():
    """``NodeCore`` (the node's and the replay's logic) fed ``header.stamp``s at a wall-clock
    epoch: a 10 Hz stream is said sparse once; of three gaps 5 s apart the first is said with
    its stamps, the second is held back (one notice per 10 s of node clock), the third is said
    with the count of the one held back."""
    from builtin_interfaces.msg import Time

    from ponytail_ros.app.node_core import NodeCore
    from ponytail_ros.app.param_values import complete_values
    core = NodeCore(complete_values({'chains': ['ponytail'], 'markers': {'style': 'off'}}))
    said = []
    core.on_notice = lambda key, text: said.append((key, text))
    motion = SwayYawMotion()
    holes = [(2.0, 3.0), (7.0, 8.0), (12.5, 13.5)]
    for k in range(int(16.0 * 100)):                 # ticks at 100 Hz, poses at 10 Hz
        t_ns = WALL_NS + k * 10_000_000
        if k % 10 == 0 and not any(a <= k / 100 < b for a, b in holes):
            s = motion.state_at(k / 100)
            core.push_head(Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9), t_ns,
                           tuple(s.position[0]), tuple(s.orientation[0]), 'world')
        core.tick(t_ns)
    assert [k for k, _ in said] == ['sparse', 'gap', 'gap']
    assert '10.0 Hz' in said[0][1]
    assert '1700000001.900 s to 1700000003.000 s' in said[1][1]
    assert '1700000012.400 s to 1700000013.500 s' in said[2][1]
    assert '1 more since the last such notice' in said[2][1]
    assert core.runner.gaps == 3 and sum(core.runner.resets.values()) == 0
