"""The benchmark's profiles: what ``--tiny``, ``--quick`` and ``--full`` run.

A profile is a dict of sizes (scenes and their durations, the settings swept, segment counts,
repeats, budgets) read by the commands; ``cli`` picks one and overrides ``--repeats`` and
``--scenes`` in a copy.
"""
from typing import Any

from .measure import Setting
from .scenes import SCENES

RK4, SE, RATTLE = 'rk4', 'symplectic_euler', 'rattle'
S = Setting
#: A profile's sizes (a copy of one of ``PROFILES``, with the command line's overrides).
Profile = dict[str, Any]


def _settings_quick() -> list[Setting]:
    return ([S(RK4, 1 / hz) for hz in (60, 120, 240, 480, 960)]
            + [S(SE, 1 / hz) for hz in (240, 960, 1920)]
            + [S(RATTLE, 1 / hz) for hz in (240, 480, 960)]
            + [S(RK4, 1 / 240, projection=False),
               S(RK4, 1 / 240, projection=False, baumgarte_stiffness=1e4, baumgarte_damping=200.0),
               S(RK4, 1 / 240, tick_rate=30.0), S(RK4, 1 / 240, tick_rate=60.0)])


def _settings_full() -> list[Setting]:
    return ([S(RK4, 1 / hz) for hz in (30, 60, 120, 240, 360, 480, 960, 2000)]
            + [S(SE, 1 / hz) for hz in (120, 240, 480, 960, 1920, 3840, 7680)]
            + [S(RATTLE, 1 / hz) for hz in (120, 240, 480, 960, 1920, 3840)]
            + [S(RK4, 1 / 240, projection=False), S(SE, 1 / 960, projection=False),
               S(RK4, 1 / 240, projection=False, baumgarte_stiffness=1e4, baumgarte_damping=200.0),
               S(RK4, 1 / 240, baumgarte_stiffness=1e4, baumgarte_damping=200.0),
               S(SE, 1 / 960, projection=False, baumgarte_stiffness=1e4, baumgarte_damping=200.0),
               S(RK4, 1 / 240, tick_rate=30.0), S(RK4, 1 / 240, tick_rate=60.0),
               S(RK4, 1 / 240, tick_rate=120.0), S(SE, 1 / 960, tick_rate=60.0)])


def _settings_tiny() -> list[Setting]:
    return [S(RK4, 1 / 240), S(SE, 1 / 480), S(RATTLE, 1 / 480),
            S(RK4, 1 / 240, tick_rate=60.0)]


#: name -> sizes; ``settings`` is a function (a fresh list per call).
PROFILES: dict[str, Profile] = {
    'tiny': dict(
        scenes=SCENES, durations=dict(moving=0.1, release=0.1, shake=0.1, rope=0.1, damped=0.1),
        dt_ref=1 / 1920, repeats=1, timing_window=0.05, settings=_settings_tiny,
        seg_counts=(3,), seg_settings=[S(RK4, 1 / 240)],
        scaling_n=(1, 3, 10), scaling_steps_budget=2e4, scaling_repeats=1,
        mujoco_n=(3,), mujoco_dts=(1 / 240, 1 / 960), mujoco_duration=0.1, mujoco_dt_ref=1 / 1920,
        mujoco_crosscheck_max=10, mujoco_scaling_max=10, mujoco_budget_s=5.0, long_run_s=0.5,
        batch_c=(1, 3), batch_segments=5, batch_steps=2, batch_loop_max=3, batch_repeats=1,
        energy_T=0.2, energy_settings=[S(RK4, 1 / 240), S(SE, 1 / 480), S(RATTLE, 1 / 480)],
        terms_seconds=0.05, terms_repeats=1),
    'quick': dict(
        scenes=SCENES, durations=dict(moving=3.0, release=1.5, shake=2.0, rope=1.5, damped=3.0),
        dt_ref=1 / 4000, repeats=3, timing_window=0.25, settings=_settings_quick,
        seg_counts=(), seg_settings=[],
        scaling_n=(1, 3, 10, 30, 100, 300, 1000), scaling_steps_budget=3e4,
        scaling_repeats=3,
        mujoco_n=(10, 50), mujoco_dts=(1 / 60, 1 / 240, 1 / 1000, 1 / 4000), mujoco_duration=3.0,
        mujoco_dt_ref=1 / 4000, mujoco_crosscheck_max=20, mujoco_scaling_max=100,
        mujoco_budget_s=5.0, long_run_s=30.0,
        batch_c=(1, 10, 100, 1000), batch_segments=20, batch_steps=6, batch_loop_max=100,
        batch_repeats=3,
        energy_T=10.0, energy_settings=[S(RK4, 1 / hz) for hz in (60, 120, 240, 480)]
        + [S(SE, 1 / hz) for hz in (240, 480, 960, 1920)]
        + [S(RATTLE, 1 / hz) for hz in (240, 480, 960, 1920)],
        terms_seconds=2.0, terms_repeats=3),
    'full': dict(
        scenes=SCENES + ('damped',),
        durations=dict(moving=3.0, release=1.9, shake=2.0, rope=2.0, damped=3.0),
        dt_ref=1 / 8000, repeats=5, timing_window=1.0, settings=_settings_full,
        seg_counts=(2, 5, 20, 40),
        seg_settings=[S(RK4, 1 / 240), S(RK4, 1 / 480), S(RK4, 1 / 960), S(SE, 1 / 960),
                      S(SE, 1 / 3840), S(RATTLE, 1 / 960)],
        scaling_n=(1, 2, 5, 10, 20, 50, 100, 200, 500, 1000),
        scaling_steps_budget=1e5, scaling_repeats=5,
        mujoco_n=(10, 20, 50, 100, 200), mujoco_dts=(1 / 60, 1 / 120, 1 / 240, 1 / 500, 1 / 1000,
                                                     1 / 2000, 1 / 4000),
        mujoco_duration=3.0, mujoco_dt_ref=1 / 8000, mujoco_crosscheck_max=50,
        mujoco_scaling_max=200, mujoco_budget_s=60.0, long_run_s=120.0,
        batch_c=(1, 10, 100, 1000), batch_segments=20, batch_steps=24, batch_loop_max=1000,
        batch_repeats=5,
        energy_T=10.0, energy_settings=[S(RK4, 1 / hz) for hz in (30, 60, 120, 240, 480, 960)]
        + [S(SE, 1 / hz) for hz in (120, 240, 480, 960, 1920, 3840)]
        + [S(RATTLE, 1 / hz) for hz in (120, 240, 480, 960, 1920, 3840)]
        + [S(RK4, 1 / 240, projection=False), S(SE, 1 / 960, projection=False)],
        terms_seconds=5.0, terms_repeats=5),
}
