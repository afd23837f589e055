"""The composed real-time loop's compiled kernels (``tuner --bench realtime``, the default
drive) and the words they share with Python (``T_*``: the schedule and its figures;
``G_*``: the gate; ``EV_*``: the event ring; ``M_*``: the messages). Compiled so that no
Python thread beside the loop can delay a period start (docs/real-drive.md, "How the
composed loop runs"); the Python side is :mod:`.compiled_loop`.

:func:`run_periods` runs period after period, each: wait for the start
(``loop_clock.wait_start``: sleep to the spin margin, then busy-wait); the drive's period
(``period_kernel.run_period``) and its messages into the outbox's rings; the controller's
answer (``im_controller.kernel.answer_state``) into the rings; the drive takes the answer
(``period_kernel.take_command``); the durations into the histograms.
:func:`run_hardware_periods` is the same loop around a user's power stage called by
address (``im_drive_sim.hardware_period``).

What needs Python comes through shared words, never the GIL: a thread's turn at the
nodes' state parks the loop between two periods (``G_WANT``, ``G_PARKED``:
``compiled_loop.LoopGate``); an experiment's end goes into an event ring the serving
thread hands to the controller; ``G_STOP`` (set by ``im_drive_sim.stop_signal`` on SIGINT
or SIGTERM) zeroes the current from the next period.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from im_controller.kernel import W_INTERNALS_DUE, answer_state
from im_controller.layout import STATUS_DONE, STATUS_FAULT
from im_drive_sim import hardware_period as HP, period_kernel as PK
from im_drive_sim.loop_clock import (
    CLOCK_MONOTONIC,
    CLOCK_REALTIME,
    N_CLOCK,
    T_LATE,
    T_START,
    nap as _nap,
    now_ns as _now,
    wait_start as _wait_start,
)
from im_drive_sim.outbox import R_HEAD, put_slot
from im_drive_sim.pacing import count_durations

# -- the words of T (int64): the schedule's first (im_drive_sim.loop_clock), then the loop's
T_EXIT = N_CLOCK + 0  #: why the last call returned (EXIT_*)
T_STATUS = N_CLOCK + 1  #: the last experiment status >= STATUS_DONE
T_PERIODS = N_CLOCK + 2  #: periods run since the caller zeroed it
T_RESUME = N_CLOCK + 3  #: a period under way: its missed steps still to run (-1: none)
T_MAX_PERIODS = N_CLOCK + 4  #: the call's limit
T_COMMANDS = N_CLOCK + 5  #: commands the drive took since the caller zeroed it
T_REFUSED = N_CLOCK + 6  #: answers the drive refused (not finite), since the loop was made
T_STALL = N_CLOCK + 7  #: the drive's stall test hook: its step (-1: none)
T_STALL_NS = N_CLOCK + 8  #: the stall test hook's duration [ns]
#: the last period's experiment status (a FAULT is an event once, not each period)
T_LAST_ST = N_CLOCK + 9
N_T = N_CLOCK + 10

EXIT_BUDGET, EXIT_PERIODS, EXIT_QUIT, EXIT_FAULT = range(4)

# -- the words of the gate (int64), shared with the Python threads (LoopGate) -------------
G_WANT = 0  #: != 0: a Python thread wants the loop parked (its turn at the nodes' state)
G_PARKED = 1  #: 1: the loop is parked between two periods (set and cleared by the loop)
G_STOP = 2  #: != 0: safe stop (zero current, latched) from the next period on
G_QUIT = 3  #: != 0: return (after a waiter's turn)
G_RUNNING = 4  #: 1: the loop's compiled run is on (cleared by the loop when it quits)
N_G = 5

#: experiment ends the loop leaves for the serving thread: status, step, then R
EVENT_CAPACITY = 64
EV_HEAD, EV_TAIL, EV_LOST = range(3)

# the messages, in the order of the rings' sources
M_STATE, M_CLOCK, M_JOINT, M_COMMAND, M_INTERNALS = range(5)
N_MSG = 5


@numba.njit(cache=True, nogil=True)
def _answer_and_hand_over(
    loop: Any, t0: int, due: int, D: np.ndarray, DC: np.ndarray, state: np.ndarray,
    ctl: Any, out: Any,
) -> None:  # fmt: skip
    """A period's second half, once the drive published state k+1 (``due``: its
    messages): the controller's answer, the messages into their rings, the drive takes
    the answer (``period_kernel.take_command``: the words of ``D`` it shares with every
    drive), the period's durations, an experiment's end into the event ring. ``loop``,
    ``ctl``, ``out``: :func:`run_periods`' groups of arrays."""
    T, _hist, _edges, dur_counts, dur_maxes, _gate, events, ev_ctrl, ts = loop
    R, Q, X, C, CF, cout, eout, cmd, internals, W = ctl
    raws, bufs, lens, stamps, ctrls, ring_msg, put_counts = out
    n_rings = len(bufs)
    n_r = R.shape[0]
    stamp = _now(ts, CLOCK_REALTIME)
    t1 = _now(ts, CLOCK_MONOTONIC)
    st = answer_state(R, Q, X, C, CF, state, cout, eout, cmd, internals, W)
    due |= 1 << M_COMMAND
    if W[W_INTERNALS_DUE] != 0:
        due |= 1 << M_INTERNALS
    # the messages into their rings (the heads advance after the clock call below:
    # an opaque call, so the slots are written before a consumer can see them)
    put = 0
    for m in range(N_MSG):
        if due & (1 << m):
            put_counts[m] += 1
    for r in range(n_rings):
        m = ring_msg[r]
        if due & (1 << m) and put_slot(bufs[r], lens[r], stamps[r], ctrls[r], raws[m], stamp):
            put |= 1 << r
    t2 = _now(ts, CLOCK_MONOTONIC)
    if PK.take_command(D, DC, np.int64(state[0]), cmd[0], cmd[1], cmd[2]):
        T[T_COMMANDS] += 1
    else:
        T[T_REFUSED] += 1
    t3 = _now(ts, CLOCK_MONOTONIC)
    for r in range(n_rings):
        if put & (1 << r):
            ctrls[r][R_HEAD] += 1
    count_durations(
        dur_counts,
        dur_maxes,
        ((t1 - t0) * 1e-3, (t2 - t1) * 1e-3, (t3 - t0) * 1e-3, T[T_LATE] * 1e-3),
    )
    T[T_PERIODS] += 1
    # an experiment's end, or the step into FAULT (the kernel answers STATUS_FAULT every
    # period it stays there): the serving thread publishes it
    first = not (st == STATUS_FAULT and T[T_LAST_ST] == STATUS_FAULT)
    T[T_LAST_ST] = st
    if st >= STATUS_DONE and first:
        T[T_STATUS] = st
        h = ev_ctrl[EV_HEAD]
        if h - ev_ctrl[EV_TAIL] < events.shape[0]:
            row = events[h % events.shape[0]]
            row[0] = st
            row[1] = state[0]
            for j in range(n_r):
                row[2 + j] = R[j]
            _now(ts, CLOCK_MONOTONIC)  # an opaque call: the row is written first
            ev_ctrl[EV_HEAD] = h + 1
        else:
            ev_ctrl[EV_LOST] += 1


