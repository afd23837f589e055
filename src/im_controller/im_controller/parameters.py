"""The controller node's ROS parameters, pure: names, sections, defaults, descriptions,
the checks of the structure read at start, and :func:`configuration`, where parameter
values become the core configuration (``declarations`` declares them on the node).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

from . import config as cf
from .config import GAIN_NAMES, ExperimentConfig, Gains

#: Tunable sections: parameter prefix -> dataclass. Gains are top-level (k_pw, ...).
TUNABLE_SECTIONS = {'loss': cf.LossConfig, 'trajectory': cf.TrajectoryConfig}
#: Read-only sections (structure, hard safety limits, and the fallback gains that hold the
#: settle and finish a stopped move: a drive's own start, docs/drive-family.md).
READ_ONLY_SECTIONS = {
    'control': cf.ControlConfig,
    'safety': cf.SafetyConfig,
    'fallback_gains': Gains,
}
#: Fields taken from the drive's parameter file, not declared as parameters.
FROM_DRIVE = {'control.Ts', 'control.isq_max'}

#: the largest ``first_experiment_id`` (ids stay exact in every reader: JSON, float64)
MAX_EXPERIMENT_ID = 2**31 - 1

DESCRIPTIONS = {
    'k_pw': 'PI speed controller, proportional gain',
    'k_iw': 'PI speed controller, integral gain',
    'k_pos': 'proportional position gain',
    'tau_sm': 'reference smoothing time constant',
    'tau_eq': 'equivalent time constant of the position loop (reference model)',
    'loss.a1': 'weight of the position-error term f1 = |theta* - theta|',
    'loss.a2': 'weight of the speed-error term f2 = |omega* - omega|',
    'loss.a3': 'weight of the smoothness term f3 = |isqF* - isq*|',
    'loss.threshold1': 'supervisor: stop when the running weighted term 1 exceeds this',
    'loss.threshold2': 'supervisor: stop when the running weighted term 2 exceeds this',
    'loss.threshold3': 'supervisor: stop when the running weighted term 3 exceeds this',
    'loss.penalty': 'loss multiplier of a stopped experiment',
    'loss.isqf_tau': 'time constant of the isq* filter in f3 (paper: 0.02 s)',
    'loss.sat_ratio': 'terms count only while |isq*|/isq_max < sat_ratio (paper: 0.99)',
    'trajectory.distance': 'rotation per experiment (direction alternates)',
    'trajectory.a_max': 'acceleration limit of the minimum-time trajectory',
    'trajectory.v_max': 'speed limit of the minimum-time trajectory',
    'trajectory.duration': 'experiment length (1.125 s = 5625 steps)',
    'trajectory.load_delay': 'load step this long after the reference change',
    'trajectory.load_torque': 'load step magnitude (70 % of rated torque)',
    'trajectory.load_sign': "'oppose_move' or 'fixed'",
    'trajectory.settle': 'standstill settle before each experiment, fallback gains, no loss',
    'control.feedforward': "speed feed-forward reading: 'model' (d theta_m/dt) or 'undelayed'",
    'safety.max_position_error': 'hard limit on |theta_m - theta| (read-only)',
    'safety.max_speed': 'hard limit on |omega| (read-only)',
    **{
        f'fallback_gains.{n}': f'fallback {n}: holds the settle, finishes a stopped move '
        '(read-only; the hand-tuned start)'
        for n in GAIN_NAMES
    },
}

#: The integer parameters: name -> (default, description, range); read-only but for
#: :data:`WRITABLE_INTS`.
INT_PARAMETERS: dict[str, tuple[int, str, tuple[int, int]]] = {
    'internals_decimation': (
        1,
        'publish controller/internals every N answered states (1 = every step)',
        (1, 100000),
    ),
    'service_period_steps': (
        250,
        'serve services and parameters every N steps (and whenever idle)',
        (1, 1000000),
    ),
    'timing_tolerance': (
        0,
        'periods of an experiment (of its 5625 on the drive timeline) that may be held '
        "or late before its result is marked 'timing' (not the paper's timing: the "
        'tuner re-runs it). 0 on a simulated bench; a real bench whose power stage '
        'applies commands at period starts may need a few (docs/real-drive.md). '
        "Changes between experiments only (a tuner's --timing-tolerance auto raises it "
        'when its host gets louder)',
        (0, 1_000_000),
    ),
    'first_experiment_id': (
        0,
        'id of the first experiment this node starts; the next ones count up from '
        'it (an id names an experiment in its start answer and loss message, and '
        'its parity sets the move direction). A tuner resuming a run without '
        'replay sets it past the ids of the run, so that they stay unique in it',
        (0, MAX_EXPERIMENT_ID),
    ),
}


class ControllerError(Exception):
    """A start-up configuration error: one line, exit code 2."""


def section_defaults(sections: dict[str, type]) -> list[tuple[str, float | str]]:
    """(parameter name, default) of every field of ``sections`` that is a parameter
    (``FROM_DRIVE`` fields are not): strings as they are, numbers as floats."""
    defaults = ExperimentConfig()
    out: list[tuple[str, float | str]] = []
    for section, cls in sections.items():
        for f in dataclasses.fields(cls):
            key = f'{section}.{f.name}'
            if key in FROM_DRIVE:
                continue
            value = getattr(getattr(defaults, section), f.name)
            out.append((key, value if isinstance(value, str) else float(value)))
    return out


#: The integer parameters a client may change (between experiments): the timing
#: tolerance the next experiment is judged by.
WRITABLE_INTS = frozenset({'timing_tolerance'})


def is_tunable(name: str) -> bool:
    """A gain, an experiment parameter or the timing tolerance: changes only between
    experiments."""
    return name in GAIN_NAMES or name in WRITABLE_INTS or name.split('.', 1)[0] in TUNABLE_SECTIONS


def configuration(
    value: Callable[[str], object], Ts: float, isq_max: float
) -> tuple[ExperimentConfig, Gains]:
    """The validated configuration the parameters ``value(name)`` make, with the drive's
    ``Ts`` [s] and the ``isq_max`` clamp [A] (ControllerConfigError names a bad one)."""
    sections = {}
    for section, cls in {**TUNABLE_SECTIONS, **READ_ONLY_SECTIONS}.items():
        kw: dict[str, object] = {}
        for f in dataclasses.fields(cls):
            key = f'{section}.{f.name}'
            if key == 'control.Ts':
                kw[f.name] = Ts
            elif key == 'control.isq_max':
                kw[f.name] = isq_max
            else:
                kw[f.name] = value(key)
        sections[section] = cls(**kw)
    cfg = cf.validate_experiment_config(ExperimentConfig(**sections))
    gains = cf.validate_gains(Gains(*(value(n) for n in GAIN_NAMES)))  # type: ignore[arg-type]
    return cfg, gains


def check_choice(name: str, value: object, choices: tuple[str, ...]) -> str:
    """The string parameter ``name`` (``mode``, ``lockstep_idle``), one of ``choices``
    (ControllerError otherwise)."""
    if value not in choices:
        raise ControllerError(f"parameter '{name}' must be one of {choices}, got {value!r}")
    return str(value)


def check_isq_max(isq_max: object, drive_isq_max: float) -> float:
    """The ``safety.isq_max`` clamp [A]: in (0, the drive file's machine.isq_max]; only a
    tighter clamp can be set (ControllerError otherwise)."""
    if not (
        isinstance(isq_max, float) and math.isfinite(isq_max) and 0.0 < isq_max <= drive_isq_max
    ):
        raise ControllerError(
            f'parameter safety.isq_max must be in (0, {drive_isq_max:g}] A (the drive '
            f"file's machine.isq_max; only a tighter clamp can be set), got {isq_max!r}"
        )
    return isq_max
