"""``--drive``: which drive the composed real-time bench runs, checked against the drive
contract of docs/real-drive.md before anything is created.

A drive is named (``benches.NAMED_DRIVES``), ``lib:PATH`` (a C shared library with the
drive ABI, ``im_drive_sim.hardware_abi``) or ``package.module:Class`` (a compiled hardware
class, a hardware class as ``im_drive_sim.example_drive.Hardware``, or an
``ExampleDrive`` subclass). Anything else is refused with one line saying which part of
the contract it misses. :func:`resolve` also builds a power stage once, with the drive
file the bench will load, so a constructor that raises (no inverter on the bus) is
refused before the run directory exists; the bench takes that instance
(:meth:`DriveChoice.factory`). No rclpy at import.
"""

from __future__ import annotations

import importlib
import inspect
import os
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..benches import NAMED_DRIVES


def sim_drive(context: Any, overrides: list[Any]) -> Any:
    """The simulator, in real time, with every drive parameter of the tuner's."""
    from rclpy.parameter import Parameter

    from im_drive_sim.drive_sim_node import DriveSimNode

    return DriveSimNode(
        context=context,
        parameter_overrides=[
            Parameter('mode', value='realtime'),
            Parameter('realtime_wait_for_controller', value=False),
            *overrides,
        ],
        warn_unknown=False,
    )


def example_drive(context: Any, overrides: list[Any]) -> Any:
    """The example drive around its stand-in plant, compiled (:func:`compiled_example`)."""
    from im_drive_sim.example_drive import ExampleDrive

    return ExampleDrive(
        context=context, parameter_overrides=_file_only(overrides), hardware_class=compiled_example
    )


def compiled_example(config: Any) -> Any:
    """``--drive example``'s power stage: the stand-in plant, compiled
    (``im_drive_sim.example_hardware``), behind the ABI's Python interface."""
    from im_drive_sim.example_hardware import CompiledHardware
    from im_drive_sim.hardware_abi import CompiledClassHardware

    return CompiledClassHardware(CompiledHardware(config), name='example')


def _file_only(overrides: list[Any]) -> list[Any]:
    """Of the tuner's drive parameters, the drive file (all a drive but the simulator
    takes)."""
    return [p for p in overrides if p.name == 'config_file']


#: Drives by name; anything else is ``lib:PATH`` or ``package.module:Class``
DRIVES = tuple(NAMED_DRIVES)
_DOC = 'docs/real-drive.md'


def _expected() -> str:
    """What ``--drive`` takes, for a refusal."""
    return ', '.join(f"'{k}'" for k in NAMED_DRIVES) + ", 'lib:PATH' or 'package.module:Class'"


class DriveSpecError(ValueError):
    """``--drive`` names no usable drive (the message says why, on one line)."""


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f'{type(exc).__name__}: {text[0]}' if text else type(exc).__name__


#: the prefix of a drive library: ``lib:PATH``
LIB = 'lib:'


def load_drive_class(spec: str) -> type:
    """The class named by ``package.module:Class`` (DriveSpecError if there is none)."""
    mod_name, sep, cls_name = spec.partition(':')
    if not sep or not mod_name or not cls_name:
        raise DriveSpecError(f'--drive {spec!r}: expected {_expected()}')
    try:
        mod = importlib.import_module(mod_name)
    except SystemExit as exc:  # a module that ends the process when imported
        raise DriveSpecError(
            f'--drive {spec!r}: importing {mod_name} called sys.exit({exc.code!r})'
        ) from None
    except Exception as exc:  # an import error of the user's module, whatever it is
        raise DriveSpecError(
            f'--drive {spec!r}: cannot import {mod_name}: {_first_line(exc)}'
        ) from None
    cls = getattr(mod, cls_name, None)
    if not isinstance(cls, type):
        raise DriveSpecError(f'--drive {spec!r}: {mod_name} has no class {cls_name}')
    return cls


def _is_ros_node(cls: type) -> bool:
    node = sys.modules.get('rclpy.node')  # a node class's module imported rclpy already
    return node is not None and issubclass(cls, node.Node)


