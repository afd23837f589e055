"""replay waits for a live controller as long as it works (a slow machine), and stops on
one that sits idle without the answer (a diverged controller): judged on the controller
process's own CPU time, on a clock the test holds, and on real processes' /proc."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from im_tuner.replay import node as N


class FakeChild:
    def __init__(self) -> None:
        self.cpu = 0.0

    def check(self) -> None:
        pass

    def cpu_s(self) -> float:
        return self.cpu


@pytest.fixture
def clock(monkeypatch):
    now = [1000.0]
    monkeypatch.setattr(N.time, 'monotonic', lambda: now[0])
    return now


def test_a_working_controller_is_waited_for_however_long(clock):
    child, notes = FakeChild(), []
    wait = N._Patience(
        child, 'the command answering step 7', N.IDLE_S, N.ReplayFailed, notes.append
    )
    for _ in range(600):  # 10 minutes, a slow machine: 0.25 s of CPU per 5 s
        clock[0] += 1.0
        child.cpu += 0.05
        wait.check()
    assert len(notes) == 60 and notes[0].startswith('waiting for the command answering step 7')


def test_an_idle_controller_without_the_answer_ends_the_replay(clock):
    child = FakeChild()
    wait = N._Patience(child, 'the command answering step 7', N.IDLE_S, N.ReplayFailed, None)
    child.cpu += 1.0  # it worked (a compile), then diverged and sits idle
    clock[0] += 1.0
    wait.check()
    clock[0] += N.IDLE_S  # idle, not yet past the window
    child.cpu += 0.01
    wait.check()
    clock[0] += 0.5
    with pytest.raises(N.ReplayFailed, match=r'step 7: none after 12 s, the controller idle'):
        wait.check()


def test_the_cpu_of_a_real_process_is_what_is_measured():
    busy = subprocess.Popen([sys.executable, '-c', 'while True: pass'])
    idle = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])
    try:
        children = []
        for p in (busy, idle):
            c = object.__new__(N._Child)  # only the process: cpu_s reads /proc
            c.proc = p
            children.append(c)
        before = [c.cpu_s() for c in children]
        deadline = time.monotonic() + 30.0
        while children[0].cpu_s() - before[0] < 0.5 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert children[0].cpu_s() - before[0] >= 0.5  # a working process gains CPU
        assert children[1].cpu_s() - before[1] < N.IDLE_CPU_S  # a waiting one does not
    finally:
        for p in (busy, idle):
            p.kill()
            p.wait()
