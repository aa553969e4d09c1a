"""pytest plugin of ponytail_ros: registered as the ``pytest11`` entry point
``ponytail_ros.testing.plugin``, so installing ponytail_ros (pip or colcon) is enough (or pass
``-p ponytail_ros.testing.plugin``).

Fixtures:

* ``ponytail`` — a factory ``ponytail(params=None, overrides=None, **harness_options) ->
  Harness``: the node in-process on its own isolated rclpy context, driven by sim time; every
  harness it made is closed after the test. ``params`` defaults to the ``ponytail_params``
  fixture.
* ``ponytail_params`` — the params file ``ponytail`` uses when given none (default None: the
  node's defaults); override it in a ``conftest.py`` or a test module.
* ``ponytail_offline`` — :func:`ponytail_ros.testing.run_offline` with the same default
  params: ``ponytail_offline(head, duration, params=None, **options) -> Trace`` (no ROS).

Nothing here imports rclpy until ``ponytail`` is used.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, TypeAlias

import pytest

from .motion import HeadInput
from .offline import run_offline
from .trace import Trace

ParamsArg: TypeAlias = str | Path | None


@pytest.fixture
def ponytail_params() -> ParamsArg:
    """The params file the ``ponytail`` fixtures use by default (None: node defaults)."""
    return None


@pytest.fixture
def ponytail(ponytail_params: ParamsArg) -> Iterator[Callable[..., Any]]:
    """Factory of :class:`ponytail_ros.testing.Harness` objects, closed after the test."""
    from .harness import Harness
    made: list[Harness] = []

    def make(params: ParamsArg = None, overrides: Mapping[str, Any] | None = None,
             **options: Any) -> Harness:
        h = Harness(params if params is not None else ponytail_params, overrides, **options)
        made.append(h)
        return h
    try:
        yield make
    finally:
        for h in made:
            h.close()


@pytest.fixture
def ponytail_offline(ponytail_params: ParamsArg) -> Callable[..., Trace]:
    """:func:`ponytail_ros.testing.run_offline` with ``params`` defaulting to
    ``ponytail_params``."""
    def run(head: HeadInput, duration: float, params: ParamsArg = None,
            **options: Any) -> Trace:
        return run_offline(params if params is not None else ponytail_params, head, duration,
                           **options)
    return run
