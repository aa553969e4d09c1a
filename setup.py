"""ament_python package setup for ponytail_ros.

Installs the same way under `colcon build` (dependencies from package.xml) and with pip into a
plain virtual environment (dependencies from the extras below: the ROS 2 Kilted PyPI wheels).
"""
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

package_name = 'ponytail_ros'
HERE = Path(__file__).resolve().parent

# The ROS 2 Kilted wheels on PyPI. rclpy needs an RMW implementation and does not pull one.
ROS_WHEELS = [
    'ros-rclpy',
    'ros-rmw-fastrtps-cpp',
    'ros-geometry-msgs',
    'ros-std-msgs',
    'ros-visualization-msgs',
    'ros-rosgraph-msgs',
    'ros-diagnostic-msgs',
]
# tf2_msgs (for /tf) is not among the wheels: interfaces/tf2_msgs builds it with the rosidl
# generators from PyPI, CMake and a C++ compiler (its build_backend.py); without a compiler the
# set-up still completes and `import tf2_msgs` fails cleanly (live TF off).
TF2_MSGS = 'ros-tf2-msgs @ ' + (HERE / 'interfaces' / 'tf2_msgs').as_uri()
# numba compiles the internal step (ponytail_ros.core.step); nopython, cache=True, no fastmath.
CORE = ['numpy>=1.24', 'scipy>=1.10', 'mcap>=1.1', 'PyYAML', 'numba>=0.60',
        'rosbags']  # rosbags: rosbag2's .db3 storage and zstd compression (bag folders)

setup(
    name=package_name,
    version='0.2.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        # Viewing and launching (RViz, Foxglove; `ros2 launch` in a ROS 2 install)
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/rviz', glob('rviz/*.rviz')),
        ('share/' + package_name + '/foxglove', glob('foxglove/*.json')),
    ],
    # Under colcon the dependencies come from package.xml (rosdep); install_requires stays minimal
    # so that a sourced workspace does not try to pull PyPI wheels over the system ROS install.
    install_requires=['setuptools'],
    extras_require={
        # tqdm: ponytail_replay's progress bar (a plain text line without it)
        'pypi': ROS_WHEELS + [TF2_MSGS] + CORE + ['tqdm'],
        'plot': ['matplotlib'],
        'test': ['pytest', 'pytest-xdist', 'hypothesis', 'rosbags', 'matplotlib', 'ruff', 'mypy'],
        'bench': ['mujoco'],
    },
    zip_safe=True,
    maintainer='ponytail_ros developers',
    maintainer_email='ponytail@example.com',
    description='Physically simulated ponytails, tails, ropes and swords for animated characters.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'ponytail_demo = ponytail_ros.entry_points:demo',
            'ponytail_node = ponytail_ros.entry_points:node',
            'ponytail_head_demo = ponytail_ros.ros.head_demo:main',
            'ponytail_replay = ponytail_ros.entry_points:replay',
            'ponytail_bench = ponytail_ros.bench.cli:main',
        ],
        # pytest plugin: the ponytail / ponytail_offline fixtures (ponytail_ros.testing). Named
        # after its module, so that "-p ponytail_ros.testing.plugin" and a conftest's
        # pytest_plugins find it registered instead of registering it a second time.
        'pytest11': [
            'ponytail_ros.testing.plugin = ponytail_ros.testing.plugin',
        ],
    },
)
