"""The composed real-time loop compiled: many periods of the simulator and the controller
in one numba call that never holds the GIL (``tuner --bench realtime``, the default
drive).

Why (issue 27, docs/real-drive.md "Real-time set-up"): the loop run as Python -- a
handful of node methods per period, each a few dozen interpreter operations -- took
p50 ~40 us and p99 ~100 us of the 200 us period on a 2-core machine, and needed the GIL
every period, so any Python thread beside it (the tuner, the recorder's drain) could
delay a period start by up to the interpreter's switch interval. ros2_control runs its
update loop as compiled code that never waits for an interpreter; this is that loop for
the simulator composed with the controller. One call of :func:`run_periods` runs up to
:data:`CHUNK_PERIODS` periods (5 ms), each:

1. wait for the period start (``clock_nanosleep`` on CLOCK_MONOTONIC to the spin margin,
   then a busy-wait: ``pacing.Pacer``'s schedule, overruns and lateness histogram);
2. the drive's period (``im_drive_sim.period_kernel.run_period``: latch, model step,
   state k+1) and its messages into the outbox's rings (``outbox.put_slot``);
3. the controller's answer (``im_controller.kernel.answer_state``) and its command and
   internals into the rings;
4. the drive takes the answer (``period_kernel.take_command``): fresh for the next period;
5. the period's durations into the loop's histograms (``pacing.count_durations``).

It returns to Python after the work of a period -- in that period's slack, never at a
period start -- when the chunk is done, an experiment ended (the controller's node
publishes and logs it from the serving thread), the serving thread asked for the loop
lock (:class:`LoopGate`), the model's noise block ran out (``DriveSim.run_kernel``
refills it) or the drive's stall test hook is due. The nodes stay the owners of their
state: ``DriveSimNode.period_words`` / ``ControllerNode.answer_words`` hand it over
before a call and take it back after. The bit-for-bit test of the composed bench (a
real-time run against its lock-step replay) holds this loop to the Python one.

Written by hand, not with a library: no library runs a numba loop on a wall-clock
schedule; the clock calls are libc's (``types.ExternalFunction``, as ``outbox`` calls
rcl).
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numba
import numpy as np
from numba import types

from im_controller.experiment import STATUS_DONE
from im_controller.kernel import W_INTERNALS_DUE, answer_state
from im_drive_sim import period_kernel as PK
from im_drive_sim.outbox import R_HEAD, put_slot
from im_drive_sim.pacing import LATENESS_EDGES_US, count_durations

__all__ = ['CHUNK_PERIODS', 'CompiledPeriods', 'LoopGate', 'run_periods']

#: Periods per compiled call at most (5 ms): how often the loop thread looks at Python
#: (the tuner's stop request, the counters) when nothing else calls it back.
CHUNK_PERIODS = 25

_clock_gettime = types.ExternalFunction('clock_gettime', types.int32(types.int32, types.uint64))
_clock_nanosleep = types.ExternalFunction(
    'clock_nanosleep', types.int32(types.int32, types.int32, types.uint64, types.uint64)
)
CLOCK_REALTIME, CLOCK_MONOTONIC, TIMER_ABSTIME = 0, 1, 1
NS = 1_000_000_000

# -- the words of T (int64) ---------------------------------------------------------------
T_T0 = 0  #: the schedule's anchor [ns, CLOCK_MONOTONIC]: period n starts at t0 + n ts
T_N = 1  #: periods started since t0
T_TS = 2  #: the period [ns]
T_SPIN = 3  #: busy-wait before a start [ns]
T_WALL = 4  #: 1: a drive that cannot pause (late starts skip whole periods, held)
T_OVERRUNS = 5  #: starts more than a period late
T_MISSED_TOTAL = 6  #: whole periods those starts skipped (wall clock)
T_MAX_LATE = 7  #: worst start lateness [ns]
T_LATE = 8  #: the last start's lateness [ns] (after a skip: from the period it became)
T_EXIT = 9  #: why the last call returned (EXIT_*)
T_STATUS = 10  #: the experiment status that ended it (EXIT_STATUS)
T_PERIODS = 11  #: periods run since the caller zeroed it
T_RESUME = 12  #: a period under way: its missed steps still to run (-1: none)
T_START = 13  #: that period's start [ns]
T_MAX_PERIODS = 14  #: the call's limit
T_COMMANDS = 15  #: commands the drive took since the caller zeroed it
T_REFUSED = 16  #: answers the drive refused (not finite), idem
T_STALL = 17  #: the drive's stall test hook: its step (-1: none)
T_MAX_LATE_AT = 18  #: when the worst late start was due [ns, CLOCK_MONOTONIC]
#: the worst lateness of the starts that followed Python (a call's first period: the
#: loop thread took the GIL, and ran Python, since the period before) [ns]
T_MAX_LATE_PY = 19
N_T = 20

EXIT_BUDGET, EXIT_PERIODS, EXIT_STATUS, EXIT_WANT, EXIT_STALL = range(5)

# the messages, in the order of the rings' sources
M_STATE, M_CLOCK, M_JOINT, M_COMMAND, M_INTERNALS = range(5)
N_MSG = 5


@numba.njit(cache=True)
def _now(ts: np.ndarray, clock: int) -> int:
    _clock_gettime(np.int32(clock), np.uint64(ts.ctypes.data))
    return ts[0] * NS + ts[1]


@numba.njit(cache=True)
def _sleep_until(ts: np.ndarray, t_ns: int) -> None:
    ts[0] = t_ns // NS
    ts[1] = t_ns - ts[0] * NS
    p = np.uint64(ts.ctypes.data)
    _clock_nanosleep(np.int32(CLOCK_MONOTONIC), np.int32(TIMER_ABSTIME), p, np.uint64(0))


@numba.njit(cache=True)
def _wait_start(
    T: np.ndarray, late_hist: np.ndarray, edges: np.ndarray, ts: np.ndarray, first: bool
) -> int:
    """Wait for the next period start (``pacing.Pacer.wait``, in ns); returns the whole
    periods it skipped (a drive that cannot pause; else 0 and the schedule re-anchored).
    ``first``: the call's first period (Python ran since the period before)."""
    period = T[T_TS]
    deadline = T[T_T0] + (T[T_N] + 1) * period
    target = deadline - T[T_SPIN]
    if _now(ts, CLOCK_MONOTONIC) < target:
        _sleep_until(ts, target)
    now = _now(ts, CLOCK_MONOTONIC)
    while now < deadline:
        now = _now(ts, CLOCK_MONOTONIC)
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
def run_periods(
    S: np.ndarray,
    P: np.ndarray,
    noise: np.ndarray,
    budget: int,
    T: np.ndarray,
    late_hist: np.ndarray,
    edges: np.ndarray,
    dur_counts: np.ndarray,
    dur_maxes: np.ndarray,
    D: np.ndarray,
    DC: np.ndarray,
    state: np.ndarray,
    clock_sec: np.ndarray,
    clock_nsec: np.ndarray,
    joint_sec: np.ndarray,
    joint_nsec: np.ndarray,
    joint_pos: np.ndarray,
    joint_vel: np.ndarray,
    joint_eff: np.ndarray,
    R: np.ndarray,
    Q: np.ndarray,
    X: np.ndarray,
    C: np.ndarray,
    CF: np.ndarray,
    cout: np.ndarray,
    eout: np.ndarray,
    cmd: np.ndarray,
    internals: np.ndarray,
    W: np.ndarray,
    raws: Any,
    bufs: Any,
    lens: Any,
    stamps: Any,
    ctrls: Any,
    ring_msg: np.ndarray,
    put_counts: np.ndarray,
    want: np.ndarray,
    ts: np.ndarray,
) -> int:
    """Up to ``T[T_MAX_PERIODS]`` periods (module docstring), stepping the model at most
    ``budget`` times (``DriveSim.run_kernel``'s count: the noise block). Returns the
    model steps taken; ``T[T_EXIT]`` says why it returned; ``T[T_PERIODS]`` counts the
    periods run. ``raws[m]``: message m's bytes (M_*); ring r (``bufs[r]`` ...) takes
    message ``ring_msg[r]``; ``want[0]`` != 0: return after the period under way."""
    used = 0
    first = True
    T[T_EXIT] = EXIT_PERIODS
    n_rings = len(bufs)
    while True:
        if T[T_RESUME] < 0:  # no period under way: wait for the next start
            if T[T_PERIODS] >= T[T_MAX_PERIODS]:
                T[T_EXIT] = EXIT_PERIODS
                break
            if want[0] != 0:
                T[T_EXIT] = EXIT_WANT
                break
            if used >= budget:
                T[T_EXIT] = EXIT_BUDGET
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
        due = PK.run_period(
            S, P, noise, D, DC, state, clock_sec, clock_nsec,
            joint_sec, joint_nsec, joint_pos, joint_vel, joint_eff,
        )  # fmt: skip
        used += 1
        T[T_RESUME] = -1
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
        if st >= STATUS_DONE:
            T[T_STATUS] = st
            T[T_EXIT] = EXIT_STATUS
            break
        if 0 <= T[T_STALL] <= state[0]:
            T[T_EXIT] = EXIT_STALL
            break
    return used


