"""The composed real-time loop's Python side: :class:`CompiledPeriods` runs the
simulator's periods with the controller's as one numba call that never holds the GIL
(:mod:`.loop_kernels`; :class:`CompiledHardwarePeriods`: a user's power stage called by
address), and :class:`LoopGate` is the lock a Python thread holds to read or change the
state the loop runs on. The call returns only to quit, or to refill a noisy model's noise
block (``DriveSim.run_kernel``, every 4096 periods): then the loop thread takes the GIL.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from typing import Any

import numpy as np

from im_drive_sim import hardware_period as HP, period_kernel as PK
from im_drive_sim.hardware_abi import KIND_C, N_MEASUREMENT, HardwareFault, entry_words
from im_drive_sim.loop_clock import (
    T_LATE,
    T_MAX_LATE,
    T_MAX_LATE_AT,
    T_MAX_LATE_PY,
    T_MISSED_TOTAL,
    T_N,
    T_OVERRUNS,
    T_SPIN,
    T_T0,
    T_TS,
    T_WALL,
)
from im_drive_sim.pacing import LATENESS_EDGES_US

from .loop_kernels import (
    EV_HEAD,
    EV_LOST,
    EV_TAIL,
    EVENT_CAPACITY,
    EXIT_BUDGET,
    EXIT_FAULT,
    G_PARKED,
    G_RUNNING,
    G_WANT,
    N_G,
    N_MSG,
    N_T,
    T_COMMANDS,
    T_EXIT,
    T_MAX_PERIODS,
    T_PERIODS,
    T_REFUSED,
    T_RESUME,
    T_STALL,
    T_STALL_NS,
    run_hardware_periods,
    run_periods,
)


class LoopGate:
    """The loop lock (``RealtimeBench.lock``, the controller's ``loop_lock``): what a
    Python thread holds to read or change the state the loop runs on (gains, an
    experiment's start, a fault reset, a safe stop).

    While a compiled loop runs (:attr:`running`) it never takes the GIL nor a Python
    lock, so a thread entering the gate (``with gate:``) *parks* it instead: it raises
    ``gate[G_WANT]``, the loop finishes the period under way and waits between two
    periods (``gate[G_PARKED]``), the nodes take their state back from the loop's
    arrays, the thread does its work, the loop's arrays take the nodes' state again
    and the loop goes on -- late, if the thread held it past the next period start,
    as with any lock. Without a compiled loop it is a plain re-entrant lock."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._depth = 0
        self._parked = False
        #: > 0: a thread that parks the loop runs SCHED_FIFO at this priority for its
        #: turn (the loop's minus one: priority inheritance, as a PI mutex gives a
        #: real-time waiter's priority to the holder) -- beside busy processes a normal
        #: thread the loop waits for would otherwise wait for the CPU with it
        self.boost = 0
        self.boosted = 0  #: turns run boosted (the summary's loop figures)
        self._restore: tuple[int, Any] | None = None
        #: the loop's words shared with Python (G_*): read and written by both sides
        self.gate = np.zeros(N_G, np.int64)
        #: the compiled loop running now (None: the nodes own their state)
        self.running: CompiledPeriods | None = None

    def __enter__(self) -> LoopGate:
        self._lock.acquire()
        self._depth += 1
        if self._depth == 1 and self.running is not None:
            self._park()
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            if self._depth == 1 and self._parked:
                self._parked = False
                assert self.running is not None
                self.running.take()  # the loop's arrays from the nodes again
                self.gate[G_WANT] = 0  # after the arrays: the loop reads them next
        finally:
            self._depth -= 1
            if self._depth == 0 and self._restore is not None:
                self._lower_priority()
            self._lock.release()

    def _raise_priority(self) -> None:
        """This thread to SCHED_FIFO ``boost`` for its turn (what it was, kept)."""
        try:
            self._restore = (os.sched_getscheduler(0), os.sched_getparam(0))
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.boost))
            self.boosted += 1
        except OSError:  # not permitted (the loop's FIFO was): run the turn as it is
            self._restore = None

    def _lower_priority(self) -> None:
        policy, param = self._restore or (os.SCHED_OTHER, os.sched_param(0))
        self._restore = None
        with contextlib.suppress(OSError):  # (what it was is always permitted back)
            os.sched_setscheduler(0, policy, param)

    def _park(self) -> None:
        compiled, g = self.running, self.gate
        assert compiled is not None
        if self.boost > 0:
            self._raise_priority()
        g[G_WANT] = 1
        # parked within a period; between two compiled calls (the noise block's refill)
        # the loop thread needs the GIL, which this sleep lets go of
        while g.item(G_PARKED) == 0 and g.item(G_RUNNING) != 0:
            time.sleep(20e-6)
        if g.item(G_PARKED) != 0:
            self._parked = True
        else:  # the loop quit meanwhile: it runs no more
            g[G_WANT] = 0
            self.running = None
        compiled.give_back()  # the nodes own their state during the turn

    def loop_ended(self, compiled: CompiledPeriods) -> None:
        """The loop thread, its compiled run over: the nodes own their state."""
        with self._lock:
            compiled.give_back()
            compiled.sync_figures()
            self.running = None


