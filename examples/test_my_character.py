"""Tests of my character's ponytail, with plain pytest and the installed ponytail_ros only:

    pip install '.[pypi]'               # from a clone (README: Install); brings the pytest
    pytest examples/                    #   plugin (fixtures ponytail, ponytail_offline)

``ponytail`` runs the real ponytail node in-process on an isolated ROS context, driven by sim
time; ``ponytail_offline`` runs the same node logic without ROS (faster, for tuning checks).
"""
from pathlib import Path

import pytest
from walk_cycle import walk, walk_then_stop

from ponytail_ros.testing import (
    assert_energy_does_not_grow,
    assert_joints_closed,
    assert_no_penetration,
    assert_no_resets,
    assert_tips_close,
)

PARAMS = Path(__file__).with_name('my_character.yaml')


@pytest.fixture
def ponytail_params():
    """The params file the ponytail fixtures use: my character's."""
    return PARAMS


def test_ponytail_stays_out_of_the_skull_while_walking(ponytail):
    run = ponytail().run(walk, duration=3.0)        # 3 s of sim time, ticks at 60 Hz
    # 180 ticks; the first waits for a third head pose (the chain starts moving with the head)
    assert run.n_ticks == 179
    # The first ticks show the chain in its reset pose (hanging through the skull) until the
    # first steps push it out: judge from 50 ms on. 1 mm allows the 0.2 mm sag of the first
    # segment's inner half, which the solver holds out only on its outer half.
    assert_no_penetration(run, max_depth=1e-3, since=0.05)
    assert_joints_closed(run, tolerance=1e-6)       # no stretch, root on the head
    assert_no_resets(run)                           # no guard reset: the step is fine enough


def test_ponytail_only_loses_energy_once_the_head_stops(ponytail_offline):
    run = ponytail_offline(walk_then_stop, duration=4.0)     # the walk stops at t = 2 s
    assert_energy_does_not_grow(run, tolerance=1e-6, since=2.2)


def test_more_damping_does_not_change_the_swing_much(ponytail_offline):
    reference = ponytail_offline(walk, duration=3.0)
    tuned = ponytail_offline(walk, duration=3.0, overrides={'ponytail.damping': 0.0012})
    assert_tips_close(tuned, reference, max_distance=5e-3, rms=2e-3)
