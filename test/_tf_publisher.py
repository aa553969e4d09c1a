"""A separate process for test_tf_live.py, plain rclpy + tf2_msgs (none of the package's code):
a body on TF, world -> base_link (moving), base_link -> neck (/tf_static), neck -> head
(moving), stamped with this process's clock at 100 Hz, and the same head composed by hand as a
PoseStamped on /bob/head_pose. Prints ``T0 <ns>`` (the motion's time origin) once it runs.

Motion (tau = (stamp - T0) s): base_link at (0.2 tau, 0.1, 1.0), yawed 0.3 rad; neck 0.4 m above
base_link, rolled 0.1 rad; head at (0.02, 0, 0.1 + 0.05 tau) in neck, pitched 0.2 rad: the head
moves along a straight line at constant orientation.
"""
import math
import sys

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped, TransformStamped
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage


def quat(axis, angle):
    a = np.asarray(axis, float) * math.sin(angle / 2)
    return np.array([a[0], a[1], a[2], math.cos(angle / 2)])


def qmul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz])


def rotate(q, v):
    qv = np.array([v[0], v[1], v[2], 0.0])
    return qmul(qmul(q, qv), q * np.array([-1, -1, -1, 1]))[:3]


Q_BASE, Q_NECK, Q_HEAD = quat([0, 0, 1], 0.3), quat([1, 0, 0], 0.1), quat([0, 1, 0], 0.2)
P_NECK = np.array([0.0, 0.0, 0.4])


def base(tau):
    return np.array([0.2 * tau, 0.1, 1.0]), Q_BASE


def head_in_neck(tau):
    return np.array([0.02, 0.0, 0.1 + 0.05 * tau]), Q_HEAD


def head_in_world(tau):
    pb, qb = base(tau)
    ph, qh = head_in_neck(tau)
    return pb + rotate(qb, P_NECK + rotate(Q_NECK, ph)), qmul(qmul(qb, Q_NECK), qh)


def transform(stamp, parent, child, p, q):
    t = TransformStamped()
    t.header.stamp, t.header.frame_id, t.child_frame_id = stamp, parent, child
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = map(
        float, p)
    (t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
     t.transform.rotation.w) = map(float, q)
    return t


def main():
    rclpy.init(args=sys.argv)
    node = rclpy.create_node('tf_body')
    tf = node.create_publisher(TFMessage, '/tf', QoSProfile(
        depth=100, reliability=ReliabilityPolicy.RELIABLE))
    static = node.create_publisher(TFMessage, '/tf_static', QoSProfile(
        depth=100, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    head = node.create_publisher(PoseStamped, '/bob/head_pose', 10)
    t0 = node.get_clock().now().nanoseconds
    static.publish(TFMessage(transforms=[transform(node.get_clock().now().to_msg(), 'base_link',
                                                   'neck', P_NECK, Q_NECK)]))

    def tick():
        now = node.get_clock().now()
        stamp, tau = now.to_msg(), (now.nanoseconds - t0) * 1e-9
        tf.publish(TFMessage(transforms=[transform(stamp, 'world', 'base_link', *base(tau))]))
        tf.publish(TFMessage(transforms=[transform(stamp, 'neck', 'head', *head_in_neck(tau))]))
        p, q = head_in_world(tau)
        msg = PoseStamped()
        msg.header.stamp, msg.header.frame_id = stamp, 'world'
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, p)
        (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
         msg.pose.orientation.w) = map(float, q)
        head.publish(msg)
    node.create_timer(0.01, tick)
    print(f'T0 {t0}', flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass


if __name__ == '__main__':
    main()
