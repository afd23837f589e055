"""Waiting for another process as long as it works: a slow machine is not a failure.

A fixed time limit on a child (a replay's controller, the recorder child) confuses a
loaded machine, where numba's compile and DDS discovery take tens of seconds, with a
broken child. Instead, a wait ends when the process sits idle: its
CPU time (itself and its descendants, from ``/proc``) grows by less than ``IDLE_CPU_S``
within ``idle_s`` of wall time. A process that works gets the time it needs, and the
wait says every ``NOTE_EVERY_S`` what it waits for. Linux only (``/proc``); elsewhere the
CPU time reads as 0, so the wait ends after ``idle_s``, as a plain time limit would.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

IDLE_S = 10.0  #: [s] of wall time
IDLE_CPU_S = 0.2  #: [s] of the process's CPU time within IDLE_S: less is idle
NOTE_EVERY_S = 10.0  #: [s] between lines saying what is waited for


def process_cpu_s(pid: int) -> float:
    """CPU time [s] the process ``pid`` and its descendants used so far (0: gone)."""
    total, todo, seen = 0.0, [pid], set()
    tick = os.sysconf('SC_CLK_TCK')
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            stat = Path(f'/proc/{p}/stat').read_text()
            fields = stat[stat.rindex(')') + 2 :].split()
            total += (int(fields[11]) + int(fields[12])) / tick  # utime, stime
            for task in Path(f'/proc/{p}/task').iterdir():
                todo += [int(c) for c in (task / 'children').read_text().split()]
        except (OSError, ValueError, IndexError):
            continue  # (gone meanwhile)
    return total


class Patience:
    """One wait on process ``pid``: :meth:`check` raises ``error(text)`` once the process
    has been idle for ``idle_s`` (the module docstring), and gives ``note`` a line every
    NOTE_EVERY_S; ``alive`` (optional) is called first, to raise on a process that died."""

    def __init__(
        self,
        pid: int,
        what: str,
        error: Callable[[str], Exception],
        *,
        idle_s: float = IDLE_S,
        note: Callable[[str], None] | None = None,
        alive: Callable[[], None] | None = None,
        cpu: Callable[[int], float] = process_cpu_s,
    ) -> None:
        self.pid, self.what, self.error, self.idle_s = pid, what, error, idle_s
        self.note, self.alive, self.cpu_of = note, alive, cpu
        self.t0 = self.busy_at = self.noted = time.monotonic()
        self.cpu = cpu(pid)

    def check(self) -> None:
        if self.alive is not None:
            self.alive()
        now = time.monotonic()
        cpu = self.cpu_of(self.pid)
        if cpu - self.cpu >= IDLE_CPU_S:  # it works: the idle window starts again
            self.cpu, self.busy_at = cpu, now
        elif now - self.busy_at > self.idle_s:
            raise self.error(
                f'{self.what}: none after {now - self.t0:.0f} s, the process idle for the '
                f'last {now - self.busy_at:.0f} s (it used {cpu - self.cpu:.2f} s of CPU)'
            )
        if self.note is not None and now - self.noted >= NOTE_EVERY_S:
            self.noted = now
            self.note(f'waiting for {self.what}: {now - self.t0:.0f} s (the process works)')
