"""rosbag2's metadata in an MCAP file: the QoS profiles as the YAML rosbag2 writes
(``offered_qos_profiles``), its yaml-cpp block layout, and the names of the metadata records.
"""
from __future__ import annotations

from typing import Any

import yaml
from rclpy.qos import (
    QoSDurabilityPolicy,
    QoSHistoryPolicy,
    QoSLivelinessPolicy,
    QoSProfile,
    QoSReliabilityPolicy,
)

__all__ = ['PARAMETERS_METADATA']

#: Metadata record name for the parameters in effect during a recording (str -> str).
PARAMETERS_METADATA = 'ponytail_ros/parameters'
_ROSBAG2_RECORD = 'rosbag2'
_ROSBAG2_METADATA_VERSION = 9
# The PyPI wheels this package targets are Kilted builds and do not set ROS_DISTRO.
_DEFAULT_ROS_DISTRO = 'kilted'
_MAX_TIME_NS = 2**63 - 1  # rosbag2's "no message yet" starting time (nanoseconds::max())


class _YamlCppDumper(yaml.SafeDumper):
    """PyYAML emitting the block style of yaml-cpp, which rosbag2 uses.

    Sequences indented under their key, ``~`` for null, ``""`` for the empty string. Key order
    is the insertion order of the dicts, which follows rosbag2's encoders.
    """

    def increase_indent(self, flow=False, indentless=False):
        return super().increase_indent(flow, False)


_YamlCppDumper.add_representer(
    type(None), lambda dumper, _: dumper.represent_scalar('tag:yaml.org,2002:null', '~'))
_YamlCppDumper.add_representer(
    str, lambda dumper, value: dumper.represent_scalar(
        'tag:yaml.org,2002:str', value, style='"' if value == '' else None))


def _dump_yaml(data: Any) -> str:
    # yaml-cpp's Dump has no trailing newline; width=inf keeps long strings on one line.
    return yaml.dump(data, Dumper=_YamlCppDumper, sort_keys=False, default_flow_style=False,
                     width=float('inf')).rstrip('\n')


def _rmw_time(duration) -> dict:
    """An rclpy Duration as rmw_time_t ``{sec, nsec}`` (infinite -> 9223372036 s 854775807 ns)."""
    return {'sec': duration.nanoseconds // 10**9, 'nsec': duration.nanoseconds % 10**9}


def _qos_dict(qos: QoSProfile) -> dict:
    """One QoS profile as rosbag2 (metadata version 9) encodes it: policy names, rmw times."""
    return {
        'history': QoSHistoryPolicy(qos.history).short_key,
        'depth': qos.depth,
        'reliability': QoSReliabilityPolicy(qos.reliability).short_key,
        'durability': QoSDurabilityPolicy(qos.durability).short_key,
        'deadline': _rmw_time(qos.deadline),
        'lifespan': _rmw_time(qos.lifespan),
        'liveliness': QoSLivelinessPolicy(qos.liveliness).short_key,
        'liveliness_lease_duration': _rmw_time(qos.liveliness_lease_duration),
        'avoid_ros_namespace_conventions': qos.avoid_ros_namespace_conventions,
    }
