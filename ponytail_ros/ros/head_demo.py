"""``ponytail_head_demo``: publishes a scripted head pose for the ponytail node.

Run: ``ponytail_head_demo [--ros-args -p rate:=60.0 -p motion:=script -r __ns:=/alice]``.
Node name ``head_demo``; publishes ``head_pose`` (``geometry_msgs/PoseStamped``, reliable,
depth 10: a reliable publisher connects to the node's best-effort subscription) stamped with the
node clock (``use_sim_time`` works).

Parameters:
    rate (Hz, 1–2000, default 100): publish rate.
    frame_id (default 'world'): header.frame_id.
    motion: 'script' (``head_script.HeadScript``: idle sway, nod, shake, turn, run with bob,
        sharp stop; loops every 24 s), 'sway' (``SwayYawMotion``) or 'still'.
    origin (3 doubles, m, default [0, 0, 1.6]): where the head starts (moves the whole motion).
    time_scale (0.01–100, default 1): play speed of the motion.
    best_effort (default False): publish best effort instead of reliable.
    characters (1–1024, default 1): with more than 1, also publish ``frame_poses``
        (``geometry_msgs/PoseArray``, same QoS and stamp): the heads of characters 2..N, one
        pose each: the same motion started ``app.crowd.CHARACTER_PHASE`` s later per
        character, ``CHARACTER_SPACING`` m apart along X: the input of a node with
        ``frames_topic: frame_poses`` (``python -m ponytail_ros.app.crowd`` writes its params
        file).
    output: 'pose' (default: ``head_pose``), 'tf' (the head as a TF tree instead) or 'both'.
        The tree (``app/head_tree.py``): ``<frame_id> -> <tf.prefix>base_link`` (below the
        head on the ground, turned with its yaw; ``world`` for an empty ``frame_id``) and
        ``<tf.prefix>neck -> <tf.prefix>head`` on ``/tf`` every period;
        ``<tf.prefix>base_link -> <tf.prefix>neck`` (``neck_height`` m up) once on
        ``/tf_static`` (transient local). Composed, ``<frame_id> -> head`` is the
        ``head_pose`` pose, same stamp. Needs ``tf2_msgs`` (the set-up builds it). Only the
        first character's head is a tree (``frame_poses`` stays a topic).
    tf.prefix (default: the namespace, e.g. 'alice/' under /alice, '' at the root): prepended
        to the tree's frame names, as the ponytail node's segment frames.
    neck_height (m, 0-10, default 1.5): the static base_link -> neck offset.
The motion itself is ROS-free (``ponytail_ros/app/head_script.py``).
"""
import sys

import numpy as np
from geometry_msgs.msg import PoseArray, PoseStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from ponytail_ros.app.crowd import crowd_offsets
from ponytail_ros.app.head_script import HeadScript
from ponytail_ros.app.wire import pose_array_layout
from ponytail_ros.core.head import StillMotion, SwayYawMotion
from ponytail_ros.ros.spin import run_node

__all__ = ['HeadDemoNode', 'make_motion', 'main', 'namespace_prefix']

MOTIONS = ('script', 'sway', 'still')
OUTPUTS = ('pose', 'tf', 'both')
#: tf2's QoS: /tf keep last 100 (tf2_ros' broadcaster), /tf_static transient local keep last 1.
TF_STATIC_TOPIC = '/tf_static'


def make_motion(kind, origin=(0.0, 0.0, 1.6), time_scale=1.0):
    """The ``HeadMotion`` of a ``motion`` parameter value."""
    origin = np.asarray(origin, dtype=float)
    if kind == 'script':
        return HeadScript(origin=origin, time_scale=time_scale)
    if kind == 'sway':
        m = SwayYawMotion(p0=origin)
        if time_scale != 1.0:
            m.f *= time_scale
            m.fy *= time_scale
        return m
    if kind == 'still':
        return StillMotion(origin)
    raise ValueError(f'motion must be one of {MOTIONS}, not {kind!r}')


def namespace_prefix(namespace):
    """The TF frame prefix of a node namespace: '/alice' -> 'alice/', '/' -> ''."""
    ns = namespace.strip('/')
    return ns + '/' if ns else ''