def _binds(fn: Any, args: tuple[Any, ...]) -> bool | None:
    """Whether ``fn`` takes ``args`` (None: its signature cannot be read)."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return None
    try:
        sig.bind(*args)
    except TypeError:
        return False
    return True


def _method_takes(cls: type, name: str, n_args: int) -> bool | None:
    """Whether ``instance.name(*n_args numbers)`` is a valid call (None: cannot tell)."""
    raw = inspect.getattr_static(cls, name)
    nums = (0.0,) * n_args
    if isinstance(raw, staticmethod):
        return _binds(raw.__func__, nums)
    if isinstance(raw, classmethod):
        return _binds(getattr(cls, name), nums)
    return _binds(getattr(cls, name), (object(), *nums))  # a plain method: self first


def check_drive_class(spec: str, cls: type) -> str:
    """Check ``cls`` against the drive contract; returns its form, 'node' or 'hardware'."""
    name = cls.__name__
    if _is_ros_node(cls):
        from im_drive_sim.example_drive import ExampleDrive

        if not issubclass(cls, ExampleDrive):
            hint = ' (the simulator is --drive sim)' if name == 'DriveSimNode' else ''
            raise DriveSpecError(
                f'--drive {spec!r}: {name} is a ROS node but not a drive node: a drive '
                f'node class is an ExampleDrive subclass{hint} ({_DOC})'
            )
        if inspect.isabstract(cls):
            raise DriveSpecError(f'--drive {spec!r}: {name} is abstract ({_DOC})')
        try:
            inspect.signature(cls).bind(context=None, parameter_overrides=[])
        except (TypeError, ValueError):
            raise DriveSpecError(
                f'--drive {spec!r}: {name}(context=..., parameter_overrides=[...]) is not '
                f"a valid call: a drive node class keeps ExampleDrive's constructor ({_DOC})"
            ) from None
        return 'node'
    from im_drive_sim.hardware_abi import (
        DriveLibraryError,
        check_compiled_class,
        is_compiled_class,
    )

    if is_compiled_class(cls):
        try:
            check_compiled_class(cls)
        except DriveLibraryError as exc:
            raise DriveSpecError(f'--drive {spec!r}: {exc}') from None
        if _binds(cls, (object(),)) is False:
            raise DriveSpecError(f'--drive {spec!r}: {name}(config) is not a valid call ({_DOC})')
        return 'compiled'
    contract = (
        f'a hardware class has read() -> Measurement, write(isq_ref, load_torque) and '
        f'Class(config), or give an ExampleDrive subclass ({_DOC})'
    )
    missing = [m for m in ('read', 'write') if not callable(getattr(cls, m, None))]
    if missing:
        raise DriveSpecError(
            f'--drive {spec!r}: {name} has no {" and no ".join(m + "()" for m in missing)}: '
            f'{contract}'
        )
    if inspect.isabstract(cls):
        raise DriveSpecError(f'--drive {spec!r}: {name} is abstract: {contract}')
    for meth, n, call in (('read', 0, 'read()'), ('write', 2, 'write(isq_ref, load_torque)')):
        if _method_takes(cls, meth, n) is False:
            raise DriveSpecError(f'--drive {spec!r}: {name}.{call} is not a valid call: {contract}')
    if callable(getattr(cls, 'close', None)) and _method_takes(cls, 'close', 0) is False:
        raise DriveSpecError(
            f'--drive {spec!r}: {name}.close() is not a valid call: close takes no '
            f'arguments ({_DOC})'
        )
    if _binds(cls, (object(),)) is False:
        raise DriveSpecError(f'--drive {spec!r}: {name}(config) is not a valid call: {contract}')
    return 'hardware'


def _library_path(spec: str) -> Path:
    """``lib:PATH``'s file (DriveSpecError: none given, or no such file)."""
    path = spec[len(LIB) :]
    if not path:
        raise DriveSpecError(f"--drive {spec!r}: expected 'lib:PATH' (a shared library)")
    p = Path(path).expanduser()
    if not p.is_file():
        raise DriveSpecError(f'--drive {spec!r}: no such file: {p}')
    return p


@dataclass
class DriveChoice:
    """A checked ``--drive``: its spec, the class and its form, and (a hardware class)
    the instance built by :func:`resolve` with the drive file ``config``."""

    spec: str
    cls: type | None = None  #: None: a named drive or a library
    form: str = ''  #: 'node', 'hardware', 'compiled', 'library' or '' (a named drive)
    hardware: Any = None  #: the hardware instance, until the bench takes it
    config: Any = None  #: the DriveConfig it was built with
    #: the command-delay probe of the hardware (hardware_probe.DelayProbe), once built
    probe: Any = None
    taken: bool = field(default=False, repr=False)

    def factory(self, config: Any) -> Any:
        """``hardware_class`` for ExampleDrive: hands over the instance built by
        :func:`resolve` (once), or builds one if the drive loaded another file."""
        if self.hardware is not None and not self.taken and config == self.config:
            self.taken = True
            return self.hardware
        close_hardware(self)
        return _make_hardware(self, config)