@numba.njit(cache=True, nogil=True)
def _park(gate: np.ndarray, ts: np.ndarray) -> bool:
    """Between two periods: park while a Python thread has its turn at the nodes'
    state (``gate[G_WANT]``, :class:`LoopGate`); True if it parked."""
    if gate[G_WANT] == 0:
        return False
    gate[G_PARKED] = 1
    while gate[G_WANT] != 0:
        _nap(ts, 20_000)
    gate[G_PARKED] = 0
    return True


@numba.njit(cache=True, nogil=True)
def _must_return(T: np.ndarray, gate: np.ndarray) -> int:
    """Between two periods, after the gate: why the loop returns now (EXIT_QUIT:
    ``gate[G_QUIT]``, the loop's run marked off; EXIT_PERIODS: ``T[T_MAX_PERIODS]``
    reached), or -1 (it goes on)."""
    if gate[G_QUIT] != 0:
        gate[G_RUNNING] = 0
        return EXIT_QUIT
    if T[T_PERIODS] >= T[T_MAX_PERIODS]:
        return EXIT_PERIODS
    return -1


@numba.njit(cache=True, nogil=True)
def run_periods(
    S: np.ndarray,
    P: np.ndarray,
    noise: np.ndarray,
    budget: int,
    loop: Any,
    drive: Any,
    ctl: Any,
    out: Any,
) -> int:
    """Periods (module docstring) until ``gate[G_QUIT]`` or ``T[T_MAX_PERIODS]``,
    stepping the model at most ``budget`` times (``DriveSim.run_kernel``'s count: the
    noise block). Returns the model steps taken; ``T[T_EXIT]`` says why it returned;
    ``T[T_PERIODS]`` counts the periods run.

    The arrays come in groups (tuples; ``compiled_loop.CompiledPeriods`` makes them):
    ``loop`` = (T, the lateness histogram and its edges [ns], the duration counts and
    maxima, gate, events, the event ring's words, ts), the loop's own words; ``drive`` =
    (D, DC, state, clock, joint), the drive's (``period_kernel.run_period``);
    ``ctl`` = (R, Q, X, C, CF, cout, eout, cmd, internals, W), the controller's
    (``im_controller.kernel.answer_state``); ``out`` = (raws, bufs, lens, stamps, ctrls,
    ring_msg, put_counts), the outbox's: ``raws[m]`` message m's bytes (M_*), ring r
    (``bufs[r]`` ...) takes message ``ring_msg[r]``. Between two periods it parks while
    ``gate[G_WANT]`` (:class:`LoopGate`); an experiment's end goes into ``events``
    (status, step, R) for the serving thread."""
    T, late_hist, edges, _dc, _dm, gate, _ev, _evc, ts = loop
    D, DC, state, clock, joint = drive
    used = 0
    first = True
    T[T_EXIT] = EXIT_PERIODS
    while True:
        if T[T_RESUME] < 0:  # between two periods: the gate, then the next start
            if _park(gate, ts):
                first = True  # the next start follows a park: counted as after Python
            if gate[G_STOP] != 0 and D[PK.D_STOPPED] == 0.0:
                PK.safe_stop(S, D)
            why = _must_return(T, gate)
            if why < 0 and used >= budget:
                why = EXIT_BUDGET
            if why >= 0:
                T[T_EXIT] = why
                break
            T[T_RESUME] = _wait_start(T, late_hist, edges, ts, first)
            first = False
        missed = T[T_RESUME]
        if missed > 0:  # periods that went by: the model runs them held, unpublished
            n = min(missed, budget - used)
            PK.run_missed(S, P, noise, D, DC, state, n)
            used += n
            T[T_RESUME] = missed - n
        if used >= budget:  # the noise block ran out inside the period: refill, go on
            T[T_EXIT] = EXIT_BUDGET
            break
        t0 = T[T_START]
        due = PK.run_period(S, P, noise, D, DC, state, clock, joint)
        used += 1
        T[T_RESUME] = -1
        _answer_and_hand_over(loop, t0, due, D, DC, state, ctl, out)
        if 0 <= T[T_STALL] <= state[0]:  # the drive's stall test hook, once
            T[T_STALL] = -1
            _nap(ts, T[T_STALL_NS])
    return used


