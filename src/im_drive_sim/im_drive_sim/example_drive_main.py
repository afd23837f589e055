"""``ros2 run im_drive_sim example_drive``: checks its command line before the node is imported,
and turns ``--hardware`` into the node's hardware class (:func:`hardware_factory`)."""

from __future__ import annotations

import argparse
from typing import Any

from . import rt
from .cli import Parser, check_then_run, executable


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
    ap.add_argument(
        '--hardware',
        default='python',
        metavar='HW',
        help="the power stage: 'python' (the stand-in plant as a Python hardware class, "
        "the default), 'example' (the same plant compiled), or 'lib:PATH' (a C shared "
        'library with the drive ABI, share/im_drive_sim/include/im_drive.h; docs/real-drive.md)',
    )
    rt.add_arguments(ap, 'the drive loop')
    return ap


def check_hardware(spec: str) -> str:
    """``--hardware``: 'python', 'example' or 'lib:PATH' (UsageError otherwise)."""
    from pathlib import Path

    from .cli import UsageError

    if spec in ('python', 'example'):
        return spec
    if spec.startswith('lib:') and len(spec) > 4:
        if not Path(spec[4:]).expanduser().is_file():
            raise UsageError(f'--hardware {spec}: no such file')
        return spec
    raise UsageError(f"--hardware {spec!r}: expected 'python', 'example' or 'lib:PATH'")


def hardware_factory(spec: str) -> Any:
    """``hardware_class`` for ``--hardware``: None (the Python stand-in), the compiled
    stand-in, or a drive library (``hardware_abi.LibraryHardware``)."""
    if spec == 'python':
        return None
    if spec == 'example':
        from .example_hardware import CompiledHardware
        from .hardware_abi import CompiledClassHardware

        return lambda config: CompiledClassHardware(CompiledHardware(config), name='example')
    from .hardware_abi import LibraryHardware

    return lambda config: LibraryHardware(spec[4:], config)


def main() -> int:
    """The executable (``ros2 run``: :mod:`im_drive_sim.launch`)."""
    return check_then_run('example_drive', parser, 'im_drive_sim.example_drive:main')


if __name__ == '__main__':
    executable('example_drive', main)
