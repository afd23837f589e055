"""``ros2 run im_drive_sim drive_sim``: checks its command line before the node is imported."""

from __future__ import annotations

import argparse

from . import rt
from .cli import Parser, add_simulator_options, check_then_run, executable, int_in
from .contract import MODES


def parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog='ros2 run im_drive_sim drive_sim',
        description='Induction-motor drive simulator (5 kHz). Topics: drive/state (out), '
        'drive/command (in), drive/joint_states, drive/status, /clock. '
        'Parameters are set with --ros-args -p name:=value; the options below '
        'are shortcuts for them. See docs/interfaces.md.',
    )
    ap.add_argument('--mode', choices=MODES, help='lockstep (default) or realtime')
    add_simulator_options(ap, 'the simulated motor', 'model fidelity')
    ap.add_argument(
        '--max-steps', type=int_in(0, 2**62), help='stop after N steps (0: run until shut down)'
    )
    rt.add_arguments(ap, 'the drive loop')
    return ap


def main() -> int:
    """The executable (``ros2 run``: :mod:`im_drive_sim.launch`)."""
    return check_then_run('drive_sim', parser, 'im_drive_sim.drive_sim_node:main')


if __name__ == '__main__':
    executable('drive_sim', main)
