"""A user's power stage inside the compiled, GIL-free 5 kHz loop: the drive ABI. The loop
calls it *by address*, with no GIL, in two forms (docs/real-drive.md, "A drive library
(C)" and "A compiled hardware class"): a C shared library exporting :data:`SYMBOLS`
(``share/im_drive_sim/include/im_drive.h``; a negative return is a drive fault,
:class:`HardwareFault`), and a compiled Python class called through C wrappers built once
(numba ``cfunc``, :class:`CompiledClassHardware`; ``example_hardware`` is one).

Both are wrapped in an object with the Python hardware-class interface (``write``,
``read() -> Measurement``, ``close``, ``command_delay``) for what runs outside the loop,
plus ``entry()``: the addresses the compiled loop calls (:class:`HardwareEntry`).

Written by hand, not with a library: numba calls a function pointer held in a runtime
integer only through an intrinsic (a few lines of LLVM IR below); ctypes' own function
objects are compile-time constants in numba, which would make the loop uncachable.
"""

from __future__ import annotations

import ctypes
import inspect
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
from llvmlite import ir
from numba import carray, cfunc, njit, types
from numba.core.registry import CPUDispatcher
from numba.extending import intrinsic

from . import contract
from .params import ConfigError, DriveConfig

#: ``im_drive_read``'s ``m[8]``, in order (``example_drive.Measurement``'s fields; SI units):
#: the state's fields from theta_meas to load_torque (``contract.STATE_FIELDS``)
MEASUREMENT_FIELDS: tuple[str, ...] = contract.STATE_FIELDS[
    contract.STATE_INDEX['theta_meas'] : contract.STATE_INDEX['load_torque'] + 1
]
N_MEASUREMENT = len(MEASUREMENT_FIELDS)

#: ``IM_DRIVE_ABI_VERSION`` of the header this loop calls by (include/im_drive.h; a test
#: reads it there): a library whose ``im_drive_abi_version()`` differs is refused unopened
ABI_VERSION = 1

#: the library's functions: name -> (required, argument types, return type)
SYMBOLS: dict[str, tuple[bool, list[Any], Any]] = {
    'im_drive_abi_version': (True, [], ctypes.c_int),
    'im_drive_open': (True, [ctypes.c_char_p], ctypes.c_int),
    'im_drive_write': (True, [ctypes.c_double, ctypes.c_double], ctypes.c_int),
    'im_drive_read': (True, [ctypes.c_void_p], ctypes.c_int),
    'im_drive_command_delay': (False, [], ctypes.c_int),
    'im_drive_close': (False, [], None),
}

#: how the loop calls the entry: C ABI as above, or with the hardware's state first
#: (``(double *state, int64 n, ...)``: the compiled class's wrappers)
KIND_C, KIND_CTX = 0, 1

_DOC = 'docs/real-drive.md'


class DriveLibraryError(ConfigError):
    """A drive library or compiled class that cannot be used (one line: which, why; a
    ``ConfigError``, so a drive node refuses it as a bad drive file: exit 2)."""


class HardwareFault(RuntimeError):
    """The power stage returned a negative code: a drive fault (zero current follows)."""


@dataclass(frozen=True)
class HardwareEntry:
    """What the compiled loop calls: the addresses of write, read and (KIND_CTX, optional)
    elapse, and the state array ``ctx`` (address, length) passed first to KIND_CTX calls."""

    kind: int
    write: int
    read: int
    elapse: int = 0
    ctx: int = 0
    ctx_len: int = 0
    #: what a fault message names: ``lib:PATH`` or ``package.module:Class``
    name: str = ''


# -- calls by address (the loop's side) --------------------------------------------------
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
_F64 = ir.DoubleType()
_F64P = _F64.as_pointer()


