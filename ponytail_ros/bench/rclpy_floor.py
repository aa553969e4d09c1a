"""``python -m ponytail_ros.bench.rclpy_floor``: the least an rclpy node doing the ponytail
node's ROS work costs, with no simulation at all.

It subscribes to ``head_pose`` (``PoseStamped``, as bytes: ``raw=True``, as the node does) and,
on a wall-clock timer at ``rate`` Hz (``spin.timer_callback``, as the node's), publishes a
``PoseArray`` of ``n_poses`` poses on ``segment_poses`` as pre-serialised bytes (the node
publishes its CDR bytes raw), spun as ``ponytail_node`` is (``ros.spin``: the executor of
``PONYTAIL_EXECUTOR``, ``EventsExecutor`` by default). ``--objects`` uses message objects both
ways instead (what a plain rclpy node does). ``node_cpu --floor`` measures it beside the head
demo exactly as it measures the real node: the difference is what the simulation and its
bookkeeping cost, and the floor bounds what any Python node can reach on the machine.
"""
import argparse
import sys

__all__ = ['main']


def main(argv=None):
    import rclpy
    from geometry_msgs.msg import Pose, PoseArray, PoseStamped
    from rclpy.node import Node
    from rclpy.serialization import serialize_message

    from ponytail_ros.ros.spin import make_executor, spin_until_signal, timer_callback

    p = argparse.ArgumentParser(prog='python -m ponytail_ros.bench.rclpy_floor',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--rate', type=float, default=120.0, help='publish rate (Hz)')
    p.add_argument('--n-poses', type=int, default=12, help='poses per PoseArray')
    p.add_argument('--objects', action='store_true',
                   help='message objects in and out instead of bytes')
    args, ros_args = p.parse_known_args(sys.argv[1:] if argv is None else argv)
    rclpy.init(args=['floor', *ros_args])
    node = Node('rclpy_floor')
    last = [None]

    def on_head(msg):
        last[0] = msg                     # kept, as the node keeps its samples

    node.create_subscription(PoseStamped, 'head_pose', on_head, 10, raw=not args.objects)
    pub = node.create_publisher(PoseArray, 'segment_poses', 10)
    template = PoseArray()
    template.header.frame_id = 'world'
    template.poses = [Pose() for _ in range(args.n_poses)]
    wire = serialize_message(template)

    def tick(info=None):
        if not args.objects:
            pub.publish(wire)
            return
        msg = PoseArray()
        msg.header.stamp = node.get_clock().now().to_msg()
        msg.header.frame_id = 'world'
        msg.poses = [Pose() for _ in range(args.n_poses)]
        pub.publish(msg)

    node.create_timer(1.0 / args.rate, timer_callback(tick))
    try:
        spin_until_signal(make_executor(), node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
