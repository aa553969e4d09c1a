"""A crowd split over several ponytail nodes: one process per group of characters.

    ros2 launch ponytail_ros crowd.launch.py [groups:=2] [characters:=20] [first_group:=0]

Group ``g`` runs in the namespace ``crowd_<g>``: a head demo publishing ``characters`` heads
(``crowd_<g>/head_pose`` and ``crowd_<g>/frame_poses``) and one ponytail node simulating all of
them (its params: ``params_file`` copied per character, as ``python -m ponytail_ros.app.crowd``
writes them). Groups stand 2 m apart along Y, their characters 1 m apart along X. Segments
appear on ``/tf`` as ``crowd_<g>/<chain>_<k>/<i>``, children of ``world``.

One node's timer runs on one core; past what one core keeps at its rate (``python -m
ponytail_ros.bench.scale_out`` measures it), add groups. The nodes talk over the ROS 2 (DDS)
graph, so groups can run on several machines of one ``ROS_DOMAIN_ID``: launch
``groups:=2 first_group:=0`` on one and ``groups:=2 first_group:=2`` on another.
"""
import os
import tempfile

from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription

#: Distance between neighbouring groups, m, along world Y (characters spread along X).
GROUP_SPACING = 2.0


def crowd_groups(context):
    from ponytail_ros.app.crowd import crowd_values, params_file_text
    from ponytail_ros.app.param_values import values_from_params_file

    source = LaunchConfiguration('params_file').perform(context)
    groups = int(LaunchConfiguration('groups').perform(context))
    first = int(LaunchConfiguration('first_group').perform(context))
    characters = int(LaunchConfiguration('characters').perform(context))
    params = params_file_text(crowd_values(values_from_params_file(source), characters),
                              characters, source)
    folder = tempfile.mkdtemp(prefix='ponytail_crowd_')
    path = os.path.join(folder, 'crowd.yaml')
    with open(path, 'w') as f:
        f.write(params)
    actions = []
    for g in range(first, first + groups):
        namespace = f'crowd_{g}'
        actions += [
            Node(package='ponytail_ros', executable='ponytail_head_demo', name='head_demo',
                 namespace=namespace, parameters=[{
                     'rate': 100.0, 'characters': characters,
                     'origin': [0.0, g * GROUP_SPACING, 1.6]}]),
            Node(package='ponytail_ros', executable='ponytail_node', name='ponytail',
                 namespace=namespace, parameters=[path], output='screen'),
        ]
    return actions


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument('groups', default_value='2',
                              description='ponytail nodes (processes) on this machine'),
        DeclareLaunchArgument('characters', default_value='20',
                              description='characters per node'),
        DeclareLaunchArgument('first_group', default_value='0',
                              description='number of the first group (another machine: more)'),
        DeclareLaunchArgument('params_file',
                              default_value=PathJoinSubstitution([
                                  FindPackageShare('ponytail_ros'), 'config',
                                  'ponytail.yaml']),
                              description="one character's node parameters"),
        OpaqueFunction(function=crowd_groups),
    ])
