"""The drive ABI (hardware_abi): the example's stand-in plant in its three forms (Python,
compiled class, C library) gives the same numbers; the loop's calls by address give what
the Python calls give; a library that cannot be used is refused in one line."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from numba import njit

from im_drive_sim import hardware_abi as H
from im_drive_sim.drive_file import load_config
from im_drive_sim.example_drive import Hardware
from im_drive_sim.example_hardware import CompiledHardware

PKG = Path(__file__).resolve().parents[1]
EXAMPLE_C = PKG / 'examples' / 'example_drive.c'
INCLUDE = PKG / 'include'
CC = shutil.which('cc') or shutil.which('gcc')
needs_cc = pytest.mark.skipif(CC is None, reason='no C compiler (cc) on this machine')


def commands(n: int, seed: int = 3) -> np.ndarray:
    """A seeded sequence of (isq_ref, load_torque) commands [A], [N m]."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-7.0, 7.0, n), rng.uniform(-1.0, 1.0, n)])


def measure(hw, cmds: np.ndarray, elapse_every: int = 0) -> np.ndarray:
    """Write each command, read; every ``elapse_every`` periods two unsampled ones."""
    out = np.zeros((len(cmds), 8))
    for i, (isq, load) in enumerate(cmds):
        if elapse_every and i % elapse_every == elapse_every - 1:
            hw.elapse(2)
        hw.write(isq, load)
        m = hw.read()
        out[i] = [getattr(m, f) for f in H.MEASUREMENT_FIELDS]
    return out


def build_example(tmp: Path, config, name: str = 'libexample.so', extra: tuple = ()) -> Path:
    """The C example built with ``config``'s constants (exact: repr of each float)."""
    m, s = config.machine, config.sensors
    defs = {
        'IM_TS': config.Ts,
        'IM_KT': m.Kt,
        'IM_J': m.J,
        'IM_B': m.B,
        'IM_ISD': m.rated_flux_current,
        'IM_POLE_PAIRS': float(m.pole_pairs),
        'IM_CURRENT_BANDWIDTH': config.control.current_bandwidth,
        'IM_SPEED_FILTER_TAU': s.speed_filter_tau,
        'IM_ENCODER_COUNTS': float(s.encoder_counts),
        'IM_COMMAND_DELAY': config.command_delay,
    }
    out = tmp / name
    cmd = [CC, '-O2', '-ffp-contract=off', '-shared', '-fPIC', f'-I{INCLUDE}']
    cmd += [f'-D{k}={v!r}' for k, v in defs.items()] + list(extra)
    subprocess.run([*cmd, '-o', str(out), str(EXAMPLE_C), '-lm'], check=True)
    return out


def build_c(tmp: Path, name: str, source: str) -> Path:
    src = tmp / f'{name}.c'
    src.write_text(source)
    out = tmp / f'lib{name}.so'
    subprocess.run([CC, '-shared', '-fPIC', f'-I{INCLUDE}', '-o', str(out), str(src)], check=True)
    return out


@pytest.mark.parametrize('delay', [1, 2])
def test_the_compiled_stand_in_is_the_python_one_bit_for_bit(delay: int) -> None:
    config = load_config(None, {'command_delay': delay})
    cmds = commands(3000)
    py = measure(Hardware(config), cmds, elapse_every=97)
    compiled = H.CompiledClassHardware(CompiledHardware(config), name='example')
    assert compiled.command_delay == delay
    got = measure(compiled, cmds, elapse_every=97)
    assert np.array_equal(py, got)
    assert np.abs(py[:, 0]).max() > 1.0  # the plant moved: a comparison of something


@needs_cc
@pytest.mark.parametrize('delay', [1, 2])
def test_the_c_example_is_the_python_stand_in_bit_for_bit(tmp_path: Path, delay: int) -> None:
    config = load_config(None, {'command_delay': delay})
    lib = H.LibraryHardware(build_example(tmp_path, config), config)
    assert lib.command_delay == delay
    cmds = commands(3000, seed=5)
    assert np.array_equal(measure(Hardware(config), cmds), measure(lib, cmds))
    lib.close()


@njit(cache=False)
def _by_address(E: np.ndarray, cmds: np.ndarray, out: np.ndarray) -> int:
    m = np.zeros(8)
    worst = 0
    for i in range(cmds.shape[0]):
        rc = H.call_write(E, cmds[i, 0], cmds[i, 1])
        rc = min(rc, H.call_read(E, m))
        worst = min(worst, rc)
        out[i] = m
    return worst


