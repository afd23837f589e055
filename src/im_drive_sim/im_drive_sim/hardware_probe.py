"""The declared command delay, measured: a short latency probe of a power stage (its
``write``/``read``, whatever its form) before a composed bench runs it (``tuner --bench
realtime --drive ...``). The steps, the onset rule and why the repeats' phases are spread
over the period: docs/real-drive.md, "Command delay"; a drive whose median onset is later
than it declares is refused in one line.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

BASELINE = 8  #: periods of zero current before each step
ON = 3  #: periods the step is held
SETTLE = 12  #: periods of zero current after it
REPEATS = 5  #: odd: the median is one of them
STEP_FRACTION = 0.1  #: of isq_max
MAX_ONSET = 6  #: reads after the write looked at
LATE = 0.5  #: a period starting this late [periods] is not caught up, its repeat rerun
JITTER = 0.2  #: spread of the read times around the step [periods] that reruns a repeat


@dataclass(frozen=True)
class DelayProbe:
    """The probe's result: the onset of each step [periods] (0: not seen within
    MAX_ONSET reads), the declared delay, and whether the drive is as fast as declared."""

    onsets: tuple[int, ...]
    declared: int

    @property
    def onset(self) -> int:
        """The judged onset [periods]: the median of the onsets seen (the upper one of
        an even count); 0 when no step was seen."""
        seen = sorted(o for o in self.onsets if o > 0)
        return seen[len(seen) // 2] if seen else 0

    @property
    def ok(self) -> bool:
        """Not slower than declared (a step never seen is not judged: a drive whose isq
        does not follow its reference is check_drive's concern)."""
        return self.onset == 0 or self.onset <= self.declared

    def text(self) -> str:
        seen = ', '.join(f'k+{o}' if o else 'not seen' for o in self.onsets)
        judged = f'k+{self.onset}' if self.onset else 'not seen'
        return (
            f'a current step takes effect in {judged} (median of {seen}; '
            f'declared command delay {self.declared})'
        )


def probe_delay(hw: Any, ts: float, isq_max: float, declared: int) -> DelayProbe:
    """Run the probe on ``hw`` (``write(isq_ref, load_torque)``, ``read()`` -> a
    Measurement) with period ``ts`` [s] and current limit ``isq_max`` [A]; it ends with
    zero current written."""
    step = STEP_FRACTION * isq_max
    onsets = []
    t0 = time.perf_counter()
    n = 0
    late = False

    def period(isq_ref: float) -> tuple[float, float]:
        """One probe period: wait for its deadline, write, read; (isq [A], the time the
        read returned, after the deadline [s])."""
        nonlocal n, t0, late
        n += 1
        deadline = t0 + n * ts
        now = time.perf_counter()
        if now > deadline + LATE * ts:  # preempted: move on by whole periods, no burst
            late = True
            skip = math.ceil((now - deadline) / ts)
            t0 += skip * ts
            deadline += skip * ts
        while time.perf_counter() < deadline:  # busy-wait: a few ms in all
            pass
        hw.write(isq_ref, 0.0)
        m = hw.read()
        lag = time.perf_counter() - deadline
        if not hasattr(m, 'isq'):
            raise TypeError(f'read() returned {type(m).__name__}, not a Measurement')
        return float(m.isq), lag

    try:
        r = again = 0
        while r < REPEATS:
            sign = 1.0 if r % 2 == 0 else -1.0
            late = False
            t0 += ts / REPEATS  # this repeat's phase: 1/REPEATS of a period on
            base_lags = [period(0.0) for _ in range(BASELINE)]
            after_lags = [period(sign * step) for _ in range(ON)]
            after_lags += [period(0.0) for _ in range(SETTLE)]
            base = np.array([x for x, _ in base_lags])
            after = [x for x, _ in after_lags]
            # the read times from the last zero before the step to the last read judged
            lags = [base_lags[-1][1]] + [lag for _, lag in after_lags[:MAX_ONSET]]
            jittered = max(lags) - min(lags) > JITTER * ts
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
            if (late or jittered) and again < REPEATS:  # disturbed: run it again
                again += 1
                continue
            onsets.append(onset)
            r += 1
    finally:
        hw.write(0.0, 0.0)
    return DelayProbe(tuple(onsets), int(declared))