def _make_hardware(choice: DriveChoice, config: Any) -> Any:
    """The power stage of a checked ``--drive`` (a hardware, compiled or library form),
    built with ``config``: every problem one DriveSpecError line."""
    from im_drive_sim.hardware_abi import (
        CompiledClassHardware,
        DriveLibraryError,
        LibraryHardware,
    )

    spec = choice.spec
    try:
        if choice.form == 'library':
            return LibraryHardware(spec[len(LIB) :], config)
        cls = choice.cls
        assert cls is not None
        hw = _build(spec, f'{cls.__name__}(config)', lambda: cls(config))
        if choice.form == 'compiled':
            wrapped = CompiledClassHardware(hw, name=spec)
            wrapped.entry()  # the loop's wrappers compiled now: an error is this line
            return wrapped
        return hw
    except DriveLibraryError as exc:
        msg = str(exc)
        raise DriveSpecError(msg if msg.startswith(spec) else f'--drive {spec!r}: {msg}') from None


def close_hardware(choice: DriveChoice | None) -> None:
    """Close a hardware instance the bench never took (a run refused or failed before it
    started); the errors of ``close()`` are not the run's concern then."""
    if choice is None or choice.hardware is None or choice.taken:
        return
    choice.taken = True
    close = getattr(choice.hardware, 'close', None)
    if callable(close):
        try:
            close()
        except Exception as exc:  # reported, not raised: the run is ending anyway
            print(f'warning: {choice.spec}: close() raised {_first_line(exc)}', file=sys.stderr)


#: every hardware instance :func:`resolve` built in this process (close_untaken)
_BUILT: list[DriveChoice] = []


def holds_hardware() -> bool:
    """Whether a hardware instance built by :func:`resolve` is open and no bench took it."""
    return bool(_BUILT)


def close_untaken() -> None:
    """Close every hardware instance built by :func:`resolve` that no bench took (the
    tuner calls this on its way out, whatever the way)."""
    while _BUILT:
        close_hardware(_BUILT.pop())


def resolve(spec: str, drive_config: str | Path | None, build: bool = True) -> DriveChoice:
    """Check ``--drive`` and, for a hardware class (``build``), build it now with the drive
    file the bench will load (``drive_config``; None = the packaged motor). Every problem
    is a DriveSpecError of one line; a constructor that raises is named with its exception."""
    if spec in DRIVES:
        return DriveChoice(spec)
    if spec.startswith(LIB):
        _library_path(spec)
        choice = DriveChoice(spec, None, 'library')
    else:
        cls = load_drive_class(spec)
        choice = DriveChoice(spec, cls, check_drive_class(spec, cls))
    if choice.form in ('hardware', 'compiled', 'library') and build:
        from im_drive_sim.drive_file import load_config
        from im_drive_sim.params import ConfigError

        try:
            config = load_config(drive_config)
        except ConfigError as exc:
            raise DriveSpecError(f'--drive {spec!r}: {exc}') from None
        choice.hardware = _make_hardware(choice, config)
        choice.config = config
        _BUILT.append(choice)
        from im_drive_sim.example_drive import hardware_command_delay

        try:
            declared = hardware_command_delay(choice.hardware)
        except ConfigError as exc:
            _BUILT.remove(choice)
            close_hardware(choice)
            raise DriveSpecError(f'--drive {spec!r}: {exc} (docs/real-drive.md)') from None
        _check_delay(choice, declared)
    return choice


def _check_delay(choice: DriveChoice, declared: int) -> None:
    """The declared command delay measured on the power stage (``hardware_probe``): a
    drive slower than it declares is refused in one line (nothing created yet)."""
    from im_drive_sim.hardware_probe import probe_delay

    config = choice.config
    try:
        choice.probe = probe_delay(
            choice.hardware, float(config.Ts), float(config.machine.isq_max), declared
        )
    except Exception as exc:  # the user's read/write raised (a HardwareFault too): one line
        _BUILT.remove(choice)
        close_hardware(choice)
        raise DriveSpecError(
            f'--drive {choice.spec!r}: the command-delay probe failed: {_first_line(exc)}'
        ) from None
    if not choice.probe.ok:
        _BUILT.remove(choice)
        close_hardware(choice)
        slower = choice.probe.onset
        raise DriveSpecError(
            f'--drive {choice.spec!r}: slower than it declares: {choice.probe.text()}; '
            f'declare command_delay = {slower} if it is {slower} '
            f'(docs/real-drive.md, "Command delay")'
        )


