"""``ros2 run im_controller controller``: checks its command line before the node is imported."""

from __future__ import annotations

import argparse

from im_drive_sim.cli import Parser, add_config_option, check_then_run, executable
from im_drive_sim.contract import MODES

DESCRIPTION = (
    "Cascaded position/speed controller with the paper's loss experiment. Start an "
    'experiment with the ~/start_experiment service (std_srvs/Trigger); results on '
    'controller/loss. Parameters: --ros-args -p name:=value (see docs/controller.md).'
)


def parser() -> argparse.ArgumentParser:
    ap = Parser(prog='ros2 run im_controller controller', description=DESCRIPTION)
    ap.add_argument('--mode', choices=MODES, help='lockstep (default) or realtime')
    add_config_option(ap, 'Ts and isq_max')
    return ap


def main() -> int:
    """The executable (``ros2 run``: :mod:`im_drive_sim.launch`)."""
    return check_then_run('controller', parser, 'im_controller.controller_node:main')


if __name__ == '__main__':
    executable('controller', main)