class CompiledPeriods:
    """:func:`run_periods` for a ``DriveSimNode`` composed with a ``ControllerNode``
    whose loop topics go through ``outbox`` (after any recorder tap was made).

    What runs in Python between two calls runs in a period's slack, so the words are
    read with ``.item`` (numpy scalar arithmetic is slow there)."""

    #: the drive's message views :func:`run_periods` takes after ``state``, in groups
    #: (``period_views``' keys): /clock's, then joint_states'
    DRIVE_VIEWS: tuple[tuple[str, ...], ...] = (
        ('clock_sec', 'clock_nsec'),
        ('joint_sec', 'joint_nsec', 'joint_pos', 'joint_vel', 'joint_eff'),
    )

    def __init__(
        self, drive: Any, controller: Any, outbox: Any, durations: Any, pacer: Any, gate: LoopGate
    ) -> None:
        """``gate``: the bench's loop lock; its words are the loop's gate."""
        self.drive, self.controller, self.pacer, self.gate = drive, controller, pacer, gate
        self.durations = durations
        self.sim = getattr(drive, 'sim', None)  # the simulator's model (run_kernel)
        dv = drive.period_views()
        cv = controller.answer_views()
        self._drive_args = (dv['state'], *(tuple(dv[k] for k in g) for g in self.DRIVE_VIEWS))
        self._ctl_args = tuple(
            cv[k] for k in ('R', 'Q', 'X', 'C', 'CF', 'cout', 'eout', 'cmd', 'internals')
        )
        # in the order M_*; a drive without /clock (a user's) has no such message
        pubs = (
            drive.state_pub,
            getattr(drive, 'clock_pub', None),
            drive.joint_pub,
            controller.client.command_pub,
            controller.internals_pub,
        )
        raws = (
            dv['state_raw'],
            dv.get('clock_raw', np.zeros(0, np.uint8)),
            dv['joint_raw'],
            cv['cmd_raw'],
            cv['internals_raw'],
        )
        self.channels: list[Any] = []
        rings, ring_msg = [], []
        for m, pub in enumerate(pubs):
            ch = None if pub is None else outbox.channel(pub)
            if pub is not None and ch is None:
                raise ValueError(f'{pub.topic_name} does not go through the outbox')
            self.channels.append(ch)
            for ring in (ch.dds, ch.tap) if ch is not None else ():
                if ring is not None:
                    rings.append(ring)
                    ring_msg.append(m)
        self.put_counts = np.zeros(N_MSG, np.int64)
        self._out = (
            raws,
            tuple(r.buf for r in rings),
            tuple(r.lens for r in rings),
            tuple(r.stamps for r in rings),
            tuple(r.ctrl for r in rings),
            np.array(ring_msg, np.int64),
            self.put_counts,
        )
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
        self.events = np.zeros((EVENT_CAPACITY, 2 + len(cv['R'])))
        self.ev_ctrl = np.zeros(3, np.int64)
        self._loop = (
            self.T, self.late_hist, self._edges, durations.counts, durations.maxes,
            gate.gate, self.events, self.ev_ctrl, self._ts,
        )  # fmt: skip
        self._refused_said = 0
        self._lost_said = 0

    def warm_up(self) -> None:
        """Compile (or load) the loop's kernel for these arrays now, not in a period: a
        call that runs no period."""
        self.take()
        self.T[T_MAX_PERIODS] = self.T[T_PERIODS] = 0
        self._call(1)  # returns at once: no period to run
        self.give_back()

    def start(self) -> None:
        """Period 0 starts now (the next one a period later), as ``Pacer.restart``."""
        self.T[T_T0] = time.perf_counter_ns()
        self.T[T_N] = 0

    def take(self) -> None:
        """The nodes' state into the loop's arrays, in place (the kernel holds them):
        the loop's arrays own it from here on, until :meth:`give_back`."""
        D, DC = self.drive.period_words()
        W = self.controller.answer_words()
        if self._D.shape != D.shape:
            self._D, self._DC, self._W = D, DC, W
        else:
            self._D[:], self._DC[:], self._W[:] = D, DC, W
        self.T[T_STALL] = getattr(self.drive, 'stall_step', -1)
        self.T[T_STALL_NS] = round(getattr(self.drive, 'stall_s', 0.0) * 1e9)
        self.stale = False

    def give_back(self) -> None:
        """The loop's arrays back to the nodes (idempotent): they own their state until
        :meth:`take`."""
        if self.stale:
            return
        T = self.T
        self.drive.set_period_words(self._D, self._DC, T.item(T_COMMANDS) > 0)
        if hasattr(self.drive, 'stall_step'):
            self.drive.stall_step = T.item(T_STALL)
        T[T_COMMANDS] = 0
        self.controller.set_answer_words(self._W)
        self.stale = True

    def _kernel(self, S: Any, P: Any, noise: Any, _offset: int, count: int) -> int:
        return int(
            run_periods(
                S, P, noise, count, self._loop, (self._D, self._DC, *self._drive_args),
                (*self._ctl_args, self._W), self._out,
            )
        )  # fmt: skip

    def _ended(self) -> bool:
        return self.T.item(T_EXIT) != EXIT_BUDGET

    def _call(self, budget: int) -> None:
        """The kernel, stepping the model at most ``budget`` times."""
        self.sim.run_kernel(budget, self._kernel, self._ended)

    def run(self) -> None:
        """The loop thread's whole compiled run: periods until ``gate[G_QUIT]`` (the
        loop returns to Python only to refill the model's noise block, every 4096
        periods). The caller then calls ``LoopGate.loop_ended``."""
        T, g = self.T, self.gate.gate
        T[T_MAX_PERIODS] = 1 << 62
        T[T_PERIODS] = 0
        T[T_EXIT] = EXIT_BUDGET
        with self.gate:  # no thread is at the nodes' state: take it, then run
            self.take()
            g[G_RUNNING] = 1
            self.gate.running = self
        try:
            self._call(1 << 62)
        finally:
            g[G_RUNNING] = 0

    def poll_events(self) -> int:
        """Hand the experiment ends the loop left to the controller (the serving
        thread); returns how many."""
        refused = self.T.item(T_REFUSED)
        if refused > self._refused_said:  # as the drive says it when not compiled
            self._refused_said = refused
            self.drive.get_logger().error(
                f'drive/command: non-finite command ignored ({refused} so far)',
                throttle_duration_sec=1.0,
            )
        c = self.ev_ctrl
        if c.item(EV_LOST) > self._lost_said:  # a full event ring: never in practice
            self._lost_said = c.item(EV_LOST)
            self.drive.get_logger().error(
                f'the compiled loop lost {self._lost_said} experiment ends (the serving '
                f'thread did not take them): their results are lost, the tuner re-runs them'
            )
        n = 0
        while c.item(EV_TAIL) < c.item(EV_HEAD):
            row = self.events[c.item(EV_TAIL) % len(self.events)].copy()
            c[EV_TAIL] += 1
            self.controller.compiled_event(int(row[0]), row[2:])
            n += 1
        return n

    def periods(self) -> int:
        """Periods run so far."""
        return self.T.item(T_PERIODS)

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
            if ch is None:
                continue
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


