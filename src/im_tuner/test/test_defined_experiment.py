"""The defined experiment: the loss is a function of the gains alone, not of
how long the bench held between experiments.

Each experiment begins with a standstill settle (``trajectory.settle``, 0.5 s = 2500
periods on the drive's timeline, the fallback gains holding, no load, no loss). Measured
here on the pure core (the offline bench: the controller's kernel and the drive model):

* **the measurement noise** of the simulated bench: the standard deviation of 24 repeated
  measurements of the same gains, one experiment after another (directions alternating).
  The drive file has no noise source switched on; what varies is what the encoder (4096
  counts) cannot see -- where inside a count the rotor stands, how it creeps -- 0.05 % of
  the loss for the hand-tuned gains, 0.8 % for a fast set, 0.03 % for a slow one, 0.5 %
  near the stability edge;
* **the loss after a hold** of 0, 1, 45, 250 and 2500 periods after an experiment of the
  hand-tuned gains lies within 4 such standard deviations of their mean, for every set
  (at most 2.8 measured). Without the settle the hand-tuned loss read 1.1216 after a hold
  of 0 periods and 0.979 after 2500 (about 290 standard deviations apart): what the
  previous experiment left (its load removal, the integrator unwinding) reached the loss.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from im_controller.config import ExperimentConfig, Gains, TrajectoryConfig
from im_controller.runner import ExperimentRunner, config_for_drive
from im_drive_sim.drive_file import load_config
from im_drive_sim.sim import DriveSim
from im_tuner.offline import hold_offline, run_experiment_offline

GAINS = {
    'hand-tuned': Gains(),
    'fast': Gains(k_pw=0.9, k_iw=60.0, k_pos=45.0, tau_sm=0.003, tau_eq=0.004),
    'slow': Gains(k_pw=0.3, k_iw=8.0, k_pos=15.0, tau_sm=0.008, tau_eq=0.01),
    # k_pw 0.25 or k_pos 80 with these: the supervisor stops the experiment
    'near the stability edge': Gains(k_pw=0.3, k_iw=60.0, k_pos=60.0, tau_sm=0.0, tau_eq=0.0),
}
HOLDS = (0, 1, 45, 250, 2500)
CONFIG = load_config(None)


def _config(sim: DriveSim, settle: float | None) -> ExperimentConfig:
    cfg = config_for_drive(None, sim)
    if settle is None:
        return cfg
    return dataclasses.replace(cfg, trajectory=TrajectoryConfig(settle=settle))


def _after_hold(gains: Gains, hold: int, settle: float | None = None) -> float:
    """The loss of ``gains`` in the experiment that follows one of the hand-tuned gains
    and a hold of ``hold`` periods."""
    sim = DriveSim(CONFIG, seed=1)
    sim.reset(omega=0.0, fluxed=True)
    runner = ExperimentRunner(_config(sim, settle), Gains())
    runner.reset(sim.theta_meas)
    run_experiment_offline(sim, Gains(), runner.config, 0, runner, record=False)
    hold_offline(sim, runner, hold)
    return run_experiment_offline(sim, gains, runner.config, 1, runner, record=False)[0].loss


def _noise(gains: Gains) -> tuple[float, float]:
    """Mean and standard deviation of 24 repeated measurements of ``gains``: one
    experiment after another (directions alternating), each with its settle."""
    sim = DriveSim(CONFIG, seed=1)
    sim.reset(omega=0.0, fluxed=True)
    runner = ExperimentRunner(config_for_drive(None, sim), Gains())
    runner.reset(sim.theta_meas)
    run_experiment_offline(sim, Gains(), runner.config, 0, runner, record=False)
    losses = np.array(
        [
            run_experiment_offline(sim, gains, runner.config, i, runner, record=False)[0].loss
            for i in range(1, 25)
        ]
    )
    return float(losses.mean()), float(losses.std(ddof=1))


@pytest.mark.parametrize('name', list(GAINS))
def test_the_loss_does_not_depend_on_the_hold_before_the_experiment(name):
    gains = GAINS[name]
    mean, sd = _noise(gains)
    assert 0.0 < sd < 0.01 * mean  # 0.03-0.8 % of the loss
    losses = np.array([_after_hold(gains, h) for h in HOLDS])
    dev = np.abs(losses - mean) / sd
    assert dev.max() < 4.0, (name, mean, sd, losses.tolist(), dev.tolist())


def test_without_the_settle_the_loss_depends_on_the_hold():
    """The check above can fail: with ``settle`` 0 (the experiment as it was) the hold
    before it moves the hand-tuned loss by far more than the noise."""
    _mean, sd = _noise(Gains())
    losses = np.array([_after_hold(Gains(), h, settle=0.0) for h in HOLDS])
    assert losses[0] == pytest.approx(1.1216316257479648, rel=1e-9)
    assert losses[-1] < 0.985 and (losses.max() - losses.min()) > 100.0 * sd, losses