def _tf_types():
    """``(TFMessage, TransformStamped)``, or a ValueError naming ``output`` when tf2_msgs is
    not importable."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError as err:
        raise ValueError(f'output needs tf2_msgs for a TF tree, and it is not importable '
                         f'({err}); the set-up (pip install -e .[pypi]) builds it with a C++ '
                         f'compiler, or use output:=pose') from None
    from geometry_msgs.msg import TransformStamped
    return TFMessage, TransformStamped


def _transform_msg(msg_type, parent, child, transform):
    msg = msg_type()
    msg.header.frame_id = parent
    msg.child_frame_id = child
    t, r = msg.transform.translation, msg.transform.rotation
    t.x, t.y, t.z = (float(v) for v in transform.translation)
    r.x, r.y, r.z, r.w = (float(v) for v in transform.rotation)
    return msg


def _pose(motion, t):
    """``(position (3,), orientation (4,))`` of ``motion`` at ``t`` (its ``pose`` when it has
    one: no derivatives needed)."""
    if hasattr(motion, 'pose'):
        return motion.pose(t)
    state = motion.state_at(t)
    return state.position[0], state.orientation[0]


class HeadDemoNode(Node):
    """Publishes ``head_pose`` from a scripted motion at ``rate``."""

    def __init__(self, node_name='head_demo', *, context=None, **kwargs):
        super().__init__(node_name, context=context, **kwargs)

        def rng(lo, hi, text):
            return ParameterDescriptor(description=text, floating_point_range=[
                FloatingPointRange(from_value=lo, to_value=hi, step=0.0)], read_only=True)
        rate = self.declare_parameter('rate', 100.0, rng(1.0, 2000.0, 'Publish rate, Hz.')).value
        self._frame = self.declare_parameter('frame_id', 'world', ParameterDescriptor(
            description='header.frame_id', read_only=True)).value
        kind = self.declare_parameter('motion', 'script', ParameterDescriptor(
            description='script, sway or still', additional_constraints='one of: ' +
            ', '.join(MOTIONS), read_only=True)).value
        origin = self.declare_parameter('origin', [0.0, 0.0, 1.6], ParameterDescriptor(
            description='Start position of the head, m', read_only=True)).value
        scale = self.declare_parameter('time_scale', 1.0,
                                       rng(0.01, 100.0, 'Play speed.')).value
        best_effort = self.declare_parameter('best_effort', False, ParameterDescriptor(
            description='Publish best effort instead of reliable', read_only=True)).value
        characters = self.declare_parameter('characters', 1, ParameterDescriptor(
            description='Characters: more than 1 also publishes frame_poses (PoseArray), the '
                        'heads of characters 2..N', integer_range=[
                IntegerRange(from_value=1, to_value=1024, step=1)], read_only=True)).value
        output = self.declare_parameter('output', 'pose', ParameterDescriptor(
            description='pose (head_pose), tf (a TF tree) or both', additional_constraints=
            'one of: ' + ', '.join(OUTPUTS), read_only=True)).value
        self._prefix = self.declare_parameter(
            'tf.prefix', namespace_prefix(self.get_namespace()), ParameterDescriptor(
                description='Prefix of the TF frame names (default: the namespace)',
                read_only=True)).value
        neck_height = self.declare_parameter('neck_height', 1.5, rng(
            0.0, 10.0, 'base_link -> neck height, m')).value
        if output not in OUTPUTS:
            raise ValueError(f'output = {output!r} is not one of: {", ".join(OUTPUTS)}')
        if kind not in MOTIONS:
            raise ValueError(f'motion = {kind!r} is not one of: {", ".join(MOTIONS)}')
        self.motion = make_motion(kind, list(origin), scale)
        qos = QoSProfile(depth=10, reliability=(ReliabilityPolicy.BEST_EFFORT if best_effort
                                                else ReliabilityPolicy.RELIABLE))
        self._pub = (self.create_publisher(PoseStamped, 'head_pose', qos)
                     if output != 'tf' else None)
        self._tf_pub = self._make_tf(neck_height) if output != 'pose' else None
        # The other characters' heads: offsets in space and time, one PoseArray (raw CDR).
        self._offsets = crowd_offsets(int(characters))[1:]
        self._frames_pub = (self.create_publisher(PoseArray, 'frame_poses', qos)
                            if len(self._offsets) else None)
        self._frames_layout = pose_array_layout(self._frame, len(self._offsets))
        self._t0 = None
        self._msg = PoseStamped()
        self._msg.header.frame_id = self._frame
        self.create_timer(1.0 / rate, self._on_timer)
        where = ([self._pub.topic_name] if self._pub else []) + (
            [f'/tf ({" -> ".join([self._tf_parent] + self._tree_frames)})'] if self._tf_pub
            else [])
        self.get_logger().info(f'Publishing {kind} head motion on {" and ".join(where)} at '
                               f'{rate:g} Hz in frame {self._frame!r}')

    def _make_tf(self, neck_height):
        """The /tf publisher (the tree's moving edges); /tf_static gets base_link -> neck now."""
        from rclpy.qos import DurabilityPolicy

        from ponytail_ros.app.head_tree import TREE_FRAMES, neck_transform
        from ponytail_ros.app.messages import TF_QOS_DEPTH, TF_TOPIC
        tf_message, transform_stamped = _tf_types()
        self._tf_types = tf_message, transform_stamped
        self._tree_frames = [self._prefix + f for f in TREE_FRAMES]
        # An empty frame_id is no TF frame: the tree hangs from 'world' then, the frame the
        # ponytail node takes empty head frames for (its fixed_frame default).
        self._tf_parent = self._frame or 'world'
        self._neck_height = float(neck_height)
        static_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._static_pub = self.create_publisher(tf_message, TF_STATIC_TOPIC, static_qos)
        base, neck, _ = self._tree_frames
        static = _transform_msg(transform_stamped, base, neck, neck_transform(neck_height))
        static.header.stamp = self.get_clock().now().to_msg()
        self._static_pub.publish(tf_message(transforms=[static]))
        return self.create_publisher(tf_message, TF_TOPIC, QoSProfile(depth=TF_QOS_DEPTH))

    def _publish_tree(self, stamp, p, q):
        from ponytail_ros.app.head_tree import head_tree
        tf_message, transform_stamped = self._tf_types
        tree = head_tree(p, q, self._neck_height)
        base, neck, head = self._tree_frames
        edges = [_transform_msg(transform_stamped, self._tf_parent, base, tree.base),
                 _transform_msg(transform_stamped, neck, head, tree.head)]
        for edge in edges:
            edge.header.stamp = stamp
        self._tf_pub.publish(tf_message(transforms=edges))

    def _on_timer(self):
        now = self.get_clock().now()
        if now.nanoseconds == 0:
            return
        t = now.nanoseconds * 1e-9
        if self._t0 is None:
            self._t0 = t
        state = self.motion.state_at(t - self._t0)
        p, q = state.position[0].tolist(), state.orientation[0].tolist()
        msg = self._msg
        msg.header.stamp = now.to_msg()
        pos, ori = msg.pose.position, msg.pose.orientation
        pos.x, pos.y, pos.z = p
        ori.x, ori.y, ori.z, ori.w = q
        if self._pub is not None:
            self._pub.publish(msg)
        if self._tf_pub is not None:
            self._publish_tree(msg.header.stamp, p, q)
        if self._frames_pub is not None:
            block = np.empty((len(self._offsets), 7))
            for k, (shift, delay) in enumerate(self._offsets):
                position, orientation = _pose(self.motion, t - self._t0 - delay)
                block[k, :3] = position + shift
                block[k, 3:] = orientation
            self._frames_pub.publish(self._frames_layout.encode(msg.header.stamp.sec,
                                                                msg.header.stamp.nanosec, block))


HELP = f"""usage: ponytail_head_demo [-h] [--ros-args -p rate:=60.0 -p motion:=script
                          -r __ns:=/alice]

{__doc__.split(chr(10), 1)[1].strip()}

Exit status: 0 on Ctrl-C/SIGTERM, 2 for invalid parameters (one line naming the parameter)."""


def main(args=None):
    """Entry point of ``ponytail_head_demo``; returns the exit code."""
    from rclpy.exceptions import ParameterException
    return run_node('ponytail_head_demo', HeadDemoNode, args,
                    bad_input=(ParameterException, ValueError), help_text=HELP)


if __name__ == '__main__':
    sys.exit(main())
