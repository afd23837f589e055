"""Waiting for a child as long as it works (im_tuner.patience): a replay's controller or
the recorder child on a slow machine is waited for; one that sits idle without what is
waited for ends the wait. Judged on the process's own CPU time, on a clock the test
holds, and on real processes' /proc."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from im_tuner import patience as P


class Failed(Exception):
    pass


@pytest.fixture
def clock(monkeypatch):
    now = [1000.0]
    monkeypatch.setattr(P.time, 'monotonic', lambda: now[0])
    return now


def waiting(cpu: list[float], notes: list[str] | None = None) -> P.Patience:
    return P.Patience(
        4242, 'the command answering step 7', Failed,
        note=None if notes is None else notes.append, cpu=lambda _pid: cpu[0],
    )  # fmt: skip


def test_a_working_process_is_waited_for_however_long(clock):
    cpu, notes = [0.0], []
    wait = waiting(cpu, notes)
    for _ in range(600):  # 10 minutes, a slow machine: 0.25 s of CPU per 5 s
        clock[0] += 1.0
        cpu[0] += 0.05
        wait.check()
    assert len(notes) == 60 and notes[0].startswith('waiting for the command answering step 7')


def test_an_idle_process_without_the_answer_ends_the_wait(clock):
    cpu = [0.0]
    wait = waiting(cpu)
    cpu[0] += 1.0  # it worked (a compile), then diverged and sits idle
    clock[0] += 1.0
    wait.check()
    clock[0] += P.IDLE_S  # idle, not yet past the window
    cpu[0] += 0.01
    wait.check()
    clock[0] += 0.5
    with pytest.raises(Failed, match=r'step 7: none after 12 s, the process idle for the last'):
        wait.check()


def test_the_cpu_of_a_real_process_is_what_is_measured():
    busy = subprocess.Popen([sys.executable, '-c', 'while True: pass'])
    idle = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])
    try:
        before = [P.process_cpu_s(p.pid) for p in (busy, idle)]
        deadline = time.monotonic() + 30.0
        while P.process_cpu_s(busy.pid) - before[0] < 0.5 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert P.process_cpu_s(busy.pid) - before[0] >= 0.5  # a working process gains CPU
        assert P.process_cpu_s(idle.pid) - before[1] < P.IDLE_CPU_S  # a waiting one does not
    finally:
        for p in (busy, idle):
            p.kill()
            p.wait()
    assert P.process_cpu_s(busy.pid) == 0.0  # gone: nothing to count


WATCHED = """
import sys, time
from im_tuner.bench import drive_spec
drive_spec.CONSTRUCTOR_IDLE_S = 1.0
def busy():  # 3 s of computing (numba's compile on a loaded machine): waited for
    t = time.process_time()
    while time.process_time() - t < 3.0:
        pass
    return 'built'
print(drive_spec._watched("--drive 'm:Busy': Busy(config)", busy), flush=True)
drive_spec._watched("--drive 'm:Hangs': Hangs(config)", lambda: time.sleep(60))
print('returned', flush=True)
"""


def test_a_drive_constructor_that_never_returns_ends_the_process_in_one_line():
    """A hardware class's ``__init__`` is watched (drive_spec._watched): one that computes
    returns whatever it takes, one that sits idle ends the process with one line, exit 2
    (here with an idle limit of 1 s instead of 30)."""
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, '-c', WATCHED], capture_output=True, text=True, timeout=60)
    took = time.monotonic() - t0
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    assert p.stdout.split() == ['built'], p.stdout
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "--drive 'm:Hangs': Hangs(config) did not return" in lines[0]
    assert 'idle for 1 s' in lines[0], lines
    assert took < 30.0, took  # the 60 s sleep was not waited for
