"""The move must fit the experiment (config.MOVE_RULE): a distance, a_max, v_max or
duration for which the minimum-time move does not end by the experiment's last sample is
refused naming the move's time and the limit (found: ``-p trajectory.distance:=1000.0``,
a 25 s move in a 1.125 s experiment, was accepted)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from im_controller import trajectory as traj_module
from im_controller.config import (
    MOVE_KEYS,
    NUMERIC_SPECS,
    ControlConfig,
    ControllerConfigError,
    ExperimentConfig,
    TrajectoryConfig,
    trajectory_times,
    validate_experiment_config,
)
from im_controller.trajectory import trajectory

TS = 2e-4
LAST = 5624 * TS  # the last sample of the default 1.125 s experiment [s]


def _cfg(**traj) -> ExperimentConfig:
    return ExperimentConfig(trajectory=dataclasses.replace(TrajectoryConfig(), **traj))


def test_the_generator_and_the_check_use_one_formula():
    assert traj_module.trajectory_times is trajectory_times
    # the default move (docs/controller.md): 1/15 s up, 0.0119 s cruise, 0.1452 s in all
    t_acc, t_dec, t_end, v_peak = trajectory_times(math.pi, 600.0, 40.0)
    assert (t_acc, v_peak) == (pytest.approx(1 / 15), 40.0)
    assert t_dec - t_acc == pytest.approx(0.0119, abs=1e-4)
    assert t_end == pytest.approx(math.pi / 40 + 40 / 600, rel=1e-15)
    assert set(MOVE_KEYS) <= set(NUMERIC_SPECS)


@pytest.mark.parametrize(
    'change, t_move',
    [
        ({'distance': 1000.0}, 1000 / 40 + 40 / 600),  # the finding: 25.07 s
        ({'distance': 42.4}, 42.4 / 40 + 40 / 600),  # just over (1.1267 s)
        ({'a_max': 1.0}, 2 * math.sqrt(math.pi)),  # a triangle of 3.545 s
        ({'v_max': 2.0}, math.pi / 2 + 2 / 600),  # a slow cruise, 1.574 s
        ({'duration': 0.1, 'load_delay': 0.05}, math.pi / 40 + 40 / 600),  # 0.1452 > 0.0998
    ],
)
def test_a_move_longer_than_the_experiment_is_refused_naming_it(change, t_move):
    with pytest.raises(ControllerConfigError) as exc:
        validate_experiment_config(_cfg(**change))
    msg = str(exc.value)
    duration = change.get('duration', 1.125)
    last = (round(duration / TS) - 1) * TS
    assert msg.startswith('trajectory: the move of ')
    assert f'takes {t_move:.4g} s, longer than the experiment' in msg
    assert f'trajectory.duration - Ts = {last:.6g} s' in msg


def test_a_move_that_ends_on_the_last_sample_is_accepted_and_reaches_its_end():
    """The limit itself: distance such that the move ends exactly at (N-1) Ts (a
    trapezoid at 600 rad/s^2, 40 rad/s); the last sample of the reference is the whole
    distance. A hair longer is refused."""
    d = (LAST - 40 / 600) * 40
    cfg = validate_experiment_config(_cfg(distance=d))
    assert trajectory_times(d, 600.0, 40.0)[2] == pytest.approx(LAST, rel=1e-12)
    t = np.arange(5625) * TS
    pos, vel, _acc = trajectory(t, cfg)
    assert pos[-1] == pytest.approx(d, rel=1e-9) and vel[-1] == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(ControllerConfigError, match='longer than the experiment'):
        validate_experiment_config(_cfg(distance=d * (1 + 1e-6)))


def test_the_rule_depends_on_ts():
    """A slower control period makes the last sample earlier (duration - Ts)."""
    d = (LAST - 40 / 600) * 40  # fits at 200 us exactly
    ts = 1e-3  # 1125 samples, the last at 1.124 s
    with pytest.raises(ControllerConfigError, match=r'duration - Ts = 1\.124 s'):
        validate_experiment_config(
            ExperimentConfig(
                control=ControlConfig(Ts=ts),
                trajectory=dataclasses.replace(TrajectoryConfig(), distance=d),
            )
        )
