"""``ros2 run im_tuner drive_host``: checks its command line before the node is imported."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from im_drive_sim.cli import check_then_run, drive_file, executable, finite_float

from ..benches import drive_help
from ..names import DEFAULT_TIMING_TOLERANCE
from ..record import live as _live
from ..tuner_args import OptionsParser, option
from .sim_bench_main import CONFIG_HELP, SimulatorOptions

#: [s] the default tuner watchdog: 10 heartbeats (contract.HEARTBEAT_PERIOD) missed
DEFAULT_TUNER_TIMEOUT = 1.0


@dataclass
class DriveHostOptions(SimulatorOptions):
    """drive_host's command line, typed (:mod:`..tuner_args`)."""

    PROG = 'ros2 run im_tuner drive_host'
    DESCRIPTION = (
        "A drive on a computer of its own: the 5 kHz loop (the drive's period, the "
        "controller, the supervisor, the recorder's tap) in this process, on this computer. "
        'Tune it from any computer of the same ROS_DOMAIN_ID with `ros2 run im_tuner tuner '
        '--bench none` (docs/two-computers.md): only experiment-rate traffic crosses the '
        'network. Once a tuner sends heartbeats, none for --tuner-timeout brings the drive '
        'to zero current.'
    )
    RT_WHAT = 'the 5 kHz loop'

    drive: str = option(drive_help(), None, 'sim', like='drive')
    drive_config: Path | None = option(
        CONFIG_HELP + "the drive's parameters (the simulator's motor, your drive's Ts)",
        {'type': drive_file},
        like='drive_config',
    )
    model: str | None = option("the simulator's model fidelity (--drive sim)", like='model')
    tuner_timeout: float = option(
        'the tuner watchdog [s]: once a tuner sent a heartbeat (every 0.1 s), none for S -> '
        'zero current, a running experiment aborted (tuner_lost), FAULT until the tuner '
        'comes back and clears it (0.05 to 60)',
        {'type': finite_float(0.05, 60.0, unit='s'), 'metavar': 'S'},
        DEFAULT_TUNER_TIMEOUT,
    )
    timing_tolerance: int | str = option(
        'held or late periods an experiment may have and still count (docs/real-drive.md, '
        '"Timing tolerance"); auto: what a 2 s check of this host at start-up finds 95 % of '
        f'experiments meet, twice, at least {DEFAULT_TIMING_TOLERANCE}. The check runs '
        'either way: a host that cannot meet N is told so in one line',
        None,
        DEFAULT_TIMING_TOLERANCE,
        like='timing_tolerance',
    )
    live: int | None = option(**_live.OPTIONS['--live'])
    live_host: str | None = option(**_live.OPTIONS['--live-host'])
    live_rate: float | None = option(**_live.OPTIONS['--live-rate'])
    thread_priority: int | None = option('', like='thread_priority')
    cpu_affinity: int = option('', like='cpu_affinity')
    lock_memory: bool = option('', like='lock_memory')


def parser() -> OptionsParser:
    return OptionsParser(DriveHostOptions)


def main() -> int:
    """The executable (``ros2 run``: :mod:`im_drive_sim.launch`)."""
    return check_then_run('drive_host', parser, 'im_tuner.bench.drive_host:main')


if __name__ == '__main__':
    executable('drive_host', main)