#: [s] a drive class's constructor that uses no CPU (under IDLE_CPU_S) for this long is
#: taken to hang: a vendor's open that waits on a bus returns within seconds; one that
#: waits for ever is named, not waited for (a constructor that computes -- numba's
#: compile on a loaded machine -- gets the time it needs)
CONSTRUCTOR_IDLE_S = 30.0


def _watched(what: str, make: Any) -> Any:
    """``make()`` in this thread, watched by another: once the process has been idle
    for CONSTRUCTOR_IDLE_S (:class:`..patience.Patience`) the process ends with one line
    naming ``what``, exit 2. Nothing of the run exists yet (a drive is built before its
    bench), and the constructor that never returned commanded nothing."""
    from im_drive_sim.cli import EXIT_USAGE, PROG

    from ..patience import Patience

    done = threading.Event()

    def watch() -> None:
        wait = Patience(os.getpid(), what, RuntimeError, idle_s=CONSTRUCTOR_IDLE_S)
        while not done.wait(0.5):
            try:
                wait.check()
            except RuntimeError:
                os.write(
                    2,
                    f'error: {PROG["name"]}: {what} did not return: the process sat idle '
                    f'for {CONSTRUCTOR_IDLE_S:g} s (a constructor must return: open the '
                    'device with a time limit of its own)\n'.encode(),
                )
                os._exit(EXIT_USAGE)

    threading.Thread(target=watch, name='drive-constructor-watch', daemon=True).start()
    try:
        return make()
    finally:
        done.set()


def _build(spec: str, what: str, make: Any, watch: bool = True) -> Any:
    """``make()``, with an exception (or sys.exit) of the user's code as a DriveSpecError
    naming ``what`` and the exception; ``watch``: a ``make()`` that never returns ends
    the process in one line (:func:`_watched`; a power stage, built before its bench)."""
    try:
        return _watched(f'--drive {spec!r}: {what}', make) if watch else make()
    except SystemExit as exc:
        raise DriveSpecError(f'--drive {spec!r}: {what} called sys.exit({exc.code!r})') from None
    except Exception as exc:
        raise DriveSpecError(f'--drive {spec!r}: {what} raised {_first_line(exc)}') from None


def build_node(choice: DriveChoice, context: Any, overrides: list[Any]) -> Any:
    """The drive node of a user's class (``choice.form`` 'node' or 'hardware'). The
    user's constructor that raises becomes a DriveSpecError naming the class and the
    exception; the example drive's own errors (its parameters) stay what they are."""
    from im_drive_sim.example_drive import ExampleDrive

    cls = choice.cls
    if choice.form == 'node':
        assert cls is not None
        return _build(
            choice.spec,
            cls.__name__,
            lambda: cls(context=context, parameter_overrides=overrides),
            watch=False,  # (inside the bench: its run exists; Ctrl-C ends it cleanly)
        )
    node = ExampleDrive(
        context=context, parameter_overrides=overrides, hardware_class=choice.factory
    )
    node.delay_probe = choice.probe  # (for the bag's metadata)
    return node


def make_drive(spec: str | DriveChoice, context: Any, overrides: list[Any]) -> Any:
    """The drive node of the composed real-time bench (``realtime.RealtimeBench``) named
    by ``spec`` (a name of ``benches.NAMED_DRIVES`` or a class; a DriveChoice is a
    ``--drive`` already checked, with its hardware built: :func:`resolve`), in real time.

    ``overrides``: the tuner's drive parameters; the simulator takes them all (seed,
    model, config_file), the example drive and a user's drive only ``config_file``."""
    choice = spec if isinstance(spec, DriveChoice) else None
    name = choice.spec if choice is not None else spec
    assert isinstance(name, str)
    if name in NAMED_DRIVES:
        module, _, function = NAMED_DRIVES[name].make.partition(':')
        return getattr(importlib.import_module(module), function)(context, overrides)
    return build_node(choice or resolve(name, None, build=False), context, _file_only(overrides))