@needs_cc
def test_the_loop_calls_by_address_what_python_calls(tmp_path: Path) -> None:
    config = load_config(None)
    cmds = commands(2000, seed=9)
    want = measure(Hardware(config), cmds)
    for hw in (
        H.LibraryHardware(build_example(tmp_path, config), config),
        H.CompiledClassHardware(CompiledHardware(config), name='example'),
    ):
        out = np.zeros_like(want)
        assert _by_address(H.entry_words(hw.entry()), cmds, out) == 0
        assert np.array_equal(out, want), hw.name


def test_the_library_gets_the_drive_files_path(tmp_path: Path) -> None:
    if CC is None:
        pytest.skip('no C compiler (cc) on this machine')
    lib = build_c(
        tmp_path,
        'echo',
        '#include <stdio.h>\n#include <string.h>\nstatic char seen[4096];\n'
        'int im_drive_abi_version(void){ return 1; }\n'
        'int im_drive_open(const char *f){ snprintf(seen, sizeof seen, "%s", f ? f : "NULL");'
        ' return 0; }\nint im_drive_write(double a, double b){ return 0; }\n'
        'int im_drive_read(double m[8]){ memset(m, 0, 64); return strlen(seen); }\n',
    )
    drive_file = tmp_path / 'my_drive.yaml'
    drive_file.write_text('base: paper_750w\n')
    hw = H.LibraryHardware(lib, load_config(drive_file))
    hw.read()  # its return: the length of the path it was opened with
    assert hw._read(hw._m.ctypes.data) == len(str(drive_file.resolve()))
    assert H.LibraryHardware(lib, load_config(None)).command_delay == 1


GOOD = (
    'int im_drive_abi_version(void){ return 1; }\n'
    'int im_drive_open(const char *f){ return 0; }\n'
    'int im_drive_write(double a, double b){ return 0; }\n'
    'int im_drive_read(double m[8]){ return 0; }\n'
)


NO_READ = GOOD.replace('int im_drive_read', 'int other_read')
OPEN_FAILS = GOOD.replace('f){ return 0; }', 'f){ return -5; }')
DELAY_3 = GOOD + 'int im_drive_command_delay(void){ return 3; }\n'
NO_VERSION = GOOD.replace('int im_drive_abi_version', 'int other_version')
# open fails too: the version is checked, and the library refused, before open is called
VERSION_2 = OPEN_FAILS.replace('{ return 1; }', '{ return 2; }')
READ_FAULT = GOOD.replace('m[8]){ return 0; }', 'm[8]){ return -7; }')


@needs_cc
@pytest.mark.parametrize(
    'name, source, message',
    [
        ('noread', NO_READ, 'no function im_drive_read'),
        ('noversion', NO_VERSION, 'no function im_drive_abi_version: built against a header'),
        ('version2', VERSION_2, 'built for drive ABI version 2; this im_drive_sim calls version 1'),
        ('noopen', OPEN_FAILS, 'returned -5'),
        ('delay3', DELAY_3, 'im_drive_command_delay() returned 3: 1 or 2'),
    ],
)
def test_a_library_that_cannot_be_used_is_refused_in_one_line(
    tmp_path: Path, name: str, source: str, message: str
) -> None:
    lib = build_c(tmp_path, name, source)
    with pytest.raises(H.DriveLibraryError) as err:
        H.LibraryHardware(lib, load_config(None))
    text = str(err.value)
    assert message in text and text.startswith(f'lib:{lib}') and '\n' not in text


CRASHES = {
    'segv-in-open': (
        GOOD.replace('f){ return 0; }', 'f){ *(volatile int *)0 = 1; return 0; }'),
        'im_drive_open crashed the process (SIGSEGV)',
    ),
    'exit-in-open': (
        '#include <stdlib.h>\n' + GOOD.replace('f){ return 0; }', 'f){ exit(3); }'),
        'im_drive_open ended the process (exit code 3)',
    ),
    'abort-in-constructor': (
        '#include <stdlib.h>\n__attribute__((constructor)) static void boom(void){ abort(); }\n'
        + GOOD,
        'loading it (its initialisers) crashed the process (SIGABRT)',
    ),
    'segv-in-close': (
        GOOD + 'void im_drive_close(void){ *(volatile int *)0 = 1; }\n',
        'im_drive_close() after open crashed the process (SIGSEGV)',
    ),
}


@needs_cc
@pytest.mark.parametrize('name', sorted(CRASHES))
def test_a_library_that_crashes_is_named_in_one_line_and_never_loaded_here(
    tmp_path: Path, name: str
) -> None:
    """Tried in a child first: the crash happens there, this process goes on and says
    which call did it."""
    source, message = CRASHES[name]
    lib = build_c(tmp_path, name.replace('-', '_'), source)
    with pytest.raises(H.DriveLibraryError) as err:
        H.LibraryHardware(lib, load_config(None))
    text = str(err.value)
    assert text == f'lib:{lib}: {message}; tried in a child process, nothing else ran'