def _call_by_address(name: str, params: list[Any]) -> Any:
    """A numba intrinsic ``f(addr, *args) -> int32`` that calls the C function at the
    address ``addr`` (int64) with ``args``: ``params`` are its C parameter types
    (``_F64`` a double, ``_I64`` an int64, ``_F64P`` a ``double*`` given as an int64
    address). Written with llvmlite because numba has no call through a run-time
    address."""
    sig = types.int32(types.int64, *(types.float64 if p is _F64 else types.int64 for p in params))

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        fn_type = ir.FunctionType(_I32, params).as_pointer()
        vals = [
            builder.inttoptr(v, _F64P) if p is _F64P else v
            for p, v in zip(params, args[1:], strict=True)
        ]
        return builder.call(builder.inttoptr(args[0], fn_type), vals)

    def typer(typingctx: Any, *args: Any) -> Any:
        return sig, codegen

    # numba reads the intrinsic's arguments from its typer's signature: one each, named
    names = ['typingctx', 'addr', *(f'arg{i}' for i in range(len(params)))]
    kind = inspect.Parameter.POSITIONAL_OR_KEYWORD
    typer.__signature__ = inspect.Signature([inspect.Parameter(n, kind) for n in names])  # type: ignore[attr-defined]
    typer.__name__ = typer.__qualname__ = name
    return intrinsic(typer)


_c_write: Any = _call_by_address('_c_write', [_F64, _F64])
_c_read: Any = _call_by_address('_c_read', [_F64P])
_ctx_write: Any = _call_by_address('_ctx_write', [_F64P, _I64, _F64, _F64])
_ctx_read: Any = _call_by_address('_ctx_read', [_F64P, _I64, _F64P])
_ctx_elapse: Any = _call_by_address('_ctx_elapse', [_F64P, _I64, _I64])


#: the words of an entry as the loop holds them (int64 array, :func:`entry_words`)
E_KIND, E_WRITE, E_READ, E_ELAPSE, E_CTX, E_CTX_LEN = range(6)


def entry_words(e: HardwareEntry) -> np.ndarray:
    """``e`` as the int64 words the compiled calls below take."""
    return np.array([e.kind, e.write, e.read, e.elapse, e.ctx, e.ctx_len], np.int64)


@njit(cache=True, nogil=True)
def call_write(E: np.ndarray, isq_ref: float, load_torque: float) -> int:
    """The power stage's write [A], [N m] (``E``: :func:`entry_words`); its return code."""
    if E[E_KIND] == KIND_C:
        return _c_write(E[E_WRITE], isq_ref, load_torque)
    return _ctx_write(E[E_WRITE], E[E_CTX], E[E_CTX_LEN], isq_ref, load_torque)


@njit(cache=True, nogil=True)
def call_read(E: np.ndarray, m: np.ndarray) -> int:
    """The power stage's read into ``m`` (float64[8], :data:`MEASUREMENT_FIELDS`)."""
    if E[E_KIND] == KIND_C:
        return _c_read(E[E_READ], m.ctypes.data)
    return _ctx_read(E[E_READ], E[E_CTX], E[E_CTX_LEN], m.ctypes.data)


@njit(cache=True, nogil=True)
def call_elapse(E: np.ndarray, periods: int) -> int:
    """A stand-in plant told that ``periods`` went by unsampled (0 when it has no elapse)."""
    if E[E_ELAPSE] == 0:
        return 0
    return _ctx_elapse(E[E_ELAPSE], E[E_CTX], E[E_CTX_LEN], periods)


# -- the Python side of both forms ---------------------------------------------------------
@dataclass
class Measurement:
    """What the drive samples each period (SI units; updated in place, never re-created)."""

    theta_meas: float = 0.0  #: [rad] encoder position, multi-turn
    omega_meas: float = 0.0  #: [rad/s] speed estimate
    torque: float = 0.0  #: [N m] electromagnetic torque (estimated on a real drive)
    isd: float = 0.0  #: [A] d-axis current
    isq: float = 0.0  #: [A] q-axis current
    i_alpha: float = 0.0  #: [A] stator current, alpha axis
    i_beta: float = 0.0  #: [A] stator current, beta axis
    load_torque: float = 0.0  #: [N m] load machine torque


assert tuple(f.name for f in fields(Measurement)) == MEASUREMENT_FIELDS


class _Measured:
    """The Python hardware-class interface over ``m`` (float64[8])."""

    name = ''
    command_delay = 1

    def _fill(self, meas: Any, m: np.ndarray) -> Any:
        for name, v in zip(MEASUREMENT_FIELDS, m.tolist(), strict=True):
            setattr(meas, name, v)
        return meas

    def _check(self, rc: int, what: str) -> None:
        if rc < 0:
            raise HardwareFault(f'{self.name}: {what} returned {rc} (a drive fault)')


