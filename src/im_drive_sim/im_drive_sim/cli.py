"""Command-line plumbing shared by every executable of the workspace.

One convention for bad input, everywhere: **one line on stderr, exit code 2, nothing
created or changed** (no traceback, no usage block): :class:`Parser`, :func:`parse_cli`
(the ``--ros-args`` part checked by rcl), argparse ``type=`` helpers, :func:`run_cli`; and
:func:`executable`, every executable's ``__main__`` (Ctrl-C at any moment: one line, exit
130).

The ROS parts (rcl's argument parser) are imported lazily: the module is importable in
the pure tools and tests without rclpy.
"""

from __future__ import annotations

import argparse
import contextlib
import faulthandler
import importlib
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from . import numeric

#: every executable's exit codes: done, failed (or refused by the other side), bad input,
#: interrupted (128 + SIGINT, as a shell reports a process ended by Ctrl-C)
EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
#: [s] an executable's interpreter is given to shut down once its main returned (rclpy's
#: context, a thread left running); then it is ended with the same exit code
EXIT_GRACE_S = 3.0
#: the running executable's name (:func:`executable` sets it): the prefix of a line that
#: ends the process from elsewhere than its main function
PROG = {'name': 'im_tuner'}


class UsageError(Exception):
    """Bad input on the command line or in a file it names: one line, exit code 2."""


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (raised as :class:`UsageError`); a bad value of the
    numeric baseline's switch (``IM_NUMERIC_BASELINE``, :mod:`.numeric`) is refused as a
    bad command line is, by every executable.  Long options are taken whole, never
    abbreviated: a script's command line keeps its meaning when an option is added."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault('allow_abbrev', False)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(message)

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[no-untyped-def]
        problem = numeric.switch_problem()
        if problem:
            raise UsageError(problem)
        return super().parse_known_args(args, namespace)


def _ros_args_reason(text: str) -> str:
    """rcl's message without its C source locations (``, at /project/src/...:271``)."""
    text = re.sub(r',? at /\S+:\d+', '', str(text))
    return re.sub(r'^Failed to parse ROS arguments: ', '', text).strip()


def _params_files(argv: Sequence[str]) -> list[str]:
    """The ``--params-file F`` operands inside ``--ros-args`` sections."""
    out, in_ros = [], False
    for i, a in enumerate(argv):
        if a == '--ros-args':
            in_ros = True
        elif a == '--':
            in_ros = False
        elif in_ros and a == '--params-file' and i + 1 < len(argv):
            out.append(argv[i + 1])
    return out


def check_ros_args(argv: Sequence[str]) -> list[str]:
    """``argv`` without its ROS arguments; :class:`UsageError` if they do not parse.

    A ``--params-file`` that is missing or a directory is named plainly (rcl says 'Error
    parsing a event near line 0' for a directory)."""
    for f in _params_files(argv):
        p = Path(f)
        if not p.exists():
            raise UsageError(f'--params-file {f}: no such file')
        if not p.is_file():
            raise UsageError(f'--params-file {f}: not a file')
        if not os.access(p, os.R_OK):
            raise UsageError(f'--params-file {f}: not readable')
    if '--ros-args' not in argv and not any(':=' in a for a in argv):
        # nothing for rcl to remove (not even a deprecated bare 'from:=to' remap) or to
        # check: no need to load rclpy, and a refusal of the command line comes at once
        return list(argv)
    from rclpy.utilities import remove_ros_args

    try:
        return remove_ros_args(list(argv))
    except Exception as exc:  # RCLInvalidROSArgsError and friends (pybind11 types)
        raise UsageError(f'bad --ros-args: {_ros_args_reason(str(exc))}') from None


def parse_cli(parser: argparse.ArgumentParser, argv: Sequence[str]) -> argparse.Namespace:
    """Check the ROS arguments of the full ``argv`` (program name first), then parse the
    others with ``parser``."""
    return parser.parse_args(check_ros_args(argv)[1:])


def ros2_command() -> str:
    """How to type ``ros2`` for this installation in the user's shell: ``ros2`` when that
    is what the shell finds (a sourced ROS, an activated venv), else the path of this
    prefix's own (``.venv/bin/ros2`` from the project: ``make demo`` runs without the venv
    on PATH), so that a command printed for the user runs as printed."""
    mine = Path(sys.prefix) / 'bin' / 'ros2'
    # the shell's PATH, as this venv's ros2 found it before putting its own bin first
    found = shutil.which('ros2', path=os.environ.get('IM_TUNER_SHELL_PATH'))
    if not mine.exists() or (found and os.path.realpath(found) == os.path.realpath(mine)):
        return 'ros2'
    rel = os.path.relpath(mine)
    return rel if not rel.startswith('..') else str(mine)


