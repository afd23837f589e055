"""Configuration of the cascaded position controller and of the loss experiment: frozen
dataclasses and the one place that validates them (docs/controller.md, section 7; each
field's meaning: ``parameters.DESCRIPTIONS``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np


class ControllerConfigError(ValueError):
    """An invalid controller / experiment parameter; the message names it and says why."""


GAIN_NAMES: tuple[str, ...] = ('k_pw', 'k_iw', 'k_pos', 'tau_sm', 'tau_eq')
"""Order of the tuned vector G = [k_pw, k_iw, k_pos, tau_sm, tau_eq] (paper eq. 8)."""

GAIN_UNITS: dict[str, str] = {
    'k_pw': 'A s/rad',
    'k_iw': 'A/rad',
    'k_pos': '1/s',
    'tau_sm': 's',
    'tau_eq': 's',
}

GAIN_RANGES: dict[str, tuple[float, float]] = {
    # Safe ranges accepted anywhere (node parameters, tuner candidates): the notes' search
    # box with margin and the packaged family's gains (docs/drive-family.md); values outside
    # are refused, never clipped silently.
    'k_pw': (0.0, 200.0),
    'k_iw': (0.0, 20000.0),
    'k_pos': (0.0, 300.0),
    'tau_sm': (0.0, 0.1),
    'tau_eq': (0.0, 0.1),
}


@dataclass(frozen=True)
class NumSpec:
    """Accepted values of one numeric parameter: [lo, hi] (or (lo, hi] if lo_strict)."""

    lo: float
    hi: float
    lo_strict: bool = False
    unit: str = ''


#: Every numeric parameter of the controller and the experiment, by ``section.field``:
#: the single source of truth for validation (``validate_*``) and for the ROS parameter
#: descriptors of the controller node.
NUMERIC_SPECS: dict[str, NumSpec] = {
    **{
        f'{section}.{n}': NumSpec(lo, hi, False, GAIN_UNITS[n])
        for section in ('gains', 'fallback_gains')
        for n, (lo, hi) in GAIN_RANGES.items()
    },
    'control.Ts': NumSpec(0.0, 0.01, True, 's'),
    'control.isq_max': NumSpec(0.0, 1e3, True, 'A'),
    'loss.a1': NumSpec(0.0, 1e6, False, '1/(rad s)'),
    'loss.a2': NumSpec(0.0, 1e6, False, '1/rad'),
    'loss.a3': NumSpec(0.0, 1e6, False, '1/(A s)'),
    'loss.threshold1': NumSpec(0.0, 1e12, True),
    'loss.threshold2': NumSpec(0.0, 1e12, True),
    'loss.threshold3': NumSpec(0.0, 1e12, True),
    'loss.penalty': NumSpec(1.0, 1e6),
    'loss.isqf_tau': NumSpec(0.0, 10.0, True, 's'),
    'loss.sat_ratio': NumSpec(0.0, 1.0, True),
    'trajectory.distance': NumSpec(0.0, 1e3, True, 'rad'),
    'trajectory.a_max': NumSpec(0.0, 1e6, True, 'rad/s^2'),
    'trajectory.v_max': NumSpec(0.0, 1e4, True, 'rad/s'),
    'trajectory.duration': NumSpec(0.0, 100.0, True, 's'),
    'trajectory.load_delay': NumSpec(0.0, 100.0, False, 's'),
    'trajectory.load_torque': NumSpec(0.0, 1e3, False, 'N m'),
    'trajectory.settle': NumSpec(0.0, 100.0, False, 's'),
    'safety.max_position_error': NumSpec(0.0, 1e3, True, 'rad'),
    'safety.max_speed': NumSpec(0.0, 1e4, True, 'rad/s'),
}


def _is_number(v: Any) -> bool:
    """True for int/float (and numpy scalars), False for bool, str and everything else."""
    if isinstance(v, (bool, np.bool_)):
        return False
    return isinstance(v, (int, float, np.integer, np.floating))


def _spec(key: str, name: str, v: Any) -> float:
    """Validate ``v`` against ``NUMERIC_SPECS[key]``; ``name`` is used in the message."""
    sp = NUMERIC_SPECS[key]
    bounds = f'({sp.lo:g}, {sp.hi:g}]' if sp.lo_strict else f'[{sp.lo:g}, {sp.hi:g}]'
    want = f'a finite number in {bounds}' + (f' {sp.unit}' if sp.unit else '')
    if not _is_number(v):
        raise ControllerConfigError(f'{name} must be {want}, got {v!r} (type {type(v).__name__})')
    x = float(v)
    if not math.isfinite(x) or (x <= sp.lo if sp.lo_strict else x < sp.lo) or x > sp.hi:
        raise ControllerConfigError(f'{name} must be {want}, got {v!r}')
    return x


def _choice(name: str, value: Any, choices: tuple[str, ...]) -> str:
    """``value`` if it is one of ``choices``; ``name`` is used in the message."""
    if not isinstance(value, str) or value not in choices:
        allowed = ' or '.join(repr(c) for c in choices)
        raise ControllerConfigError(f'{name} must be {allowed}, got {value!r}')
    return value


def _section(c: Any, cls: type, section: str, prefix: str, skip: str = '') -> dict[str, Any]:
    """The numeric fields of ``c`` (a ``cls``, ``NUMERIC_SPECS`` keys ``section.*``) but
    ``skip``, validated; ``prefix`` names them in the messages."""
    if not isinstance(c, cls):
        raise ControllerConfigError(f'{prefix} must be a {cls.__name__}, got {type(c).__name__}')
    return {
        f.name: _spec(f'{section}.{f.name}', f'{prefix}.{f.name}', getattr(c, f.name))
        for f in fields(cls)
        if f.name != skip
    }


@dataclass(frozen=True)
class Gains:
    """Tuned parameter vector G (paper eq. 8), in ``GAIN_NAMES`` order and ``GAIN_UNITS``;
    defaults = the notes' hand-tuned start."""

    k_pw: float = 0.53
    k_iw: float = 20.0
    k_pos: float = 30.0
    tau_sm: float = 0.005
    tau_eq: float = 0.007

    def as_tuple(self) -> tuple[float, ...]:
        return (self.k_pw, self.k_iw, self.k_pos, self.tau_sm, self.tau_eq)