@needs_cc
def test_a_library_whose_open_never_returns_is_named(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from im_drive_sim import library_trial

    monkeypatch.setattr(library_trial, 'TRIAL_TIMEOUT_S', 2.0)
    source = '#include <unistd.h>\n' + GOOD.replace('f){ return 0; }', 'f){ for (;;) pause(); }')
    lib = build_c(tmp_path, 'hang', source)
    with pytest.raises(H.DriveLibraryError, match=r'im_drive_open did not return within 2 s'):
        H.LibraryHardware(lib, load_config(None))


@needs_cc
def test_a_truncated_library_is_refused_in_one_line(tmp_path: Path) -> None:
    lib = build_c(tmp_path, 'whole', GOOD)
    cut = tmp_path / 'libcut.so'
    cut.write_bytes(lib.read_bytes()[: lib.stat().st_size // 2])
    with pytest.raises(H.DriveLibraryError) as err:
        H.LibraryHardware(cut, load_config(None))
    text = str(err.value)
    assert text.startswith(f'lib:{cut}: ') and '\n' not in text
    assert 'cannot load' in text or 'crashed the process' in text, text


def test_the_header_and_the_loader_speak_one_abi_version() -> None:
    """The version the loader accepts is the header's; the example, built against the
    header, carries it (the other tests load it)."""
    import re

    header = (INCLUDE / 'im_drive.h').read_text()
    (version,) = re.findall(r'^#define IM_DRIVE_ABI_VERSION (\d+)$', header, re.M)
    assert int(version) == H.ABI_VERSION
    assert 'int im_drive_abi_version(void);' in header
    assert 'return IM_DRIVE_ABI_VERSION;' in EXAMPLE_C.read_text()


def test_a_missing_library_is_refused(tmp_path: Path) -> None:
    with pytest.raises(H.DriveLibraryError, match='no such file'):
        H.LibraryHardware(tmp_path / 'libnone.so', load_config(None))
    (tmp_path / 'libjunk.so').write_text('not a library')
    with pytest.raises(H.DriveLibraryError, match='cannot load'):
        H.LibraryHardware(tmp_path / 'libjunk.so', load_config(None))


@needs_cc
def test_a_negative_return_is_a_fault_naming_the_library(tmp_path: Path) -> None:
    lib = build_c(tmp_path, 'faulty', READ_FAULT)
    hw = H.LibraryHardware(lib, load_config(None))
    hw.write(1.0, 0.0)
    with pytest.raises(H.HardwareFault, match=r'lib:.*libfaulty.so: im_drive_read returned -7'):
        hw.read()


class NotCompiled:
    def __init__(self, config) -> None:
        self.state = np.zeros(3)

    @staticmethod
    @njit
    def write(state, isq_ref, load_torque):
        return 0

    @staticmethod
    def read(state, m):  # not jitted
        return 0


class NoState(CompiledHardware):
    def __init__(self, config) -> None:
        self.state = [0.0]


def test_a_compiled_class_that_breaks_the_contract_is_refused() -> None:
    assert H.is_compiled_class(CompiledHardware) and not H.is_compiled_class(Hardware)
    assert not H.is_compiled_class(NotCompiled)
    with pytest.raises(H.DriveLibraryError, match='read is not numba-jitted'):
        H.check_compiled_class(NotCompiled)
    with pytest.raises(H.DriveLibraryError, match='1-D float64 array `state`'):
        H.CompiledClassHardware(NoState(load_config(None)))


class _LatchedLate(Hardware):
    """Declares 1, acts with 2: every write takes effect a period later."""

    command_delay = 1

    def __init__(self, config) -> None:
        super().__init__(config)
        self._pending = (0.0, 0.0)

    def write(self, isq_ref: float, load_torque: float) -> None:
        super().write(*self._pending)
        self._pending = (isq_ref, load_torque)


@pytest.mark.parametrize('delay', [1, 2])
def test_the_delay_probe_finds_the_delay_a_stage_has(delay: int) -> None:
    from im_drive_sim.hardware_probe import REPEATS, probe_delay

    config = load_config(None, {'command_delay': delay})
    for hw in (Hardware(config), H.CompiledClassHardware(CompiledHardware(config))):
        p = probe_delay(hw, config.Ts, config.machine.isq_max, delay)
        assert p.onsets == (delay,) * REPEATS and p.ok, p
    slow = probe_delay(_LatchedLate(load_config(None)), 200e-6, 7.0, 1)
    assert slow.onsets == (2,) * REPEATS and not slow.ok
    assert 'k+2 (median of k+2, k+2, k+2, k+2, k+2; declared command delay 1)' in slow.text()