def check_then_run(prog: str, parser: Callable[[], argparse.ArgumentParser], node_main: str) -> int:
    """An executable's entry (``python -m <pkg>.<exe>_main``): the command line is parsed
    with the node's own parser *before* the node's module is imported (numba kernels,
    rclpy: about a second, more on a loaded machine), so a refusal (one line, exit 2)
    or ``--help`` comes at once; an accepted command line goes on to ``node_main``
    (``'package.module:function'``), which parses it again and checks the rest."""
    try:
        parse_cli(parser(), sys.argv)
    except UsageError as exc:
        print(f'error: {prog}: {exc}', file=sys.stderr, flush=True)
        return EXIT_USAGE
    module, function = node_main.split(':')
    with quiet_interrupts(prog):  # numba, rclpy, the kernels: nothing held yet
        node = getattr(importlib.import_module(module), function)
    return node()


def executable(prog: str, main: str | Callable[[], int]) -> NoReturn:
    """Run an executable's ``main`` (a function, or ``'package.module:function'``, imported
    here: its imports are part of the run) and exit with its code.

    Ctrl-C (KeyboardInterrupt) at any moment -- during the imports, numba's compile, a
    node's start -- prints ``<prog>: interrupted`` and exits 130: no traceback. What the
    program holds is released by its own ``finally`` blocks as the interrupt unwinds
    them (a drive writes zero current there). Once ``main`` is over, a second Ctrl-C is
    ignored and the interpreter's shutdown is bounded (EXIT_GRACE_S), so the process
    ends promptly even when a library left a thread running."""
    # a crash in native code (a drive library's read, numba, rclpy) prints the Python
    # stack of every thread, the call into the library on top, before the process dies
    faulthandler.enable(all_threads=True)
    # a process that seems stuck prints the same on request: kill -USR1 <pid>
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    PROG['name'] = prog
    try:
        if isinstance(main, str):
            module, function = main.split(':')
            with quiet_interrupts(prog):
                main = getattr(importlib.import_module(module), function)
        # from here on Ctrl-C raises KeyboardInterrupt, so that the program's finally
        # blocks run (the launcher's early handler only ends a process holding nothing)
        if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:  # (ignored: stays so)
            signal.signal(signal.SIGINT, signal.default_int_handler)
        code = main()
    except (KeyboardInterrupt, Exception) as exc:
        # a Ctrl-C inside a C extension's initialisation (rclpy's, imported by main)
        # comes out as that import's error, the KeyboardInterrupt its cause: interrupted
        if not _caused_by_interrupt(exc):
            raise
        code = EXIT_INTERRUPTED
        print(f'{prog}: interrupted', file=sys.stderr, flush=True)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    _bounded_exit(int(code or 0))


