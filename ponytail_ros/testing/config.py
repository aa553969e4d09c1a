"""A node configuration outside a node: a params file plus overrides, completed and validated
exactly as ``PonytailNode`` declares them (``ponytail_ros.app.param_values``). Does not import
rclpy."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeAlias

from ponytail_ros.app.param_values import (
    complete_values,
    scene_and_settings,
    unknown_names,
    values_from_params_file,
)
from ponytail_ros.app.parameters import ParameterError, collider_names, frame_names, frame_topics
from ponytail_ros.app.runner import RunnerSettings
from ponytail_ros.core.scene import Scene

__all__ = ['Config', 'load_config', 'ParameterError']

PathLike: TypeAlias = str | Path


@dataclass(frozen=True)
class Config:
    """A complete, validated node parameter set.

    Attributes:
        values: every parameter of the node, name -> plain value (the node's view).
        params_file: where the values came from (None: defaults and overrides only).
        overrides: the overrides applied on top of the file, name -> value.
        chains: chain names, in the node's order (``segment_poses/<chain>`` topics).
        colliders: collider names, in the node's order.
        frames: extra kinematic frame names (``frames``), in the node's order.
        frame_topics: their pose topics (relative, ``<frame>.topic``), in that order.
        scene: the core ``Scene`` the node builds from the values.
        settings: the runner's input-handling settings.
    """

    values: dict[str, Any]
    params_file: Path | None
    overrides: dict[str, Any]
    chains: list[str]
    colliders: list[str]
    frames: list[str]
    frame_topics: list[str]
    scene: Scene
    settings: RunnerSettings

    @property
    def rate(self) -> float:
        """Tick rate, Hz (parameter ``rate``)."""
        return float(self.values['rate'])

    @property
    def pose_topics(self) -> list[str]:
        """The node's ``PoseArray`` topics (relative), one per chain, in chain order."""
        if len(self.chains) == 1:
            return ['segment_poses']
        return [f'segment_poses/{c}' for c in self.chains]

    def with_overrides(self, **overrides: Any) -> Config:
        """This configuration with more overrides (``'ponytail.damping'`` style names;
        ``__`` in a keyword stands for ``.``: ``ponytail__damping=2e-3``)."""
        merged = dict(self.overrides)
        merged.update({k.replace('__', '.'): v for k, v in overrides.items()})
        return load_config(self.params_file, merged)


def load_config(params_file: PathLike | None = None,
                overrides: Mapping[str, Any] | None = None,
                node_fqn: str = '/ponytail') -> Config:
    """The parameters a node named ``node_fqn`` would run with, given a ROS 2 params file
    (``/**: ros__parameters: ...``; None: the node's defaults) and ``overrides`` (dotted
    names, applied after the file, as ``-p name:=value`` would be).

    Raises:
        ParameterError: unreadable file, a value of the wrong type or out of range, an
            inconsistent scene, or an override that is not a parameter of this node; the
            message names the parameter.
    """
    path = Path(params_file) if params_file is not None else None
    partial: dict[str, Any] = values_from_params_file(path, node_fqn) if path is not None else {}
    extra = dict(overrides or {})
    partial.update(extra)
    unknown = [n for n in unknown_names(partial) if n in extra]
    if unknown:
        raise ParameterError(unknown[0], f'override {unknown[0]!r} is not a parameter of the '
                                         f'ponytail node with these chains/colliders/frames')
    values = complete_values(partial)
    chains, scene, settings = scene_and_settings(values)
    return Config(values=values, params_file=path, overrides=extra, chains=list(chains),
                  colliders=list(collider_names(values)), frames=list(frame_names(values)),
                  frame_topics=list(frame_topics(values)), scene=scene, settings=settings)
