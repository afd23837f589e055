"""``ros2 run im_tuner drive_host``: checks its command line before the node is imported."""

from __future__ import annotations

import argparse

from im_drive_sim import host, rt
from im_drive_sim.cli import (
    Parser,
    add_simulator_options,
    check_then_run,
    executable,
    finite_float,
)

from ..names import DEFAULT_TIMING_TOLERANCE
from ..record.live import add_live_options
from .drive_spec import drive_help
from .sim_bench_main import add_bag_options

DESCRIPTION = (
    "A drive on a computer of its own: the 5 kHz loop (the drive's period, the controller, "
    "the supervisor, the recorder's tap) in this process, on this computer. Tune it from "
    'any computer of the same ROS_DOMAIN_ID with `ros2 run im_tuner tuner --bench none` '
    '(docs/two-computers.md): only experiment-rate traffic crosses the network. Once a '
    'tuner sends heartbeats, none for --tuner-timeout brings the drive to zero current.'
)
#: [s] the default tuner watchdog: 10 heartbeats (contract.HEARTBEAT_PERIOD) missed
DEFAULT_TUNER_TIMEOUT = 1.0


def parser() -> argparse.ArgumentParser:
    ap = Parser(prog='ros2 run im_tuner drive_host', description=DESCRIPTION)
    ap.add_argument('--drive', metavar='DRIVE', default='sim', help=drive_help())
    add_simulator_options(
        ap,
        "the drive's parameters (the simulator's motor, your drive's Ts)",
        "the simulator's model fidelity (--drive sim)",
    )
    ap.add_argument(
        '--tuner-timeout',
        type=finite_float(0.05, 60.0, unit='s'),
        default=DEFAULT_TUNER_TIMEOUT,
        metavar='S',
        help='the tuner watchdog [s]: once a tuner sent a heartbeat (every 0.1 s), none for '
        'S -> zero current, a running experiment aborted (tuner_lost), FAULT until the '
        f'tuner comes back and clears it (default {DEFAULT_TUNER_TIMEOUT:g}; 0.05 to 60)',
    )
    ap.add_argument(
        '--timing-tolerance',
        type=host.tolerance_arg,
        default=DEFAULT_TIMING_TOLERANCE,
        metavar='N|auto',
        help='held or late periods an experiment may have and still count (default '
        f'{DEFAULT_TIMING_TOLERANCE}; docs/real-drive.md, "Timing tolerance"); auto: what a '
        f'2 s check of this host at start-up finds 95 %% of experiments meet, twice, at least '
        f'{DEFAULT_TIMING_TOLERANCE}. The check runs either way: a host that cannot meet N '
        'is told so in one line',
    )
    add_bag_options(ap, 'drive_host')
    add_live_options(ap)
    rt.add_arguments(ap, 'the 5 kHz loop', rt.DEFAULT_PRIORITY)
    return ap


def main() -> int:
    """The executable (``ros2 run``: :mod:`im_drive_sim.launch`)."""
    return check_then_run('drive_host', parser, 'im_tuner.bench.drive_host:main')


if __name__ == '__main__':
    executable('drive_host', main)