class CompiledHardwarePeriods(CompiledPeriods):
    """:func:`run_hardware_periods` for an ``ExampleDrive`` whose power stage is given by
    address (``ExampleDrive.hardware_entry``: a C library, a compiled class), composed
    with a ``ControllerNode``. The loop returns to Python only to quit, or on a drive
    fault (:meth:`run` raises ``HardwareFault``: zero current was written)."""

    DRIVE_VIEWS = (('joint_sec', 'joint_nsec', 'joint_pos', 'joint_vel', 'joint_eff'),)

    def __init__(
        self, drive: Any, controller: Any, outbox: Any, durations: Any, pacer: Any, gate: LoopGate
    ) -> None:
        super().__init__(drive, controller, outbox, durations, pacer, gate)
        entry = drive.hardware_entry()
        if entry is None:
            raise ValueError(f'{type(drive.hw).__name__} is not a compiled power stage')
        self.entry = entry
        self._E = entry_words(entry)
        self._F = np.zeros(3, np.int64)
        self._m = np.zeros(N_MEASUREMENT)

    def _kernel(self, *_: Any) -> int:  # type: ignore[override]
        return int(
            run_hardware_periods(
                self._loop, (self._E, self._D, self._DC, self._F, self._m, *self._drive_args),
                (*self._ctl_args, self._W), self._out,
            )
        )  # fmt: skip

    def fault(self) -> str | None:
        """The drive fault that ended the loop, in words (None: none)."""
        F = self._F
        if F.item(HP.F_CALL) == 0:
            return None
        call = HP.CALL_NAMES[F.item(HP.F_CALL)]
        if self.entry.kind == KIND_C:
            call = f'im_drive_{call}'
        return (
            f'{self.entry.name}: {call} returned {F.item(HP.F_CODE)} at step '
            f'{F.item(HP.F_STEP)} (a drive fault)'
        )

    def _call(self, budget: int) -> None:
        self._kernel()

    def run(self) -> None:
        """The loop thread's whole compiled run: periods until ``gate[G_QUIT]``, or a
        drive fault (``HardwareFault``, after the loop wrote zero current)."""
        super().run()
        if self.T.item(T_EXIT) == EXIT_FAULT:
            raise HardwareFault(self.fault() or 'a drive fault')
