"""A Ctrl-C that lands on a fork is raised after it, never lost (im_drive_sim.cli).

Python runs its at-fork callbacks (logging's lock among them) with a signal's exception
printed as "Exception ignored" and dropped: a Ctrl-C landing there would let the program
go on as if never interrupted. The script below lands one there on purpose, by an at-fork
callback that raises SIGINT in the parent."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

import pytest

from im_drive_sim.cli import held_interrupts

SCRIPT = textwrap.dedent(
    """
    import os, signal, subprocess, sys
    from im_drive_sim.cli import spawn_child

    fired = []

    def ctrl_c_on_the_fork():
        if not fired:
            fired.append(1)
            signal.raise_signal(signal.SIGINT)

    os.register_at_fork(before=ctrl_c_on_the_fork)
    try:
        if sys.argv[1] == 'spawn_child':
            child = spawn_child(['true'])
        else:
            child = subprocess.Popen(['true'], preexec_fn=lambda: None)
    except KeyboardInterrupt:
        print('interrupted', flush=True)
        sys.exit(130)
    child.wait()
    print('went on', flush=True)
    """
)


def _run(how: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, '-c', SCRIPT, how], capture_output=True, text=True, timeout=60
    )


def test_a_ctrl_c_during_spawn_child_is_raised_after_the_fork() -> None:
    r = _run('spawn_child')
    assert (r.returncode, r.stdout.strip()) == (130, 'interrupted'), r.stderr
    assert 'Exception ignored' not in r.stderr


def test_the_same_ctrl_c_on_a_plain_popen_is_lost() -> None:
    # the failure spawn_child exists for, shown on this interpreter
    r = _run('popen')
    assert (r.returncode, r.stdout.strip()) == (0, 'went on'), r.stderr
    assert 'Exception ignored' in r.stderr and 'KeyboardInterrupt' in r.stderr


def test_held_interrupts_raises_at_the_end_of_the_block_not_inside() -> None:
    reached = []
    with pytest.raises(KeyboardInterrupt), held_interrupts():
        signal.raise_signal(signal.SIGINT)
        reached.append('after the signal')
    assert reached == ['after the signal']
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_held_interrupts_without_a_ctrl_c_changes_nothing() -> None:
    with held_interrupts():
        x = 1 + 1
    assert x == 2
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
