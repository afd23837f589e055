"""Each drive's experiment and tuner start: the rule that carries the paper's set-up to
another motor and load (docs/drive-family.md).

Pure (no rclpy). ``drive_setup(drive, realism, model)`` is the seam the tuner and the study
share: the drive's config, its experiment (``ExperimentConfig`` with Ts/isq_max from the
drive) and its tuner parameters (box, start, satisfactory loss). The paper's 750 W motor
(``paper_750w``, the default) gives exactly today's ``ExperimentConfig()`` and packaged
``tuner.yaml``; every other drive is scaled from it by three ratios of the drive file's
constants to the paper file's (each exactly 1.0 for the paper's file):

* ``accel = (T_rated/J) / (T_rated/J)_paper``: the trajectory's ``a_max`` (600 rad/s^2 is
  0.6 T_rated/J for the paper: the move takes the same fraction of rated torque), and the
  weights a1, a2 divided by it (position and speed errors grow with the acceleration the
  move and the load step ask);
* ``torque = T_rated / T_rated_paper``: the load step (70 % of rated torque);
* ``current = (T_rated/Kt) / (T_rated/Kt)_paper``: the weight a3 divided by it (f3 is in
  amperes of torque current);
* ``inertia = (J/Kt) / (J/Kt)_paper``: k_pw and k_iw of the start, of the box and of the
  fallback gains multiplied by it (the speed loop's gain k_pw Kt/J and its integral
  corner k_iw/k_pw stay the paper's: the same loop bandwidths); k_pos, tau_sm, tau_eq,
  the thresholds and the satisfactory loss kept.

``v_max`` stays 40 rad/s, capped by the rated speed.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from im_controller.config import (
    GAIN_NAMES,
    ExperimentConfig,
    Gains,
    validate_experiment_config,
)
from im_drive_sim.family import DRIVE_NAMES, PACKAGED_NAMES
from im_drive_sim.params import DriveConfig, MachineParams, load_config

from .space import SearchSpace, TunerParams, load_params

__all__ = [
    'DRIVE_NAMES',
    'PACKAGED_NAMES',
    'DriveScales',
    'DriveSetup',
    'drive_scales',
    'drive_setup',
]

#: gains scaled with the drive's J/Kt (the speed loop's); the others are kept
_SPEED_LOOP_GAINS = ('k_pw', 'k_iw')


@dataclass(frozen=True)
class DriveSetup:
    """A drive and what the tuner does on it.

    name: the packaged drive's name, or the file path as given; drive: its config;
    experiment: its experiment (Ts, isq_max from the drive); params: its tuner parameters.
    """

    name: str
    drive: DriveConfig
    experiment: ExperimentConfig
    params: TunerParams


@dataclass(frozen=True)
class DriveScales:
    """The drive's ratios to the paper's file (each 1.0 for it; module docstring)."""

    accel: float  # [-] (T_rated/J) / paper's: a_max
    torque: float  # [-] T_rated / paper's: load step
    current: float  # [-] (T_rated/Kt) / paper's: weight a3
    inertia: float  # [-] (J/Kt) / paper's: k_pw, k_iw


@lru_cache(maxsize=1)
def _paper() -> MachineParams:
    return load_config(None).machine


def drive_scales(m: MachineParams) -> DriveScales:
    """The ratios of machine ``m`` to the paper's (written so each is exactly 1.0 for it)."""
    p = _paper()
    return DriveScales(
        accel=(m.rated_torque * p.J) / (m.J * p.rated_torque),
        torque=m.rated_torque / p.rated_torque,
        current=(m.rated_torque * p.Kt) / (m.Kt * p.rated_torque),
        inertia=(m.J * p.Kt) / (p.J * m.Kt),
    )


def _scaled(values: tuple[float, ...], inertia: float) -> tuple[float, ...]:
    return tuple(
        v * inertia if n in _SPEED_LOOP_GAINS else v
        for n, v in zip(GAIN_NAMES, values, strict=True)
    )


def experiment_for(drive: DriveConfig) -> ExperimentConfig:
    """The drive's experiment by the rule (module docstring); validated."""
    base = ExperimentConfig()
    m = drive.machine
    s = drive_scales(m)
    t, loss = base.trajectory, base.loss
    start = Gains(*_scaled(base.fallback_gains.as_tuple(), s.inertia))
    return validate_experiment_config(
        dataclasses.replace(
            base,
            control=dataclasses.replace(base.control, Ts=drive.Ts, isq_max=m.isq_max),
            trajectory=dataclasses.replace(
                t,
                a_max=t.a_max * s.accel,
                v_max=min(t.v_max, m.rated_speed),
                load_torque=t.load_torque * s.torque,
            ),
            loss=dataclasses.replace(
                loss, a1=loss.a1 / s.accel, a2=loss.a2 / s.accel, a3=loss.a3 / s.current
            ),
            fallback_gains=start,
        )
    )


def params_for(drive: DriveConfig, name: str) -> TunerParams:
    """The packaged tuner parameters with k_pw, k_iw (box and start) scaled to ``drive``."""
    base = load_params(None)
    k = drive_scales(drive.machine).inertia
    if k == 1.0:
        return base
    sp = base.space
    space = SearchSpace(_scaled(sp.lo, k), _scaled(sp.hi, k), _scaled(sp.start, k))
    return TunerParams(space, base.satisfactory_loss, f'{base.source} scaled for {name}')


def drive_setup(
    drive: str | Path | None = None, realism: str | None = None, model: str | None = None
) -> DriveSetup:
    """The setup of ``drive`` (a packaged name such as ``im3700w-j3``, a drive file's path,
    or None: the packaged default ``paper_750w``), with the realism profile ``realism``
    and the model ``model`` when given (None: the file's own). Raises ``ConfigError`` (a
    ``ValueError``, one line) for an unknown name or a bad file."""
    overrides: dict[str, str] = {}
    if realism is not None:
        overrides['realism'] = realism
    if model is not None:
        overrides['model'] = model
    cfg = load_config(drive, overrides=overrides or None)
    name = 'paper_750w' if drive is None else str(drive)
    return DriveSetup(name, cfg, experiment_for(cfg), params_for(cfg, name))
