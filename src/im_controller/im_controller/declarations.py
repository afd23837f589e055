"""The controller's ROS parameters declared on its node: descriptors with units and ranges
(``config.NUMERIC_SPECS``), the structure read once at start (:class:`Structure`), the
tunables. What the parameters are is ``parameters`` (pure); this is the rclpy side.
"""

from __future__ import annotations

from dataclasses import dataclass

from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.node import Node

from im_drive_sim.contract import MODES
from im_drive_sim.drive_file import load_config
from im_drive_sim.params import ConfigError
from im_drive_sim.runtime import param_descriptor

from .config import GAIN_NAMES, MOVE_KEYS, MOVE_RULE, NUMERIC_SPECS, Gains
from .layout import INTERNALS_FIELDS
from .parameters import (
    DESCRIPTIONS,
    INT_PARAMETERS,
    READ_ONLY_SECTIONS,
    TUNABLE_SECTIONS,
    WRITABLE_INTS,
    ControllerError,
    check_choice,
    check_isq_max,
    section_defaults,
)


@dataclass(frozen=True)
class Structure:
    """What the node reads once at start (read-only parameters and the drive file)."""

    mode: str  #: 'lockstep' or 'realtime'
    lockstep_idle: str  #: 'pause' or 'hold'
    Ts: float  #: control period [s] (the drive file's)
    isq_max: float  #: the isq* clamp [A]
    state_timeout: float  #: the drive-state watchdog [s]
    tuner_timeout: float  #: the tuner watchdog [s] (0: off)
    internals_decimation: int
    service_period_steps: int
    timing_tolerance: int  #: [periods]
    first_experiment_id: int


def float_descriptor(key: str, text: str, read_only: bool) -> ParameterDescriptor:
    """The descriptor of a double parameter with a ``NUMERIC_SPECS`` range and unit."""
    sp = NUMERIC_SPECS[key]
    unit = f' [{sp.unit}]' if sp.unit else ''
    bounds = f'{"(" if sp.lo_strict else "["}{sp.lo:g}, {sp.hi:g}]'
    return param_descriptor(
        text + unit,
        param_type=ParameterType.PARAMETER_DOUBLE,
        read_only=read_only,
        additional=f'finite, in {bounds}' + (f'; {MOVE_RULE}' if key in MOVE_KEYS else ''),
        float_range=(sp.lo, sp.hi),
    )


def declare_sections(node: Node, sections: dict[str, type], read_only: bool) -> None:
    """Declare every field of ``sections`` (strings and doubles) as a parameter."""
    for key, value in section_defaults(sections):
        text = DESCRIPTIONS.get(key, key)
        if isinstance(value, str):
            desc = param_descriptor(text, read_only=read_only)
        else:
            desc = float_descriptor(key, text, read_only=read_only)
        node.declare_parameter(key, value, desc)


def declare_structure(node: Node) -> Structure:
    """Declare the read-only parameters and read them (ControllerError: a bad one)."""
    mode = node.declare_parameter(
        'mode',
        'lockstep',
        param_descriptor(
            "'lockstep' (simulation) or 'realtime' (a real or real-time drive)",
            additional='one of: lockstep, realtime',
        ),
    ).value
    mode = check_choice('mode', mode, MODES)
    lockstep_idle = node.declare_parameter(
        'lockstep_idle',
        'pause',
        param_descriptor(
            "lock-step, between experiments: 'pause' (sim time stops; "
            "reproducible) or 'hold' (keep stepping the position hold)",
            additional='one of: pause, hold',
        ),
    ).value
    lockstep_idle = check_choice('lockstep_idle', lockstep_idle, ('pause', 'hold'))
    drive_file = node.declare_parameter(
        'drive_config_file',
        '',
        param_descriptor(
            "the drive's parameter file, for Ts and isq_max ('' = the packaged 750 W default)"
        ),
    ).value
    try:
        drive_cfg = load_config(drive_file or None)
    except ConfigError as exc:
        raise ControllerError(str(exc)) from exc
    # Real time: a drive silent for 0.25 s (1250 periods) is gone.  Lock-step: the drive
    # only moves when answered, so a stall is not a hazard; the watchdog only finds a
    # dead drive. A killed recorder holds the drive's reliable writers until its 1 s DDS
    # lease runs out, which a loaded host stretches past 2 s: allow 10 s there.
    default_timeout = 0.25 if mode == 'realtime' else 10.0
    state_timeout = node.declare_parameter(
        'state_timeout',
        default_timeout,
        param_descriptor(
            'watchdog: no drive state for this long while one is expected -> '
            'zero current, running experiment aborted, FAULT [s]',
            param_type=ParameterType.PARAMETER_DOUBLE,
            float_range=(0.001, 60.0),
        ),
    ).value
    tuner_timeout = node.declare_parameter(
        'tuner_timeout',
        0.0,
        param_descriptor(
            'tuner watchdog: once a client (the tuner) sent a heartbeat on ~/heartbeat, none '
            'for this long -> zero current, running experiment aborted (tuner_lost), FAULT '
            'until ~/reset_fault [s]; 0: off (a drive host sets it: --tuner-timeout)',
            param_type=ParameterType.PARAMETER_DOUBLE,
            float_range=(0.0, 60.0),
        ),
    ).value
    ints = {
        name: node.declare_parameter(
            name,
            default,
            param_descriptor(text, int_range=bounds, read_only=name not in WRITABLE_INTS),
        ).value
        for name, (default, text, bounds) in INT_PARAMETERS.items()
    }
    node.declare_parameter(
        'internals_fields',
        list(INTERNALS_FIELDS),
        param_descriptor('layout of controller/internals data'),
    )
    declare_sections(node, READ_ONLY_SECTIONS, read_only=True)
    # The isq* clamp, read-only beside the other hard limits: the drive file's
    # machine.isq_max, or a tighter one set at start (a bench may want less current
    # than the drive can give); a looser one would be a lie the drive cannot keep.
    drive_isq_max = float(drive_cfg.machine.isq_max)
    isq_max = node.declare_parameter(
        'safety.isq_max',
        drive_isq_max,
        param_descriptor(
            "isq* clamp [A]: the drive file's machine.isq_max, or lower if set "
            'at start (a higher value is refused)',
            param_type=ParameterType.PARAMETER_DOUBLE,
            additional=f'finite, in (0, {drive_isq_max:g}] (the drive file)',
        ),
    ).value
    return Structure(
        mode=mode,
        lockstep_idle=lockstep_idle,
        Ts=float(drive_cfg.Ts),
        isq_max=check_isq_max(isq_max, drive_isq_max),
        state_timeout=state_timeout,
        tuner_timeout=float(tuner_timeout),
        **ints,
    )


def declare_tunables(node: Node) -> None:
    """Declare the gains and the tunable sections (loss, trajectory), not read-only."""
    g = Gains()
    for name in GAIN_NAMES:
        node.declare_parameter(
            name,
            float(getattr(g, name)),
            float_descriptor(f'gains.{name}', DESCRIPTIONS[name], read_only=False),
        )
    declare_sections(node, TUNABLE_SECTIONS, read_only=False)