@numba.njit(cache=True, nogil=True)
def run_hardware_periods(loop: Any, drive: Any, ctl: Any, out: Any) -> int:
    """:func:`run_periods` for a user's power stage called by address
    (``im_drive_sim.hardware_period``: a C library, a compiled class): periods until
    ``gate[G_QUIT]``, ``T[T_MAX_PERIODS]`` or a drive fault (``T[T_EXIT]`` = EXIT_FAULT,
    ``F`` says which call returned what; zero current was written). The power stage
    lives on the wall clock: a late start's whole periods went by with the command held
    (``hardware_missed``). ``drive`` = (E, D, DC, F, meas, state, joint): the power
    stage's entry, the drive's words and views (``hardware_period``). Returns the
    periods run."""
    T, late_hist, edges, _dc, _dm, gate, _ev, _evc, ts = loop
    E, D, DC, F, meas, state, joint = drive
    first = True
    T[T_EXIT] = EXIT_PERIODS
    while True:
        if _park(gate, ts):
            first = True
        if gate[G_STOP] != 0 and D[PK.D_STOPPED] == 0.0:
            HP.safe_stop(E, D)
        why = _must_return(T, gate)
        if why >= 0:
            T[T_EXIT] = why
            break
        missed = _wait_start(T, late_hist, edges, ts, first)
        first = False
        t0 = T[T_START]
        due = HP.hardware_missed(E, D, DC, F, missed)
        if due != HP.FAULT:
            due = HP.hardware_period(E, D, DC, F, meas, state, joint)
        if due == HP.FAULT:
            gate[G_RUNNING] = 0
            T[T_EXIT] = EXIT_FAULT
            break
        _answer_and_hand_over(loop, t0, due, D, DC, state, ctl, out)
    return T[T_PERIODS]
