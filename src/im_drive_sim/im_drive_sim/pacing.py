"""The wall-clock schedule of a real-time drive, its command watchdog and where it takes
its commands.

Every real-time loop of the project -- the drive nodes' (``drive_io.run_realtime``) and
the composed bench's (``im_tuner.bench.realtime``, which runs a ``drive_io.DriveNode``
period by period) -- paces its periods with one :class:`Pacer`.

Pure Python but for :class:`DurationHistograms` (one compiled call a period). Nothing here
allocates per period.
"""

from __future__ import annotations

import bisect
import time
from collections.abc import Callable
from typing import Any

import numba
import numpy as np

#: Upper edges [us] of the period-start lateness histogram (``Pacer.lateness_hist``; the
#: last bin has no upper edge): within 10 us, 50, 200 (one period), 1 ms, 10 ms, beyond.
LATENESS_EDGES_US: tuple[float, ...] = (10.0, 50.0, 200.0, 1000.0, 10000.0)
LATENESS_BINS: tuple[str, ...] = ('<10us', '<50us', '<200us', '<1ms', '<10ms', '>=10ms')


class Pacer:
    """Period n starts at ``t0 + n ts`` on ``time.perf_counter``; the loop sleeps in the
    drive's command wait (taking commands as they come) and busy-waits the last
    ``spin_margin`` for a precise start; a start more than one period late is an
    *overrun*, and no burst of catch-up periods follows (``wall_clock`` below).

    ``overruns``: periods that started more than a period late; ``max_lateness_us``: the
    worst start lateness [us]; ``lateness_s``: the last period's; ``lateness_hist``:
    period starts per lateness bin (:data:`LATENESS_BINS`).

    ``wall_clock``: the drive cannot pause (a real power stage; the simulator in its
    hardware-like mode). A period that starts late by m >= 1 whole periods then is the
    period m periods further on: ``missed`` = m periods went by with the old command held
    (the drive counts them held and advances its step index by them), and the schedule
    stays on the wall clock. Otherwise (a simulated drive that pauses) the schedule is
    re-anchored and ``missed`` is 0: simulated time waits for the loop.
    """

    def __init__(self, ts: float, spin_margin: float, wall_clock: bool = False) -> None:
        if not ts > 0.0:
            raise ValueError(f'period must be > 0 s, got {ts!r}')
        if not 0.0 <= spin_margin <= ts:
            raise ValueError(f'spin margin must be in [0, {ts}] s, got {spin_margin!r}')
        self.ts = float(ts)
        self.spin_margin = float(spin_margin)
        self.t0 = time.perf_counter()
        self.n = 0  #: periods started since t0
        self.deadline = self.t0  #: start of the current period
        self.overruns = 0
        self.max_lateness_us = 0.0
        self.lateness_s = 0.0
        self.lateness_hist = [0] * len(LATENESS_BINS)
        self.wall_clock = bool(wall_clock)
        self.missed = 0  #: whole periods the last start skipped (wall_clock only)
        self.missed_total = 0  #: their sum since t0

    def restart(self) -> None:
        """Start the schedule now (period 0 starts now, the next one Ts later)."""
        self.t0 = self.deadline = time.perf_counter()
        self.n = 0

    def wait(self, sleep: Callable[[float], bool], on_wake: Callable[[], None]) -> float:
        """Wait for the next period start and return it (perf_counter [s]).

        ``sleep(s)`` sleeps up to s seconds and returns True when woken by work, which
        ``on_wake()`` then does (a drive: ``wait_command`` / ``take_commands``)."""
        deadline = self.t0 + (self.n + 1) * self.ts
        while True:
            remaining = deadline - time.perf_counter() - self.spin_margin
            if remaining <= 0.0:
                break
            if sleep(remaining):
                on_wake()
        while time.perf_counter() < deadline:
            pass  # busy-wait the last stretch: a precise period start
        now = time.perf_counter()
        late = now - deadline
        self.lateness_s = late
        late_us = late * 1e6
        if late_us > self.max_lateness_us:
            self.max_lateness_us = late_us
        self.lateness_hist[bisect.bisect_right(LATENESS_EDGES_US, late_us)] += 1
        self.n += 1
        self.missed = 0
        if late > self.ts:
            self.overruns += 1
            if self.wall_clock:
                # the periods that went by: the drive held its command over them
                m = int(late // self.ts)
                self.missed = m
                self.missed_total += m
                self.n += m
                deadline += m * self.ts
                self.lateness_s = now - deadline
            else:
                self.t0 = now - self.n * self.ts  # re-anchor: no burst of catch-up periods
                deadline = now
        self.deadline = deadline
        return deadline


class CommandWatchdog:
    """A drive's command watchdog: no command for ``timeout_s`` -> expired.

    It expires on wall time, or after ``timeout_s / ts`` periods run, whichever comes
    first -- but only once two periods ran without a command: a loop that paused (the
    composed bench while the tuner works; a stall) takes the commands that came before it
    checks, and must not trip because the loop itself paused. Before the first command
    it never expires (the drive already holds zero current).
    """

    def __init__(self, timeout_s: float, ts: float) -> None:
        self.timeout_s = float(timeout_s)
        self.max_periods = max(1, round(timeout_s / ts))
        self.since = -1  #: periods since the last command (-1: none yet)
        self.last_wall = 0.0  #: perf_counter of the last command
        #: it expired and no command resumed the drive since (the drive holds zero current)
        self.tripped = False

    def command(self) -> None:
        """A valid command came."""
        self.since = 0
        self.last_wall = time.perf_counter()

    def expired(self) -> bool:
        """Call once per period, after taking the commands: is the watchdog expired?"""
        if self.since < 0:
            return False
        self.since += 1
        return self.since >= 2 and (
            self.since > self.max_periods or time.perf_counter() - self.last_wall > self.timeout_s
        )

    def trip(self) -> bool:
        """The drive found it :meth:`expired` this period: True the first time since the
        last :meth:`resume` (the drive counts the trip and says so once)."""
        newly = not self.tripped
        self.tripped = True
        return newly

    def resume(self) -> bool:
        """A command resumes the drive: True when the watchdog had tripped (say so once)."""
        was = self.tripped
        self.tripped = False
        return was


class CommandSource:
    """Where a drive takes its commands: the ``drive/command`` subscription (raw CDR,
    our compact layout read in place), or -- composed with the controller in one loop
    (``im_tuner.bench.realtime``) -- the command the controller handed over in memory
    (:meth:`hand_over`): no DDS between the controller's answer and the drive's write.

    :meth:`next` returns the values of the next command (a sequence of
    ``len(COMMAND_FIELDS)`` floats, or another length for a malformed message the drive
    then refuses) or None when none is pending."""

    def __init__(self, subscription: Any, n: int) -> None:
        self.subscription = subscription
        self.n = n
        self._handed: Any = None  #: the controller's command values (direct mode)
        self._pending = False

    def hand_over(self, values: Any) -> None:
        """The controller's newest command (its reused values array), for the next take."""
        self._handed = values
        self._pending = True

    def next(self) -> Any:
        if self._handed is not None:
            if not self._pending:
                return None
            self._pending = False
            return self._handed
        from std_msgs.msg import Float64MultiArray

        from .cdr import read_float64_array

        r = self.subscription.handle.take_message(Float64MultiArray, True)
        return None if r is None else read_float64_array(r[0], self.n)


@numba.njit(cache=True)
def count_durations(counts: Any, maxes: Any, values: Any) -> None:  # pragma: no cover (compiled)
    """Count ``values[r]`` [us] in row r of ``counts`` (1 us bins, the last one for every
    longer duration; a negative or NaN one in bin 0) and keep each row's maximum."""
    limit = counts.shape[1] - 1
    for r in range(len(values)):
        us = values[r]
        i = 0
        if us >= 0.0:
            i = min(int(us), limit)
        counts[r, i] += 1
        if us > maxes[r]:
            maxes[r] = us


class DurationHistograms:
    """Durations [us] of several kinds (``names``), one of each per period, counted in
    1 us bins up to ``limit_us`` (longer ones in the last bin) with the exact maxima: a
    fixed few hundred kB per kind for a run of any length (a real-time loop's memory
    must not grow), percentiles to within a microsecond. :meth:`add` takes one value of
    each kind in a single compiled call."""

    def __init__(self, names: tuple[str, ...], limit_us: int = 20_000) -> None:
        self.names = tuple(names)
        self.limit = int(limit_us)
        self.counts = np.zeros((len(self.names), self.limit + 1), np.int64)
        self.maxes = np.zeros(len(self.names))
        self.n = 0
        # compile (or load) the kernel for this many kinds now, not in a period; this
        # also touches every page of the counts
        count_durations(self.counts, self.maxes, (0.0,) * len(self.names))
        self.counts.fill(0)
        self.maxes.fill(0.0)

    def add(self, values: tuple[float, ...]) -> None:
        """One period's durations [us], one per name, in the order of ``names``."""
        count_durations(self.counts, self.maxes, values)
        self.n += 1

    def percentile(self, name: str, q: float) -> float:
        """The q-th percentile [us] of ``name`` (the middle of its 1 us bin; nan when
        empty)."""
        if self.n == 0:
            return float('nan')
        r = self.names.index(name)
        rank = max(1, int(np.ceil(q / 100.0 * self.n)))
        i = int(np.searchsorted(np.cumsum(self.counts[r]), rank))
        return min(i + 0.5, float(self.maxes[r]))

    def summary(self, name: str) -> dict[str, float] | None:
        """p50, p99 and max [us] of ``name``, rounded to 0.1 us (None when empty)."""
        if self.n == 0:
            return None
        return {
            'p50': round(self.percentile(name, 50), 1),
            'p99': round(self.percentile(name, 99), 1),
            'max': round(float(self.maxes[self.names.index(name)]), 1),
        }