def validate_gains(g: Any, prefix: str = 'gains') -> Gains:
    """Check every gain is a finite number inside ``GAIN_RANGES``; returns float-typed Gains."""
    if not isinstance(g, Gains):
        raise ControllerConfigError(f'{prefix} must be a Gains instance, got {type(g).__name__}')
    return Gains(**{n: _spec(f'gains.{n}', f'{prefix}.{n}', getattr(g, n)) for n in GAIN_NAMES})


@dataclass(frozen=True)
class ControlConfig:
    """Structure of the control law (not tuned; Ts and isq_max are the drive's)."""

    feedforward: str = 'model'
    Ts: float = 2e-4
    isq_max: float = 7.0


def validate_control_config(c: Any, prefix: str = 'control') -> ControlConfig:
    if not isinstance(c, ControlConfig):
        raise ControllerConfigError(f'{prefix} must be a ControlConfig, got {type(c).__name__}')
    feedforward = _choice(f'{prefix}.feedforward', c.feedforward, ('model', 'undelayed'))
    return ControlConfig(
        feedforward, **_section(c, ControlConfig, 'control', prefix, 'feedforward')
    )


@dataclass(frozen=True)
class LossConfig:
    """Loss eq. 4-7 (weights, the isq* filter, the saturation ratio) and the supervisor
    (thresholds, penalty): docs/controller.md, sections 4 and 5."""

    a1: float = 8.0
    a2: float = 0.5
    a3: float = 1.1
    threshold1: float = 3.0
    threshold2: float = 0.8
    threshold3: float = 1.5
    penalty: float = 10.0
    isqf_tau: float = 0.02
    sat_ratio: float = 0.99


def validate_loss_config(c: Any, prefix: str = 'loss') -> LossConfig:
    return LossConfig(**_section(c, LossConfig, 'loss', prefix))


@dataclass(frozen=True)
class TrajectoryConfig:
    """The experiment (paper, "The loss function", Fig. 5; docs/controller.md, section 3)."""

    distance: float = math.pi
    a_max: float = 600.0
    v_max: float = 40.0
    duration: float = 1.125
    load_delay: float = 0.7
    load_torque: float = 1.75
    load_sign: str = 'oppose_move'
    settle: float = 0.5


