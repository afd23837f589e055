"""The parameters of the ``drive_sim`` node: names, defaults, descriptions, ranges.

All are read-only: they fix the structure of the simulation (model, mode, seed, machine
file) and are set at start with ``--ros-args -p name:=value`` (docs/interfaces.md).
:func:`declare_parameters` declares them on the node and checks what an rcl range cannot
say; the node (``drive_sim_node.DriveSimNode``) reads the values it returns. The example
drive declares those of the same names from here.
"""

from __future__ import annotations

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from .contract import COMMAND_FIELDS, MODES, STATE_FIELDS
from .params import ConfigError, DriveConfig
from .runtime import param_descriptor
from .sim import start_position


def parameter_specs() -> list[tuple[str, object, ParameterDescriptor]]:
    """(name, default, descriptor) of every parameter known before the drive file is read."""
    return [
        (
            'mode',
            'lockstep',
            param_descriptor(
                "'lockstep': one 200 us step per command received; 'realtime': paced at "
                '5 kHz by the wall clock, holding the last command.',
                additional='one of: lockstep, realtime',
            ),
        ),
        (
            'config_file',
            '',
            param_descriptor(
                'Drive parameter file (YAML, see share/im_drive_sim/config/paper_750w.yaml); '
                "'' = the packaged 750 W default."
            ),
        ),
        (
            'model',
            '',
            param_descriptor(
                "'full' (voltage-fed IM + vector control) or 'reduced' (ideal field "
                "orientation); '' = as in the parameter file.",
                additional="one of: '', full, reduced",
            ),
        ),
        (
            'command_delay',
            0,
            param_descriptor(
                'Command delay d [periods]: 1, the command answering state k acts over '
                'k -> k+1; 2, a power stage that latches it at the next period start '
                '(k+1 -> k+2); 0 = as in the parameter file (its command_delay, default 1).',
                int_range=(0, 2),
            ),
        ),
        (
            'seed',
            -1,
            param_descriptor(
                "Seed of the disturbance sources; -1 = the parameter file's seed.",
                int_range=(-1, 2**31 - 1),
            ),
        ),
        (
            'clock_decimation',
            25,
            param_descriptor(
                'Publish /clock every N steps (N = 25: every 5 ms of sim time).',
                int_range=(1, 100000),
            ),
        ),
        (
            'joint_state_decimation',
            10,
            param_descriptor('Publish drive/joint_states every N steps.', int_range=(1, 100000)),
        ),
        (
            'max_steps',
            0,
            param_descriptor(
                'Stop after this many steps (0 = run until shut down).', int_range=(0, 2**62)
            ),
        ),
        (
            'service_period_steps',
            250,
            param_descriptor(
                'Serve parameter requests every N steps (and whenever idle).',
                int_range=(1, 1000000),
            ),
        ),
        (
            'republish_period',
            0.1,
            param_descriptor(
                'Lock-step: re-send the current state after this long without a command '
                '[s], so a controller that starts later still gets it.',
                float_range=(0.001, 60.0),
            ),
        ),
        (
            'realtime_wait_for_controller',
            True,
            param_descriptor(
                'Real time: start the clock only once a controller publishes on '
                'drive/command (false: start at once and hold zero current).'
            ),
        ),
        (
            'realtime_spin_margin',
            150e-6,
            param_descriptor(
                'Real time: busy-wait this long before each period start instead of '
                'sleeping, for low jitter [s].',
                float_range=(0.0, 200e-6),
            ),
        ),
        (
            'command_timeout',
            0.05,
            param_descriptor(
                'Real time: watchdog -- no command for this long [s] -> zero current and no '
                'load until the next command (the safe state of a drive whose controller '
                'stopped).',
                float_range=(0.0002, 10.0),
            ),
        ),
        (
            'hardware_like',
            False,
            param_descriptor(
                'Real time: run on the wall clock like a power stage, which cannot pause. '
                'A period that starts m >= 1 whole periods late follows m periods that '
                'went by with the held command: the model runs them (unpublished), they '
                'count as held and missed, and the step index advances by them. '
                'false: the model pauses while the loop is late (simulated time waits).'
            ),
        ),
        (
            'test_stall_step',
            -1,
            param_descriptor(
                'Test hook: stall the loop once, in the first period that publishes this '
                'step index or a later one (-1: never), for test_stall_duration.',
                int_range=(-1, 2**62),
            ),
        ),
        (
            'test_stall_duration',
            0.02,
            param_descriptor(
                'Test hook: how long the stall at test_stall_step lasts [s].',
                float_range=(0.0, 10.0),
            ),
        ),
        (
            'state_fields',
            list(STATE_FIELDS),
            param_descriptor('Layout of drive/state data (read-only): field names in order.'),
        ),
        (
            'command_fields',
            list(COMMAND_FIELDS),
            param_descriptor('Layout of drive/command data (read-only): field names in order.'),
        ),
    ]


def declare_parameters(node: Node) -> dict:
    """Declare :func:`parameter_specs` on ``node``; returns name -> value. ConfigError for a
    ``mode`` or ``model`` outside its choices."""
    values = {}
    for name, default, desc in parameter_specs():
        values[name] = node.declare_parameter(name, default, desc).value
    if values['mode'] not in MODES:
        raise ConfigError(f"parameter 'mode' must be one of {MODES}, got {values['mode']!r}")
    if values['model'] not in ('', 'full', 'reduced'):
        raise ConfigError(
            f"parameter 'model' must be '', 'full' or 'reduced', got {values['model']!r}"
        )
    return values


def declare_initial_position(node: Node, config: DriveConfig) -> float:
    """Declare ``initial_position`` [rad] once the encoder is known: its default is half a
    count (``sim.start_position``); returns its value."""
    return node.declare_parameter(
        'initial_position',
        start_position(config),
        param_descriptor(
            'Rotor position at start [rad]; default half an encoder count (inside a '
            'count: no figure hinges on a round-off at a count edge).',
            float_range=(-1e6, 1e6),
        ),
    ).value
