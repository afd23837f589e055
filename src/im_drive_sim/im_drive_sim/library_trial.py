"""A C drive library tried once in a child process before the run loads it.

A library that crashes (SIGSEGV, SIGBUS of a truncated file, ``abort()`` in an
initialiser), ends the process (``exit()`` in ``im_drive_open``) or never returns would
take the run down without a word, or hang it; in a child it takes only the child, and
the run refuses it in one line naming the call (docs/real-drive.md, "A library that
crashes"). Used by :class:`.hardware_abi.LibraryHardware` before its own load.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

#: [s] a library's trial (load, im_drive_abi_version, im_drive_open, a write of zero and
#: im_drive_close, in a child process) must end within: a vendor's open that enumerates a
#: bus takes seconds; one that never returns is named, not waited for
TRIAL_TIMEOUT_S = 30.0

# The trial's child: the library's calls one by one, each announced before it is made, so
# that a crash or a hang is pinned to the call (stdlib only: it starts at once)
_TRIAL = """
import ctypes, os, sys
def say(what):
    os.write(1, (what + '\\n').encode())
path, drive_file, abi = sys.argv[1], sys.argv[2], int(sys.argv[3])
say('load')
try:
    lib = ctypes.CDLL(path, mode=ctypes.RTLD_LOCAL)
except OSError:  # not loadable: this process's own load says why
    say('done')
    sys.exit(0)
if hasattr(lib, 'im_drive_abi_version'):
    say('im_drive_abi_version')
    lib.im_drive_abi_version.restype = ctypes.c_int
    if lib.im_drive_abi_version() == abi and hasattr(lib, 'im_drive_open'):
        say('im_drive_open')
        lib.im_drive_open.argtypes, lib.im_drive_open.restype = [ctypes.c_char_p], ctypes.c_int
        if lib.im_drive_open(drive_file.encode() if drive_file else None) == 0:
            if hasattr(lib, 'im_drive_write'):
                say('im_drive_write')
                lib.im_drive_write.argtypes = [ctypes.c_double, ctypes.c_double]
                lib.im_drive_write(0.0, 0.0)
            if hasattr(lib, 'im_drive_close'):
                say('im_drive_close')
                lib.im_drive_close.restype = None
                lib.im_drive_close()
say('done')
"""
_TRIAL_STEP = {
    'load': 'loading it (its initialisers)',
    'im_drive_abi_version': 'im_drive_abi_version()',
    'im_drive_open': 'im_drive_open',
    'im_drive_write': 'im_drive_write(0.0, 0.0) after open',
    'im_drive_close': 'im_drive_close() after open',
}


def trial_library(path: Path, name: str, drive_file: bytes | None, abi_version: int) -> str:
    """Load and open the library at ``path`` once in a child process (then write zero
    and close it there), before this process loads it: a library that crashes
    (SIGSEGV, SIGBUS of a truncated file, abort()), ends the process (exit()) or never
    returns does so there; the one line that says so, naming the call ('' when the trial
    passed). A library that refuses (another ABI version, open returning non-zero)
    passes the trial: this process's load says why."""
    argv = [sys.executable, '-I', '-S', '-c', _TRIAL, str(path), (drive_file or b'').decode()]
    argv.append(str(abi_version))
    try:
        p = subprocess.run(
            argv, capture_output=True, text=True, timeout=TRIAL_TIMEOUT_S, check=False
        )
        steps, code = p.stdout.split(), p.returncode
    except subprocess.TimeoutExpired as exc:  # (run() killed the child by its PID)
        out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else exc.stdout or ''
        step = _TRIAL_STEP.get((out.split() or ['load'])[-1], 'it')
        return (
            f'{name}: {step} did not return within {TRIAL_TIMEOUT_S:g} s (tried in a child '
            'process; its calls must return: do blocking work in a thread of the library)'
        )
    if code == 0 and steps[-1:] == ['done']:
        return ''
    step = _TRIAL_STEP.get(steps[-1] if steps else 'load', 'it')
    if code < 0:
        try:
            what = f'crashed the process ({signal.Signals(-code).name})'
        except ValueError:
            what = f'killed the process (signal {-code})'
    else:
        what = f'ended the process (exit code {code})'
    return f'{name}: {step} {what}; tried in a child process, nothing else ran'
