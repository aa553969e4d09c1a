"""A head-only recording of the demo head script, stored as ``ros2 bag record -s mcap`` would
store it (``/head_pose``, ``geometry_msgs/msg/PoseStamped``): the input of the replay
benchmark (``replay_cost``) and of replay tests.
"""
from pathlib import Path

__all__ = ['INPUT_RATE', 'make_head_recording']

#: Head poses per second, Hz.
INPUT_RATE = 100.0


def make_head_recording(path, seconds, rate=INPUT_RATE, t0_ns=1_700_000_000_000_000_000):
    """A head-only recording of the demo head script (as ``ros2 bag record`` would store it)."""
    from geometry_msgs.msg import PoseStamped

    from ponytail_ros.app.head_script import HeadScript
    from ponytail_ros.recording.bag import BagWriter
    script = HeadScript()
    period_ns = int(round(1e9 / rate))
    msg = PoseStamped()
    msg.header.frame_id = 'world'
    with BagWriter(path, overwrite=True) as writer:
        writer.add_topic('/head_pose', PoseStamped)
        for k in range(int(seconds * rate)):
            t_ns = t0_ns + k * period_ns
            p, q = script.pose(k / rate)
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
            pos, ori = msg.pose.position, msg.pose.orientation
            pos.x, pos.y, pos.z = (float(v) for v in p)
            ori.x, ori.y, ori.z, ori.w = (float(v) for v in q)
            # received 0.5 ms after the stamp
            writer.write('/head_pose', msg, t_ns + 500_000)
    return Path(path)
