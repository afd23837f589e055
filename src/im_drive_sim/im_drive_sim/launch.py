"""How every executable of the workspace starts: ``python -m im_drive_sim.launch PROG
MODULE:FUNCTION [ARGS...]``, the line of each installed script (``lib/<pkg>/<exe>``,
what ``ros2 run <pkg> <exe>`` runs).

Nothing of the program is imported before :func:`.cli.executable` holds Ctrl-C: an
interrupt during its imports, numba's compile or a node's start ends it with one line
and exit 130, never a traceback. ``sys.argv`` is then what ``python -m MODULE ARGS``
would give (the module's file, then ARGS), and a venv's own ament index is found without
sourcing anything (``AMENT_PREFIX_PATH`` defaults to the interpreter's prefix).
"""

from __future__ import annotations

import os
import signal
import sys


def _interrupted_early(signum: int, frame: object) -> None:
    # Ctrl-C before the program's own handling begins (the imports below): nothing is
    # held yet, so the process ends at once, quietly
    prog = sys.argv[1] if len(sys.argv) > 1 else 'launch'
    os.write(2, f'{prog}: interrupted\n'.encode())
    os._exit(130)


if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # (SIG_IGN: kept)
    signal.signal(signal.SIGINT, _interrupted_early)
# `ros2 run` (the workspace's) blocks Ctrl-C across the exec and the interpreter's start:
# one pressed then was held, and comes now, to the handler above
signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})

import importlib.util  # noqa: E402 (after the handler: an interrupt here is quiet too)

from .cli import EXIT_USAGE, executable  # noqa: E402


def _start() -> None:
    if len(sys.argv) < 3 or ':' not in sys.argv[2]:
        print(
            'usage: python -m im_drive_sim.launch PROG MODULE:FUNCTION [ARGS...]', file=sys.stderr
        )
        sys.exit(EXIT_USAGE)
    prog, target = sys.argv[1], sys.argv[2]
    spec = importlib.util.find_spec(target.split(':')[0])  # (imports its packages only)
    sys.argv = [spec.origin if spec is not None and spec.origin else prog, *sys.argv[3:]]
    os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    executable(prog, target)


if __name__ == '__main__':
    _start()