class LibraryHardware(_Measured):
    """A C drive library (``--drive lib:PATH``): loaded, checked and opened here; every
    problem is a :class:`DriveLibraryError` of one line naming the library."""

    def __init__(self, path: str | Path, config: DriveConfig) -> None:
        p = Path(path).expanduser()
        self.name = f'lib:{path}'
        if not p.is_file():
            raise DriveLibraryError(f'{self.name}: no such file')
        drive_file = config.path.encode() if config.path else None
        from .library_trial import trial_library

        refused = trial_library(p.resolve(), self.name, drive_file, ABI_VERSION)
        if refused:  # it crashed, exited or hung in the child: named there
            raise DriveLibraryError(refused)
        try:
            # RTLD_LOCAL: its symbols do not leak into another library loaded later
            self.lib = ctypes.CDLL(str(p.resolve()), mode=ctypes.RTLD_LOCAL)
        except OSError as exc:
            raise DriveLibraryError(f'{self.name}: cannot load: {exc}') from None
        fns: dict[str, Any] = {}
        for sym, (required, argtypes, restype) in SYMBOLS.items():
            try:
                fns[sym] = getattr(self.lib, sym)
                fns[sym].argtypes, fns[sym].restype = argtypes, restype
            except AttributeError:
                if sym == 'im_drive_abi_version':
                    raise DriveLibraryError(
                        f'{self.name}: no function im_drive_abi_version: built against a '
                        f'header without the drive ABI version; rebuild it against '
                        f'share/im_drive_sim/include/im_drive.h (version {ABI_VERSION}, '
                        f'{_DOC}, "ABI version")'
                    ) from None
                if required:
                    raise DriveLibraryError(
                        f'{self.name}: no function {sym} (the drive ABI: '
                        f'share/im_drive_sim/include/im_drive.h, {_DOC})'
                    ) from None
        # the version first: another layout of m[] or of a call must not be opened at all
        version = int(fns['im_drive_abi_version']())
        if version != ABI_VERSION:
            raise DriveLibraryError(
                f'{self.name}: built for drive ABI version {version}; this im_drive_sim '
                f'calls version {ABI_VERSION}: rebuild it against '
                f'share/im_drive_sim/include/im_drive.h ({_DOC}, "ABI version")'
            )
        self._fns = fns
        self._write, self._read = fns['im_drive_write'], fns['im_drive_read']
        self._m = np.zeros(N_MEASUREMENT)
        self._meas = Measurement()
        self._closed = False
        rc = fns['im_drive_open'](drive_file)
        if rc != 0:
            shown = drive_file.decode() if drive_file else 'NULL'
            raise DriveLibraryError(f'{self.name}: im_drive_open({shown}) returned {rc}')
        if 'im_drive_command_delay' in fns:
            d = int(fns['im_drive_command_delay']())
            if d not in contract.COMMAND_DELAYS:
                self.close()
                raise DriveLibraryError(
                    f'{self.name}: im_drive_command_delay() returned {d}: 1 or 2 ({_DOC}, '
                    f'"Command delay")'
                )
            self.command_delay = d

    def write(self, isq_ref: float, load_torque: float) -> None:
        self._check(self._write(float(isq_ref), float(load_torque)), 'im_drive_write')

    def read(self) -> Any:
        self._check(self._read(self._m.ctypes.data), 'im_drive_read')
        return self._fill(self._meas, self._m)

    def close(self) -> None:
        """``im_drive_close`` once (after the drive's last write of zero)."""
        if self._closed:
            return
        self._closed = True
        close = self._fns.get('im_drive_close')
        if close is not None:
            close()

    def entry(self) -> HardwareEntry:
        addr = ctypes.cast(self._write, ctypes.c_void_p).value
        raddr = ctypes.cast(self._read, ctypes.c_void_p).value
        assert addr and raddr
        return HardwareEntry(KIND_C, addr, raddr, name=self.name)


def is_compiled_class(cls: type) -> bool:
    """Whether ``cls``'s ``read`` and ``write`` are numba-jitted functions (the compiled
    Python form) rather than methods."""
    return all(
        isinstance(inspect.getattr_static(cls, n, None), CPUDispatcher)
        or isinstance(getattr(cls, n, None), CPUDispatcher)
        for n in ('read', 'write')
    )


