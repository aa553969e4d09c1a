"""One character: the ponytail node beside the built-in head animation, in one namespace.

    ros2 launch ponytail_ros ponytail.launch.py [namespace:=alice] [params_file:=...] [rviz:=true]

The head demo publishes ``<ns>/head_pose``; the node publishes ``<ns>/segment_poses``,
``<ns>/segment_markers``, ``/diagnostics`` and the segments on ``/tf`` as
``<ns>/<chain>/<i>``, children of ``world``. ``rviz:=true`` opens RViz with
``rviz/ponytail.rviz`` (made for the default namespace ``alice``).
"""
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription


def generate_launch_description():
    share = FindPackageShare('ponytail_ros')
    namespace = LaunchConfiguration('namespace')
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='alice',
                              description='the character: its topics and TF frames'),
        DeclareLaunchArgument('params_file',
                              default_value=PathJoinSubstitution([share, 'config',
                                                                  'ponytail.yaml']),
                              description='the node parameters (a scene of config/)'),
        DeclareLaunchArgument('rviz', default_value='false', description='open RViz'),
        Node(package='ponytail_ros', executable='ponytail_head_demo', name='head_demo',
             namespace=namespace, parameters=[{'rate': 100.0}], output='screen'),
        Node(package='ponytail_ros', executable='ponytail_node', name='ponytail',
             namespace=namespace, parameters=[LaunchConfiguration('params_file')],
             output='screen'),
        Node(package='rviz2', executable='rviz2', name='rviz2',
             arguments=['-d', PathJoinSubstitution([share, 'rviz', 'ponytail.rviz'])],
             condition=IfCondition(LaunchConfiguration('rviz'))),
    ])
