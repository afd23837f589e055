"""The drives the tuner and the study know, by name: a drive's set-up in one call.

    drive_setup('paper_750w', realism='bench') -> DriveSetup(name, drive, experiment, params)

A MINIMAL stand-in (issue 29) until the family of packaged drives lands: it knows only
the paper's 750 W motor (``paper_750w``, the packaged default) and drive-file paths.
The seam, ``drive_setup(drive, realism, model) -> DriveSetup``, is the agreed one.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from im_controller.config import ExperimentConfig, validate_experiment_config
from im_drive_sim.params import REALISM_PROFILES, DriveConfig, load_config

from .space import TunerParams, load_params

__all__ = ['DEFAULT_DRIVE', 'DRIVES', 'DriveSetup', 'drive_setup']

#: The packaged default drive (today's bench, bit-identical).
DEFAULT_DRIVE = 'paper_750w'
#: Packaged drive names -> their drive file (None: im_drive_sim's packaged default).
DRIVES: dict[str, str | None] = {DEFAULT_DRIVE: None}


@dataclass(frozen=True)
class DriveSetup:
    """What one drive needs to be tuned or studied."""

    name: str  #: the packaged name, or the drive-file path given
    drive: DriveConfig
    experiment: ExperimentConfig  #: with Ts and isq_max from the drive
    params: TunerParams  #: search box, start gains, satisfactory loss


def drive_setup(
    drive: str | None = None, realism: str | None = None, model: str | None = None
) -> DriveSetup:
    """The set-up of ``drive`` (a packaged name, a drive-file path, None: the packaged
    default) on the realism profile ``realism`` (None: the file's own) and drive model
    ``model`` (None: the file's).  ValueError (one line) for an unknown name or profile."""
    if realism is not None and realism not in REALISM_PROFILES:
        raise ValueError(f'realism must be one of {", ".join(REALISM_PROFILES)}, got {realism!r}')
    name = DEFAULT_DRIVE if drive is None else drive
    if name in DRIVES:
        path: str | None = DRIVES[name]
    elif Path(name).suffix in ('.yaml', '.yml') or '/' in name or Path(name).is_file():
        path = name
    else:
        raise ValueError(
            f'unknown drive {name!r} (packaged: {", ".join(DRIVES)}; or a drive file path)'
        )
    overrides: dict[str, Any] = {}
    if realism is not None:
        overrides['realism'] = realism
    if model is not None:
        overrides['model'] = model
    cfg = load_config(path, overrides=overrides)
    base = ExperimentConfig()
    control = dataclasses.replace(
        base.control, Ts=float(cfg.Ts), isq_max=float(cfg.machine.isq_max)
    )
    experiment = validate_experiment_config(dataclasses.replace(base, control=control))
    return DriveSetup(name=name, drive=cfg, experiment=experiment, params=load_params())
