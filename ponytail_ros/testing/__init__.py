"""Test your own character with plain pytest: ``ponytail_ros.testing``.

* :func:`load_config` — a params file plus overrides, validated as the node does (no ROS);
* :func:`run_offline` — the node's core on a head motion in sim time, no rclpy (fast unit
  tests of a config);
* :class:`Harness` — the real ``PonytailNode`` in-process on a fresh, isolated rclpy context,
  driven by ``/clock`` (deterministic, faster than real time), collecting every ``PoseArray``,
  ``MarkerArray`` and ``/diagnostics`` message (imported on first use: needs rclpy);
* :mod:`~ponytail_ros.testing.checks` — assertions with readable failures: joints closed,
  penetration, joint limits, tip distance between runs, energy on a still head, no resets;
* the pytest plugin (:mod:`~ponytail_ros.testing.plugin`, registered as a ``pytest11`` entry
  point): fixtures ``ponytail`` (a harness factory) and ``ponytail_offline``.

Units SI, frames REP 103 (positions in the head poses' frame, quaternions ``(x, y, z, w)``).
"""
from typing import Any

from .checks import (
    CheckFailed,
    assert_energy_does_not_grow,
    assert_joints_closed,
    assert_no_penetration,
    assert_no_resets,
    assert_tips_close,
    assert_within_joint_limits,
    joint_gaps,
    max_penetration,
    tip_distance,
)
from .config import Config, ParameterError, load_config
from .motion import Motion, PoseSample, head_samples, sample_motion, still
from .offline import n_ticks, run_offline, tick_period_ns
from .trace import Reset, Trace

__all__ = ['BagSamples', 'CheckFailed', 'Config', 'Harness', 'HarnessError', 'HarnessTimeout',
           'Motion',
           'ParameterError', 'PoseSample', 'Reset', 'Trace', 'assert_energy_does_not_grow',
           'assert_joints_closed', 'assert_no_penetration', 'assert_no_resets',
           'assert_tips_close', 'assert_within_joint_limits', 'bag_samples', 'head_samples',
           'joint_gaps', 'load_config', 'max_penetration', 'n_ticks', 'run_offline',
           'sample_motion', 'still', 'tick_period_ns', 'tip_distance']

_LAZY = {'BagSamples', 'Harness', 'HarnessError', 'HarnessTimeout', 'bag_samples'}


def __getattr__(name: str) -> Any:
    # The ROS harness imports rclpy: only when asked for, so that the offline path and the
    # checks work without it.
    if name in _LAZY:
        from . import harness
        return getattr(harness, name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