def _caused_by_interrupt(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is in ``exc``'s chain of causes and contexts."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def _exit_quietly(prog: str) -> Callable[[int, object], None]:
    def handler(signum: int, frame: object) -> None:
        os.write(2, f'{prog}: interrupted\n'.encode())
        os._exit(EXIT_INTERRUPTED)

    return handler


@contextlib.contextmanager
def quiet_interrupts(prog: str) -> Iterator[None]:
    """Within the block, Ctrl-C ends the process at once with ``<prog>: interrupted`` and
    exit 130. For a stretch that holds nothing yet -- importing numba, rclpy, the
    kernels -- where a KeyboardInterrupt would surface as a traceback, or as another
    error (Python turns one raised inside a class's ``__set_name__`` into a
    RuntimeError), or be swallowed by a library. The previous handler comes back after."""
    previous = signal.getsignal(signal.SIGINT)
    if previous is signal.SIG_IGN or threading.current_thread() is not threading.main_thread():
        yield
        return
    signal.signal(signal.SIGINT, _exit_quietly(prog))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def held_interrupts() -> Iterator[None]:
    """Within the block a Ctrl-C is held, then raised as the handler before it would have
    (a KeyboardInterrupt) when the block ends. For a fork: Python runs its at-fork
    callbacks (logging's lock, among others) with the signal's exception printed as
    "Exception ignored" and dropped, so a Ctrl-C landing on a fork would be lost and the
    program would go on as if never interrupted."""
    previous = signal.getsignal(signal.SIGINT)
    if not callable(previous) or threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if held:
            previous(signal.SIGINT, None)


def _die_with_parent() -> None:
    # preexec_fn (in the child, before exec): SIGTERM when the parent dies, however it
    # dies (Linux prctl PR_SET_PDEATHSIG; it survives the exec chain of `ros2 run`)
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass  # not Linux: the children outlive a killed parent (SIGINT still ends them)


def spawn_child(argv: list[str], **popen: object) -> subprocess.Popen:
    """``subprocess.Popen(argv, **popen)`` for a child that must not outlive this process:
    it gets SIGTERM when this one dies, however it dies (a SIGKILLed tuner leaves no
    orphan drive, controller or recorder behind), and a Ctrl-C during the fork is raised
    after it (:func:`held_interrupts`), never lost."""
    with held_interrupts():
        return subprocess.Popen(argv, preexec_fn=_die_with_parent, **popen)  # type: ignore[call-overload]  # noqa: PLW1509 (only prctl)


def _bounded_exit(code: int) -> NoReturn:
    with contextlib.suppress(ValueError):  # (not the main thread: nothing to ignore)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    timer = threading.Timer(EXIT_GRACE_S, os._exit, (code,))
    timer.daemon = True
    timer.start()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    sys.exit(code)


def run_cli(prog: str, body: Callable[[], int]) -> int:
    """``body()``, with a :class:`UsageError` printed as ``error: <prog>: <reason>`` (exit 2)."""
    try:
        return body()
    except UsageError as exc:
        print(f'error: {prog}: {exc}', file=sys.stderr, flush=True)
        return EXIT_USAGE


# -- argparse types ----------------------------------------------------------------------
def plain(markdown: str) -> str:
    """``--help``'s text of an option's Markdown (the docs' tables): links as their text,
    no code marks, ``%`` escaped for argparse."""
    text = re.sub(r'\[([^\]]*)\]\([^)]*\)', r'\1', markdown)
    return text.replace('\\|', '|').replace('`', '').replace('%', '%%')


def finite_float(
    lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, unit: str = ''
) -> Callable[[str], float]:
    """A float that must be finite and within [lo, hi] (``lo_open``: lo excluded)."""

    def conv(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'not a number: {text!r}') from None
        u = f' {unit}' if unit else ''
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f'must be finite, got {text}')
        if lo is not None and (v < lo or (lo_open and v == lo)):
            raise argparse.ArgumentTypeError(
                f'must be {">" if lo_open else ">="} {lo:g}{u}, got {text}'
            )
        if hi is not None and v > hi:
            raise argparse.ArgumentTypeError(f'must be <= {hi:g}{u}, got {text}')
        return v

    conv.__name__ = 'number'  # argparse names the type in its messages
    return conv


def int_in(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """An integer within [lo, hi]."""

    def conv(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'not an integer: {text!r}') from None
        if lo is not None and v < lo:
            raise argparse.ArgumentTypeError(f'must be >= {lo}, got {text}')
        if hi is not None and v > hi:
            raise argparse.ArgumentTypeError(f'must be <= {hi}, got {text}')
        return v

    conv.__name__ = 'integer'
    return conv


def output_file(text: str) -> Path:
    """A file to be written later: not a directory, in an existing writable directory
    (checked now, so that a long job does not fail at its end)."""
    p = Path(text)
    if p.is_dir():
        raise argparse.ArgumentTypeError(f'{text} is a directory, not a file')
    parent = p.parent if str(p.parent) else Path('.')
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f'{text}: directory does not exist ({parent})')
    if not os.access(parent, os.W_OK | os.X_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise argparse.ArgumentTypeError(f'{text}: not writable')
    return p


def add_config_option(parser: argparse.ArgumentParser, what: str) -> None:
    """The ``--drive-config FILE|NAME`` option of every executable that loads a drive file
    (the tuner's and the study's are the same name): ``what`` it takes from it."""
    parser.add_argument(
        '--drive-config',
        metavar='FILE|NAME',
        type=drive_file,
        help=f'drive parameter file (YAML) or packaged drive name (im3700w-j3, ...): {what}',
    )


def add_simulator_options(parser: argparse.ArgumentParser, what: str, model: str) -> None:
    """``--drive-config`` (``what`` it takes from the file), ``--model`` (``model``: its
    help) and ``--seed``: the options of every executable that can start the simulator."""
    add_config_option(parser, what)
    parser.add_argument('--model', choices=('full', 'reduced'), help=model)
    parser.add_argument('--seed', type=int_in(0, 2**31 - 1), help='disturbance seed (>= 0)')


def drive_file(text: str) -> Path:
    """A drive file to be read, or a packaged drive's name (``family.PACKAGED_NAMES``;
    ``drive_file.load_config`` takes either): a bare name that is neither is refused naming
    the packaged drives."""
    from . import family

    p = Path(text)
    if not p.exists() and p.name == text and p.suffix == '':
        if text in family.PACKAGED_NAMES:
            return p
        raise argparse.ArgumentTypeError(family.unknown_drive_message(text))
    return input_file(text)


def input_file(text: str) -> Path:
    """A file to be read: it exists and is a regular file."""
    p = Path(text)
    if not p.exists():
        raise argparse.ArgumentTypeError(f'{text}: no such file')
    if not p.is_file():
        raise argparse.ArgumentTypeError(f'{text}: not a file')
    return p