class LoopGate:
    """The loop lock (``RealtimeBench.lock``, the controller's ``loop_lock``), with a
    turn for the other threads.

    The loop thread holds it over each compiled call (:meth:`loop_acquire`), many periods
    long, and takes it again right after; a plain lock would starve a thread waiting for
    it. So a thread entering it (``with gate:``) first raises :attr:`want`; the compiled
    loop returns after the period under way, and :meth:`loop_release` lets the waiter in
    before the loop takes the lock again (bounded by the next period start)."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._count = threading.Lock()
        self._waiting = 0
        #: != 0: a thread waits for the lock (read by the compiled loop every period)
        self.want = np.zeros(1, np.int64)

    def __enter__(self) -> LoopGate:
        with self._count:
            self._waiting += 1
            self.want[0] = 1
        try:
            self._lock.acquire()
        finally:
            with self._count:
                self._waiting -= 1
                self.want[0] = 1 if self._waiting else 0
        return self

    def __exit__(self, *exc: object) -> None:
        self._lock.release()

    def loop_acquire(self) -> None:
        self._lock.acquire()

    def loop_release(self, until: float) -> None:
        """Release; if a thread wants the lock, wait (sleeping) until it took it or until
        ``until`` (perf_counter [s]: before the next period start)."""
        self._lock.release()
        while self.want.item(0) != 0 and time.perf_counter() < until:
            time.sleep(10e-6)


class CompiledPeriods:
    """:func:`run_periods` for a ``DriveSimNode`` composed with a ``ControllerNode``
    whose loop topics go through ``outbox`` (after any recorder tap was made).

    What runs in Python between two calls is kept to a few microseconds: it runs in a
    period's slack, and numpy scalar arithmetic there measured 40 us a call in the loop
    thread (so the words are read with ``.item``)."""

    def __init__(
        self, drive: Any, controller: Any, outbox: Any, durations: Any, pacer: Any, gate: LoopGate
    ) -> None:
        self.drive, self.controller, self.pacer, self.durations = (
            drive,
            controller,
            pacer,
            durations,
        )
        self.gate = gate
        self.sim = drive.sim
        dv = drive.period_views()
        cv = controller.answer_views()
        self._drive_args = tuple(
            dv[k]
            for k in (
                'state', 'clock_sec', 'clock_nsec', 'joint_sec', 'joint_nsec',
                'joint_pos', 'joint_vel', 'joint_eff',
            )
        )  # fmt: skip
        self._ctl_args = tuple(
            cv[k] for k in ('R', 'Q', 'X', 'C', 'CF', 'cout', 'eout', 'cmd', 'internals')
        )
        pubs = (
            drive.state_pub,
            drive.clock_pub,
            drive.joint_pub,
            controller.client.command_pub,
            controller.internals_pub,
        )
        raws = (
            dv['state_raw'],
            dv['clock_raw'],
            dv['joint_raw'],
            cv['cmd_raw'],
            cv['internals_raw'],
        )
        self.channels = []
        rings, ring_msg = [], []
        for m, pub in enumerate(pubs):
            ch = outbox.channel(pub)
            if ch is None:
                raise ValueError(f'{pub.topic_name} does not go through the outbox')
            self.channels.append(ch)
            for ring in (ch.dds, ch.tap):
                if ring is not None:
                    rings.append(ring)
                    ring_msg.append(m)
        self._raws = raws
        self._rings = (
            tuple(r.buf for r in rings),
            tuple(r.lens for r in rings),
            tuple(r.stamps for r in rings),
            tuple(r.ctrl for r in rings),
        )
        self._ring_msg = np.array(ring_msg, np.int64)
        self.put_counts = np.zeros(N_MSG, np.int64)
        self._put_seen = np.zeros(N_MSG, np.int64)
        self.T = np.zeros(N_T, np.int64)
        self.T[T_TS] = drive.ts_ns
        self.T[T_SPIN] = round(pacer.spin_margin * 1e9)
        self.T[T_WALL] = int(pacer.wall_clock)
        self.T[T_RESUME] = -1
        self.late_hist = np.zeros(len(LATENESS_EDGES_US) + 1, np.int64)
        self._edges = np.array([round(e * 1000) for e in LATENESS_EDGES_US], np.int64)
        self._ts = np.zeros(2, np.int64)
        self._D = self._DC = self._W = np.zeros(0)
        self.stale = True  #: the nodes own their state (take() before a run)

    def warm_up(self) -> None:
        """Compile (or load) :func:`run_periods` for these arrays now, not in a period:
        a call that runs no period."""
        self.take()
        self.T[T_MAX_PERIODS] = self.T[T_PERIODS] = 0
        self.sim.run_kernel(1, self._kernel)  # returns at once: no period to run

    def start(self) -> None:
        """Period 0 starts now (the next one a period later), as ``Pacer.restart``."""
        self.T[T_T0] = time.perf_counter_ns()
        self.T[T_N] = 0

    def take(self) -> None:
        """The nodes' state into the loop's arrays (their owners: the nodes between
        :meth:`give_back` and this; the loop's arrays from here on)."""
        self._D, self._DC = self.drive.period_words()
        self._W = self.controller.answer_words()
        self.T[T_STALL] = self.drive.stall_step
        self.stale = False

    def give_back(self, status: int = 0) -> None:
        """The loop's arrays back to the nodes (``status``: an experiment's end, handled
        by the controller); :meth:`take` before the next :meth:`run`."""
        T = self.T
        self.drive.set_period_words(self._D, self._DC, T.item(T_COMMANDS) > 0)
        T[T_COMMANDS] = T[T_REFUSED] = 0
        self.controller.set_answer_words(self._W, status)
        self.stale = True

    def _kernel(self, S: Any, P: Any, noise: Any, _offset: int, count: int) -> int:
        return int(
            run_periods(
                S, P, noise, count, self.T, self.late_hist, self._edges,
                self.durations.counts, self.durations.maxes,
                self._D, self._DC, *self._drive_args, *self._ctl_args, self._W,
                self._raws, *self._rings, self._ring_msg, self.put_counts,
                self.gate.want, self._ts,
            )
        )  # fmt: skip

    def _ended(self) -> bool:
        return self.T.item(T_EXIT) != EXIT_BUDGET

    def run(self, max_periods: int = CHUNK_PERIODS) -> int:
        """Up to ``max_periods`` periods; the caller holds the loop lock. Nothing else
        runs in Python between two calls unless something needs it: an experiment's
        end (the controller takes it), a thread waiting for the lock (it may change the
        nodes' state: all is given back first) or the stall hook. Returns the periods
        run."""
        if self.stale:
            self.take()
        T = self.T
        T[T_MAX_PERIODS] = max_periods
        T[T_PERIODS] = 0
        T[T_EXIT] = EXIT_BUDGET
        # until the periods are done or an event; the noise block refilled on the way
        self.sim.run_kernel(1 << 62, self._kernel, self._ended)
        code = T.item(T_EXIT)
        if code == EXIT_STATUS:
            self.give_back(T.item(T_STATUS))
        elif code == EXIT_WANT:
            self.give_back()
        elif code == EXIT_STALL:
            self.give_back()
            self.drive.stall_due()
        return T.item(T_PERIODS)

    def sync_figures(self) -> None:
        """The pacer's and the drive's figures (the node's counters, for its status),
        the histograms' count and the channels' put counts, from the loop's arrays: from
        any thread (a figure read while the loop runs is a period old at most)."""
        T, pacer = self.T, self.pacer
        pacer.n = int(T[T_N])
        pacer.overruns = int(T[T_OVERRUNS])
        pacer.missed_total = int(T[T_MISSED_TOTAL])
        pacer.max_lateness_us = T.item(T_MAX_LATE) * 1e-3
        pacer.lateness_s = T.item(T_LATE) * 1e-9
        pacer.lateness_hist = [int(x) for x in self.late_hist]
        c = self.drive.counters
        if not self.stale:  # the loop's arrays are the counters' owner
            for i, name in enumerate(PK.COUNTERS):
                setattr(c, name, int(self._DC[i]))
        c.overruns, c.max_lateness_us = pacer.overruns, pacer.max_lateness_us
        self.durations.n = int(self.durations.counts[0].sum())
        for m, ch in enumerate(self.channels):
            put = int(self.put_counts[m])
            ch.put_count += put - int(self._put_seen[m])
            self._put_seen[m] = put

    def lateness_figures(self, t0: float) -> dict[str, float]:
        """Where the worst late start came from: its time since ``t0`` (perf_counter
        [s], the loop's start) and the worst lateness of the starts that followed Python
        (a call's first period) [us] -- when that is the worst, the interpreter (a thread
        holding the GIL in a long C call, Python between calls) made it; otherwise the
        loop thread itself was not scheduled."""
        T = self.T
        return {
            'max_lateness_at_s': round(T.item(T_MAX_LATE_AT) * 1e-9 - t0, 3),
            'max_lateness_after_python_us': round(T.item(T_MAX_LATE_PY) * 1e-3, 1),
        }

    def next_start(self) -> float:
        """The next period's start (perf_counter [s])."""
        # Python ints: numpy scalar arithmetic measured 40 us here in the loop thread
        T = self.T
        return (T.item(T_T0) + (T.item(T_N) + 1) * T.item(T_TS)) * 1e-9
