"""The packaged family of drives: three induction motors x load-inertia ratios 1, 3, 10.

Pure (no rclpy, no YAML): the names, what each name is, and where its file lives. A drive
name is ``<motor>-j<ratio>`` (``im3700w-j3``: the 3.7 kW motor with a load of three times
its own inertia, J_total = J_motor (1 + ratio)); the motors' own files (``paper_750w``,
``im3700w``, ``im7500w``) are the ratio-1 drives under their file names. Every name is a
file in ``im_drive_sim/config`` (``<name>.yaml``); ``drive_file.load_config`` takes a name where
it takes a path. Sources, derivation and the rule of each drive's experiment:
docs/drive-family.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path


@dataclass(frozen=True)
class Motor:
    """One packaged motor.

    key: the name prefix (``im3700w``); file: its own drive file's name (ratio 1);
    rating_w [W]: rated output power; J_motor [kg m^2]: the motor's rotor inertia (the
    paper's 2.5e-3 is motor + load machine: J_motor = 2.5e-3/2 is an assumption, so that
    ``paper_750w`` is the ratio-1 drive unchanged); source: where the constants come from.
    """

    key: str
    file: str
    rating_w: float
    J_motor: float
    source: str


MOTORS: tuple[Motor, ...] = (
    Motor(
        'im750w',
        'paper_750w',
        750.0,
        1.25e-3,
        "the paper's 750 W nameplate; constants of the shared model notes",
    ),
    Motor(
        'im3700w',
        'im3700w',
        3730.0,
        0.0131,
        'MATLAB/Simscape Asynchronous Machine preset 5 HP 400 V 50 Hz (record IM_5HP_400V_50Hz '
        'of the LBNL Modelica Buildings library)',
    ),
    Motor(
        'im7500w',
        'im7500w',
        7460.0,
        0.0343,
        'MATLAB/Simscape Asynchronous Machine preset 10 HP 400 V 50 Hz (record '
        'IM_10HP_400V_50Hz of the LBNL Modelica Buildings library)',
    ),
)

#: Load-inertia ratios J_load/J_motor of each motor's drives.
RATIOS: tuple[int, ...] = (1, 3, 10)


def drive_name(motor: Motor, ratio: int) -> str:
    """``<motor key>-j<ratio>``, e.g. ``im3700w-j3``."""
    return f'{motor.key}-j{ratio}'


#: The nine drives (motor x ratio), in order of rating then ratio.
DRIVE_NAMES: tuple[str, ...] = tuple(drive_name(m, r) for m in MOTORS for r in RATIOS)
#: The motors' own files (the ratio-1 drives).
MOTOR_FILES: tuple[str, ...] = tuple(m.file for m in MOTORS)
#: Every name a drive file may be given by.
PACKAGED_NAMES: tuple[str, ...] = MOTOR_FILES + DRIVE_NAMES


def packaged_path(name: str) -> Path | None:
    """The file of the packaged drive ``name`` (a name of ``PACKAGED_NAMES``, in
    ``im_drive_sim/config``), else None."""
    if name not in PACKAGED_NAMES:
        return None
    return Path(str(resources.files('im_drive_sim').joinpath('config', f'{name}.yaml')))


def motor_and_ratio(name: str) -> tuple[Motor, int] | None:
    """The motor and load-inertia ratio of the packaged drive ``name`` (a motor's own file:
    ratio 1), else None."""
    for m in MOTORS:
        if name == m.file:
            return m, 1
        for r in RATIOS:
            if name == drive_name(m, r):
                return m, r
    return None


def unknown_drive_message(name: str) -> str:
    """One line: ``name`` is neither a file nor a packaged drive; the names there are."""
    return (
        f'{name}: no such drive file, and not a packaged drive '
        f'(packaged: {", ".join(PACKAGED_NAMES)})'
    )
