"""A Ctrl-C while an executable starts, inside a ctypes callback (RosSession).

numba calls back into Python through ctypes as it compiles (its object cache). A signal
handler that raises KeyboardInterrupt there cannot unwind the start: Python prints the
exception as "Exception ignored on calling ctypes callback function" with a traceback
and goes on. The session keeps the signal (``stopped``) for the starting code to check,
and prints nothing of it.

The scenario runs in a child process (it owns the main thread and its signals).
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.unit

SCENARIO = r"""
import ctypes, json, os, signal, sys

from im_drive_sim.runtime import RosSession

def raise_interrupt(_signum):
    raise KeyboardInterrupt

def in_callback():
    os.kill(os.getpid(), signal.SIGINT)  # its handler runs at the next bytecode: here
    for _ in range(1000):
        pass

callback = ctypes.CFUNCTYPE(None)(in_callback)
case = sys.argv[1]
if case == 'session':
    session = RosSession(['test'], on_signal=raise_interrupt)
    try:
        callback()  # the interrupt is raised in the callback, swallowed there
        print(json.dumps({'stopped': session.stopped}), flush=True)
    finally:
        session.close()
else:  # the same callback without a session: what Python does on its own
    signal.signal(signal.SIGINT, lambda s, f: raise_interrupt(s))
    callback()
    print(json.dumps({'stopped': None}), flush=True)
"""


def _run(case: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, '-c', SCENARIO, case], capture_output=True, text=True, timeout=120
    )


def test_an_interrupt_swallowed_by_a_ctypes_callback_is_kept_and_not_printed() -> None:
    bare = _run('bare')
    # the mechanism is real: on its own, Python prints it and the code goes on
    assert bare.returncode == 0, bare.stderr
    assert 'Exception ignored on calling ctypes callback function' in bare.stderr
    assert 'KeyboardInterrupt' in bare.stderr

    p = _run('session')
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout.strip().splitlines()[-1]) == {'stopped': True}
    assert 'Exception ignored' not in p.stderr and 'Traceback' not in p.stderr, p.stderr
