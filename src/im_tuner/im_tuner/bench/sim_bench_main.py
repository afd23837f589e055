"""``ros2 run im_tuner sim_bench``: checks its command line before the node is imported."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from im_drive_sim.cli import Parser, add_simulator_options, check_then_run, executable

DESCRIPTION = (
    'The simulated bench: drive_sim + controller, lock-step. Start experiments with '
    '/controller/start_experiment (std_srvs/Trigger); results on /controller/loss.'
)
#: the bag's options: (flag, argparse keywords)
BAG_OPTIONS: tuple[tuple[str, dict[str, Any]], ...] = (
    (
        '--no-record',
        {
            'action': 'store_true',
            'help': 'do not record (default: all traffic to a bag, see --out); refused '
            'with --out or --compression, which would be ignored',
        },
    ),
    (
        '--out',
        {
            'metavar': 'DIR',
            'type': Path,
            'help': 'bag directory to create (default: bags/{prog}_<UTC time>)',
        },
    ),
    (
        '--compression',
        {
            'choices': ('none', 'zstd', 'lz4'),
            'help': 'MCAP chunk compression of the bag (default: lz4; zstd: smaller files)',
        },
    ),
)


def parser() -> argparse.ArgumentParser:
    ap = Parser(prog='ros2 run im_tuner sim_bench', description=DESCRIPTION)
    ap.add_argument(
        '--processes',
        action='store_true',
        help='run drive_sim and controller as two processes (default: one)',
    )
    add_simulator_options(ap, 'the simulated motor', 'drive model fidelity')
    add_bag_options(ap, 'sim_bench')
    return ap


def add_bag_options(ap: argparse.ArgumentParser, prog: str) -> None:
    """The bag's options (:data:`BAG_OPTIONS`) on ``prog``'s parser."""
    for flag, kw in BAG_OPTIONS:
        ap.add_argument(flag, **{**kw, 'help': kw['help'].format(prog=prog)})


def main() -> int:
    """The executable (``ros2 run``: :mod:`im_drive_sim.launch`)."""
    return check_then_run('sim_bench', parser, 'im_tuner.bench.sim_bench:main')


if __name__ == '__main__':
    executable('sim_bench', main)
