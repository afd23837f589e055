"""``ros2 run im_drive_sim example_drive``: checks its command line before the node is imported."""

from __future__ import annotations

import argparse
import sys

from . import rt
from .cli import Parser, check_then_run


def parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog='ros2 run im_drive_sim example_drive',
        description='A minimal real-time drive node (the template for a '
        'real drive): drive/state every 200 us, drive/command, '
        'isq clamp, command watchdog. Parameters (all '
        'read-only): --ros-args -p isq_max:=7.0 -p '
        'command_timeout:=0.05 -p config_file:=FILE ... '
        '(docs/real-drive.md).',
    )
    rt.add_arguments(ap, 'the drive loop')
    return ap


if __name__ == '__main__':
    sys.exit(check_then_run('example_drive', parser, 'im_drive_sim.example_drive:main'))