#: The parameters that set how long the move takes, and the rule they obey together
#: (checked by :func:`validate_experiment_config`, which knows Ts; the controller's
#: parameter descriptors say it).
MOVE_KEYS: tuple[str, ...] = (
    'trajectory.distance',
    'trajectory.a_max',
    'trajectory.v_max',
    'trajectory.duration',
)
MOVE_RULE = (
    'the move (distance under a_max and v_max, minimum time) must end by the '
    "experiment's last sample, duration - Ts"
)


def trajectory_times(
    distance: float, a_max: float, v_max: float
) -> tuple[float, float, float, float]:
    """Minimum-time rest-to-rest move under |a| <= a_max, |v| <= v_max: (t_acc, t_dec,
    t_end [s], v_peak [rad/s]), a triangle (t_acc = t_dec) when v_max is not reached."""
    if distance >= v_max * v_max / a_max:
        t_acc = v_max / a_max
        t_cruise = (distance - v_max * v_max / a_max) / v_max
        v_peak = v_max
    else:
        t_acc = math.sqrt(distance / a_max)
        t_cruise = 0.0
        v_peak = a_max * t_acc
    return t_acc, t_acc + t_cruise, 2.0 * t_acc + t_cruise, v_peak


def validate_trajectory_config(c: Any, prefix: str = 'trajectory') -> TrajectoryConfig:
    v = _section(c, TrajectoryConfig, 'trajectory', prefix, skip='load_sign')
    v['load_sign'] = _choice(f'{prefix}.load_sign', c.load_sign, ('oppose_move', 'fixed'))
    if v['load_delay'] > v['duration']:
        raise ControllerConfigError(
            f'{prefix}.load_delay must be <= duration ({v["duration"]:g} s), '
            f'got {v["load_delay"]!r}'
        )
    return TrajectoryConfig(**v)


@dataclass(frozen=True)
class SafetyConfig:
    """Hard limits, always active (in and between experiments); a violation -> FAULT."""

    max_position_error: float = 1.0
    max_speed: float = 100.0


@dataclass(frozen=True)
class ExperimentConfig:
    """Everything the experiment runner needs besides the gains under test
    (``fallback_gains``: they hold the settle and finish a stopped move)."""

    control: ControlConfig = field(default_factory=ControlConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    fallback_gains: Gains = field(default_factory=Gains)


def validate_experiment_config(c: Any) -> ExperimentConfig:
    """Validate all sections; returns a normalised (float-typed) copy."""
    if not isinstance(c, ExperimentConfig):
        raise ControllerConfigError(f'config must be an ExperimentConfig, got {type(c).__name__}')
    ctl = validate_control_config(c.control)
    traj = validate_trajectory_config(c.trajectory)
    for name in ('duration', 'settle'):
        steps = getattr(traj, name) / ctl.Ts
        if abs(steps - round(steps)) > 1e-9 * max(1.0, steps):
            raise ControllerConfigError(
                f'trajectory.{name} must be an integer number of control periods '
                f'(Ts = {ctl.Ts:g} s), got {getattr(traj, name)!r}'
            )
    # MOVE_RULE. The kernel samples t = n Ts, n = 0 .. N-1: the move reaches its end
    # (exactly `distance`) within the experiment only if it ends by (N-1) Ts.
    t_end = trajectory_times(traj.distance, traj.a_max, traj.v_max)[2]
    last = (round(traj.duration / ctl.Ts) - 1) * ctl.Ts
    if t_end > last * (1.0 + 1e-12):
        raise ControllerConfigError(
            f'trajectory: the move of {traj.distance:g} rad (a_max {traj.a_max:g} rad/s^2, '
            f'v_max {traj.v_max:g} rad/s) takes {t_end:.4g} s, longer than the experiment: '
            f'it must end by its last sample, trajectory.duration - Ts = {last:.6g} s '
            '(a shorter distance, a higher a_max or v_max, or a longer duration)'
        )
    return ExperimentConfig(
        ctl,
        validate_loss_config(c.loss),
        traj,
        SafetyConfig(**_section(c.safety, SafetyConfig, 'safety', 'safety')),
        validate_gains(c.fallback_gains, 'fallback_gains'),
    )