def check_compiled_class(cls: type) -> None:
    """The compiled form's contract: ``write(state, isq_ref, load_torque)``, ``read(state,
    m)``, optional ``elapse(state, periods)``, each a numba dispatcher (DriveLibraryError)."""
    for name, n, call in (
        ('write', 3, 'write(state, isq_ref, load_torque)'),
        ('read', 2, 'read(state, m)'),
        ('elapse', 2, 'elapse(state, periods)'),
    ):
        fn = getattr(cls, name, None)
        if fn is None and name == 'elapse':
            continue
        if not isinstance(fn, CPUDispatcher):
            raise DriveLibraryError(
                f'{cls.__name__}.{name} is not numba-jitted: the compiled form takes '
                f'numba.njit functions on the class ({_DOC})'
            )
        params = inspect.signature(fn.py_func).parameters
        if len(params) != n:
            raise DriveLibraryError(f'{cls.__name__}.{call} is not its signature ({_DOC})')


_W_SIG = types.int32(types.CPointer(types.float64), types.int64, types.float64, types.float64)
_R_SIG = types.int32(types.CPointer(types.float64), types.int64, types.CPointer(types.float64))
_E_SIG = types.int32(types.CPointer(types.float64), types.int64, types.int64)


def _wrappers(write: Any, read: Any, elapse: Any) -> tuple[Any, Any, Any]:
    """C wrappers (numba cfuncs, no GIL) of a compiled class's functions, with the state
    (pointer, length) first: the loop calls them by address (KIND_CTX)."""

    @cfunc(_W_SIG)
    def w(ctx: Any, n: int, isq: float, load: float) -> Any:  # pragma: no cover - compiled
        return np.int32(write(carray(ctx, (n,)), isq, load))

    @cfunc(_R_SIG)
    def r(ctx: Any, n: int, m: Any) -> Any:  # pragma: no cover - compiled
        return np.int32(read(carray(ctx, (n,)), carray(m, (N_MEASUREMENT,))))

    e = None
    if elapse is not None:

        @cfunc(_E_SIG)
        def e(ctx: Any, n: int, periods: int) -> Any:  # pragma: no cover - compiled
            return np.int32(elapse(carray(ctx, (n,)), periods))

    return w, r, e


class CompiledClassHardware(_Measured):
    """A compiled hardware class's instance (module docstring) with the Python interface
    of a hardware class, and its C wrappers for the loop."""

    def __init__(self, inner: Any, name: str = '') -> None:
        cls = type(inner)
        self.name = name or f'{cls.__module__}:{cls.__name__}'
        check_compiled_class(cls)
        state = getattr(inner, 'state', None)
        if not (
            isinstance(state, np.ndarray)
            and state.dtype == np.float64
            and state.ndim == 1
            and state.flags.c_contiguous
            and state.flags.writeable
            and state.size > 0
        ):
            raise DriveLibraryError(
                f'{self.name}: the instance needs a writeable 1-D float64 array `state` '
                f"(the hardware's own words) ({_DOC})"
            )
        self.inner, self.state = inner, state
        self._write_fn, self._read_fn = cls.write, cls.read
        self._elapse_fn = getattr(cls, 'elapse', None)
        self.command_delay = getattr(inner, 'command_delay', 1)
        self._m = np.zeros(N_MEASUREMENT)
        self._meas = Measurement()
        self._wrapped: tuple[Any, Any, Any] | None = None

    def write(self, isq_ref: float, load_torque: float) -> None:
        self._check(int(self._write_fn(self.state, float(isq_ref), float(load_torque))), 'write')

    def read(self) -> Any:
        self._check(int(self._read_fn(self.state, self._m)), 'read')
        return self._fill(self._meas, self._m)

    def elapse(self, periods: int) -> None:
        if self._elapse_fn is not None:
            self._check(int(self._elapse_fn(self.state, int(periods))), 'elapse')

    def close(self) -> None:
        close = getattr(self.inner, 'close', None)
        if callable(close):
            close()

    def entry(self) -> HardwareEntry:
        """The C wrappers' addresses (compiled on the first call: a second or two)."""
        if self._wrapped is None:
            try:
                self._wrapped = _wrappers(self._write_fn, self._read_fn, self._elapse_fn)
            except Exception as exc:  # numba's typing error of the user's functions
                first = str(exc).strip().splitlines()
                raise DriveLibraryError(
                    f'{self.name}: its functions do not compile for the loop: '
                    f'{type(exc).__name__}: {first[0] if first else ""}'
                ) from None
        w, r, e = self._wrapped
        return HardwareEntry(
            KIND_CTX,
            w.address,
            r.address,
            e.address if e is not None else 0,
            self.state.ctypes.data,
            self.state.size,
            name=self.name,
        )
