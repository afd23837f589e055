"""The compiled loops' clock: the wait for each period start, in numba, and the schedule's
words it keeps. Every compiled 5 kHz loop of the workspace waits here (the composed
bench's, the host check's through :func:`run_schedule`, ``benchmarks/loop_floor.py``), so
that the host check measures the loop's own wait. The schedule is ``pacing.Pacer``'s, in
nanoseconds of CLOCK_MONOTONIC: the wait sleeps (``clock_nanosleep``, absolute) to
``T[T_SPIN]`` before the start and busy-waits the rest (``T_SPIN`` = 0: a pure sleep; >=
the period: a pure spin); a drive that cannot pause (``T[T_WALL]``) counts the whole
periods a late start skipped *missed*, else the schedule re-anchors.

The words of ``T`` (int64) that the wait reads and writes come first (``T_*`` here,
``N_CLOCK`` of them); a loop that keeps more words of its own puts them after.

Written by hand: no library runs a numba loop on a wall-clock schedule; the clock calls
are libc's (``types.ExternalFunction``).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import types

from .rt import SPIN_US

_clock_gettime = types.ExternalFunction('clock_gettime', types.int32(types.int32, types.uint64))
_clock_nanosleep = types.ExternalFunction(
    'clock_nanosleep', types.int32(types.int32, types.int32, types.uint64, types.uint64)
)
CLOCK_REALTIME, CLOCK_MONOTONIC, TIMER_ABSTIME = 0, 1, 1
NS = 1_000_000_000
#: The composed loop's busy-wait before each period start [ns] (``rt.SPIN_US``)
SPIN_NS = round(SPIN_US * 1000)

# -- the schedule's words of T (int64) ----------------------------------------------------
T_T0 = 0  #: the schedule's anchor [ns, CLOCK_MONOTONIC]: period n starts at t0 + n ts
T_N = 1  #: periods started since t0
T_TS = 2  #: the period [ns]
T_SPIN = 3  #: busy-wait before a start [ns] (0: sleep only; >= T_TS: spin only)
T_WALL = 4  #: 1: a drive that cannot pause (late starts skip whole periods, held)
T_OVERRUNS = 5  #: starts more than a period late
T_MISSED_TOTAL = 6  #: whole periods those starts skipped (wall clock)
T_MAX_LATE = 7  #: worst start lateness [ns]
T_LATE = 8  #: the last start's lateness [ns] (after a skip: from the period it became)
T_START = 9  #: the last period's start [ns]
T_MAX_LATE_AT = 10  #: when the worst late start was due [ns, CLOCK_MONOTONIC]
#: the worst lateness of the starts that followed Python (a call's first period: the
#: loop thread took the GIL, and ran Python, since the period before) [ns]
T_MAX_LATE_PY = 11
N_CLOCK = 12


@numba.njit(cache=True, nogil=True)
def now_ns(ts: np.ndarray, clock: int) -> int:
    """``clock``'s time [ns]; ``ts``: two int64 words of scratch (a ``struct timespec``)."""
    _clock_gettime(np.int32(clock), np.uint64(ts.ctypes.data))
    return ts[0] * NS + ts[1]


@numba.njit(cache=True, nogil=True)
def sleep_until(ts: np.ndarray, t_ns: int) -> None:
    """Sleep until CLOCK_MONOTONIC reads ``t_ns`` [ns] (absolute: no drift)."""
    ts[0] = t_ns // NS
    ts[1] = t_ns - ts[0] * NS
    p = np.uint64(ts.ctypes.data)
    _clock_nanosleep(np.int32(CLOCK_MONOTONIC), np.int32(TIMER_ABSTIME), p, np.uint64(0))


@numba.njit(cache=True, nogil=True)
def nap(ts: np.ndarray, ns: int) -> None:
    """Sleep ``ns`` nanoseconds from now."""
    sleep_until(ts, now_ns(ts, CLOCK_MONOTONIC) + ns)


@numba.njit(cache=True, nogil=True)
def wait_start(
    T: np.ndarray, late_hist: np.ndarray, edges: np.ndarray, ts: np.ndarray, first: bool
) -> int:
    """Wait for the next period start (``pacing.Pacer.wait``, in ns); returns the whole
    periods it skipped (a drive that cannot pause; else 0 and the schedule re-anchored).
    ``late_hist[b]`` counts the start in its lateness bin (``edges`` [ns]: the bins' upper
    edges); ``first``: the call's first period (Python ran since the period before)."""
    period = T[T_TS]
    deadline = T[T_T0] + (T[T_N] + 1) * period
    target = deadline - T[T_SPIN]
    if now_ns(ts, CLOCK_MONOTONIC) < target:
        sleep_until(ts, target)
    now = now_ns(ts, CLOCK_MONOTONIC)
    while now < deadline:
        now = now_ns(ts, CLOCK_MONOTONIC)
    late = now - deadline
    if late > T[T_MAX_LATE]:
        T[T_MAX_LATE] = late
        T[T_MAX_LATE_AT] = deadline
    if first and late > T[T_MAX_LATE_PY]:
        T[T_MAX_LATE_PY] = late
    b = 0
    for e in edges:
        if late < e:
            break
        b += 1
    late_hist[b] += 1
    T[T_N] += 1
    missed = 0
    if late > period:
        T[T_OVERRUNS] += 1
        if T[T_WALL] != 0:
            missed = late // period
            T[T_MISSED_TOTAL] += missed
            T[T_N] += missed
            late -= missed * period
        else:
            T[T_T0] = now - T[T_N] * period  # re-anchor: no burst of catch-up periods
    T[T_LATE] = late
    T[T_START] = now
    return missed


@numba.njit(cache=True, nogil=True)
def run_schedule(
    T: np.ndarray, held: np.ndarray, hist: np.ndarray, edges: np.ndarray, ts: np.ndarray
) -> None:
    """Wait for period after period until ``len(held)`` periods went by on the wall
    clock; ``held[n]``: the periods skipped (held) at period n's start."""
    n_max = len(held)
    while T[T_N] < n_max:
        n = T[T_N]
        missed = wait_start(T, hist, edges, ts, False)
        if missed > 0:
            held[min(n + 1, n_max - 1)] += missed
