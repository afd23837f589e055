"""The declared command delay, measured: a short latency probe of a power stage before a
composed bench runs it (``tuner --bench realtime --drive ...``; issue 38).

A drive that acts on a command two periods after it while declaring one period makes
every experiment's labels lie (the controller counts fresh periods that were not) and
its losses are not the paper's. ``check_drive`` catches it over the topics; here the
same test runs on the power stage itself (its ``write``/``read``, whatever its form:
a Python hardware class, a compiled class, a C library), paced on the wall clock:

1. hold zero current for ``BASELINE`` periods, reading each period (the course of isq
   and its noise);
2. write a q-current step of ``STEP_FRACTION`` x isq_max (signs alternate) for ``ON``
   periods, reading each, then zero again for ``SETTLE`` periods;
3. the *onset* of the step is the first read after its write (1 = the read of the
   period that starts with the write) in which isq leaves its course by more than
   2 % of the step or 8 noise levels (check_drive's rule).

With command delay d the onset is d (the power stage applies the command over the
period that starts d - 1 periods after the write). A probe period that starts late (by
more than half a period: the process was preempted) is not caught up: the schedule moves
on from it, since writes bunched to catch up could all land in one of the power stage's
periods and the step never be applied; a repeat with a late period is run again (at most
``REPEATS`` extra). Repeated ``REPEATS`` times; what lateness is left only makes an onset
later, so the fastest one is judged: a drive whose
fastest onset is later than it declares is slower than it declares, and the bench
refuses it in one line. The motion is small: ``ON`` periods of a tenth of the current
limit, about 0.1 degree on the packaged motor.

Written by hand: the probe is a few dozen calls of the drive's own interface.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ['DelayProbe', 'probe_delay']

BASELINE = 8  #: periods of zero current before each step
ON = 3  #: periods the step is held
SETTLE = 12  #: periods of zero current after it
REPEATS = 4
STEP_FRACTION = 0.1  #: of isq_max
MAX_ONSET = 6  #: reads after the write looked at


@dataclass(frozen=True)
class DelayProbe:
    """The probe's result: the onset of each step [periods] (0: not seen within
    MAX_ONSET reads), the declared delay, and whether the drive is as fast as declared."""

    onsets: tuple[int, ...]
    declared: int

    @property
    def fastest(self) -> int:
        seen = [o for o in self.onsets if o > 0]
        return min(seen) if seen else 0

    @property
    def ok(self) -> bool:
        """Not slower than declared (a step never seen is not judged: a drive whose isq
        does not follow its reference is check_drive's concern)."""
        return self.fastest == 0 or self.fastest <= self.declared

    def text(self) -> str:
        seen = ', '.join(f'k+{o}' if o else 'not seen' for o in self.onsets)
        return f'a current step takes effect in {seen} (declared command delay {self.declared})'


def probe_delay(hw: Any, ts: float, isq_max: float, declared: int) -> DelayProbe:
    """Run the probe on ``hw`` (``write(isq_ref, load_torque)``, ``read()`` -> a
    Measurement) with period ``ts`` [s] and current limit ``isq_max`` [A]; it ends with
    zero current written."""
    step = STEP_FRACTION * isq_max
    onsets = []
    t0 = time.perf_counter()
    n = 0
    late = False

    def period(isq_ref: float) -> float:
        nonlocal n, t0, late
        n += 1
        deadline = t0 + n * ts
        now = time.perf_counter()
        if now > deadline + 0.5 * ts:  # preempted: move on from here, no burst to catch up
            late = True
            t0 += now - deadline
        while time.perf_counter() < deadline:  # busy-wait: a few ms in all
            pass
        hw.write(isq_ref, 0.0)
        m = hw.read()
        if not hasattr(m, 'isq'):
            raise TypeError(f'read() returned {type(m).__name__}, not a Measurement')
        return float(m.isq)

    try:
        r = again = 0
        while r < REPEATS:
            sign = 1.0 if r % 2 == 0 else -1.0
            late = False
            base = np.array([period(0.0) for _ in range(BASELINE)])
            after = [period(sign * step) for _ in range(ON)]
            after += [period(0.0) for _ in range(SETTLE)]
            # the course: the line through the baseline; the noise: its residual
            k = np.arange(BASELINE)
            slope, icpt = np.polyfit(k, base, 1)
            noise = float(np.std(base - (slope * k + icpt)))
            thr = max(0.02 * step, 8.0 * noise)
            onset = 0
            for i, x in enumerate(after[:MAX_ONSET]):
                if abs(x - (slope * (BASELINE + i) + icpt)) > thr:
                    onset = i + 1
                    break
            if late and again < REPEATS:  # this repeat was preempted: run it again
                again += 1
                continue
            onsets.append(onset)
            r += 1
    finally:
        hw.write(0.0, 0.0)
    return DelayProbe(tuple(onsets), int(declared))
