"""The composed real-time bench: a drive and the controller in ONE process, one loop.

A Python controller in its own process, woken by DDS, cannot hold 5 kHz
(docs/real-drive.md); ros2_control loads controllers into the process that owns the
hardware for the same reason. Both stay rclpy nodes (the classes of ``drive_sim`` /
``example_drive`` / a user's drive, :func:`.drive_spec.make_drive`, and ``controller``),
composed into this process; a real-time thread runs their periods every Ts on the wall
clock (:class:`pacing.Pacer`), compiled with the simulator or a power stage given by
address (:mod:`.compiled_loop`), else :meth:`RealtimeBench.step`. What the nodes publish
goes to an outbox that publisher threads empty (:mod:`.loop_routes`); the serving thread
(:meth:`RealtimeBench.spin_until`) serves requests, results, the recorder and the garbage
collector. The threads in full: docs/real-drive.md, "How the composed loop runs".

Python's jitter is kept out of the loop: it allocates and logs nothing per period, the
garbage collector is frozen at start and run by hand in the serving thread, and the
thread switch interval is lowered (:data:`SWITCH_INTERVAL`) so a thread holding the GIL
gives it up soon after the loop wakes. :meth:`RealtimeBench.timing` reports the periods.
"""

from __future__ import annotations

import collections
import ctypes
import gc
import os
import sys
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.parameter import Parameter

from im_controller.controller_node import ControllerNode
from im_drive_sim import rt
from im_drive_sim.loop_clock import SPIN_NS
from im_drive_sim.outbox import PublisherThread
from im_drive_sim.pacing import LATENESS_BINS, DurationHistograms, Pacer
from im_drive_sim.runtime import ROUTES
from im_drive_sim.stop_signal import StopWatcher

from ..tuning import BenchFailure
from .compiled_loop import CompiledHardwarePeriods, CompiledPeriods, LoopGate
from .drive_spec import make_drive
from .inprocess import compose, run_before_start
from .loop_kernels import G_QUIT, G_STOP
from .loop_routes import route_through_outbox

#: The interpreter's thread switch interval while the loop runs [s] (default 5 ms): how
#: long the loop thread, woken for its period, waits for a thread holding the GIL before
#: asking for it.
SWITCH_INTERVAL = 50e-6


#: The serving thread's longest wait for a request [s]: between waits it runs its round
#: (results, recorder, status), each a stretch holding the GIL the loop may need.
SERVE_WAIT = 0.02

#: The serving thread's nice value when the loop runs SCHED_FIFO (see RealtimeBench).
SERVING_NICE = -10

#: The loop thread's busy-wait before a period start [s]: it sleeps until then (timer
#: slack 1 ns, PR_SET_TIMERSLACK) and spins the rest, holding the GIL only that long.
LOOP_SPIN_MARGIN = SPIN_NS * 1e-9


class DriveLoopError(BenchFailure):
    """The real-time loop raised (a hardware class's read/write, a node's period): the
    drive was safe-stopped and the loop runs no more; the run ends as a bench failure
    (the message says where)."""


def _precise_sleep() -> None:
    """Timer slack 1 ns for the calling thread (Linux; the default 50 us makes every
    sleep of the loop wake up to 50 us late). Nothing elsewhere."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(29, ctypes.c_ulong(1), 0, 0, 0)  # PR_SET_TIMERSLACK
    except (OSError, AttributeError):
        pass


class RealtimeBench:
    """A drive + the controller in this process, one real-time loop in its own thread
    (module docstring).

    The interface of the lock-step ``InProcessBench``: ``spin_until(predicate, timeout)``
    serves requests (the tuner's node can be added to :attr:`executor`) and pollers (the
    recorder) until ``predicate()``; the loop runs meanwhile, and between calls.
    """

    def __init__(
        self,
        *,
        context: Any = None,
        drive: str = 'sim',
        drive_overrides: list[Parameter] | None = None,
        controller_overrides: list[Parameter] | None = None,
        before_start: Callable[[RealtimeBench], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        rt_options: rt.RtOptions | None = None,
        outbox_capacity: int | None = None,
        compiled: bool = True,
        host_check: dict[str, Any] | None = None,
    ) -> None:
        """``before_start(bench)`` runs once both nodes exist and match, before state 0:
        the place to start a recorder that must not miss the first message (it takes the
        loop's topics from :attr:`outbox`'s tap: ``outbox.tap()``). ``should_stop()``:
        checked every 5 ms by the stop watcher (:mod:`im_drive_sim.stop_signal`, which
        also passes a SIGINT/SIGTERM to the loop at once, without Python) and by the
        serving thread; once True the drive is safe-stopped (zero current, latched).
        ``rt_options``: the loop thread's real-time scheduling (:mod:`im_drive_sim.rt`),
        applied in it before the recorder starts (its metadata records it); what is not
        permitted is said in one line each on stderr, and the run goes on.
        ``outbox_capacity``: messages per topic ring (None: ``loop_routes.SLOTS``).
        ``host_check``: the host's check before the run, recorded with the real-time
        settings (``rt_report['host_check']``). ``compiled``: run the simulator's periods
        compiled (:mod:`.compiled_loop`; other drives always run :meth:`step`, their
        periods in Python)."""
        self.drive = make_drive(drive, context, list(drive_overrides or []))
        self.drive_kind = drive
        self.controller, self.executor = compose(
            self.drive,
            lambda: ControllerNode(
                context=context,
                parameter_overrides=[
                    Parameter('mode', value='realtime'),
                    *(controller_overrides or []),
                ],
                composed_with=self.drive,
            ),
        )
        self.stop_requested = False
        #: True -> :meth:`safe_stop` (the tuner's SIGINT/SIGTERM: zero current in the
        #: loop's next period, whatever the serving thread is doing: stop_signal)
        self.should_stop: Callable[[], bool] = should_stop or (lambda: False)
        self.safe_stopped = False
        self.failed: DriveLoopError | None = None  #: the loop raised: it runs no more
        self._pollers: list[tuple[Callable[[], Any], float]] = []
        self._polled: list[float] = []
        self._service_ws: Any = None
        self._service_count = -1
        self._entities_checked = 0.0
        self._next_spin = 0.0
        self._spin_always = False
        self._entities: tuple[list, list, list] = ([], [], [])
        ctl, drv = self.controller, self.drive
        if not ctl.client.wait_for_drive(10.0):
            self.destroy()
            raise RuntimeError('the controller and the drive did not match within 10 s')

        # -- in memory between the two nodes; their publishers through the outbox ---------
        #: held by the loop during its control work (a waiter gets its turn: LoopGate)
        self.lock = LoopGate()
        ctl.loop_lock = self.lock
        ctl.deferred = collections.deque()
        ctl.client.hand_over = drv.commands.hand_over  # the answer, to the drive at once
        # nothing takes the DDS copies of state and command in this process any more
        ctl.io_node.destroy_subscription(ctl.client.state_sub)
        drv.io_node.destroy_subscription(drv.cmd_sub)
        self.outbox = route_through_outbox(drv, ctl, outbox_capacity)

        # -- the loop thread: real-time options applied in it, then it waits for go -------
        opts = rt_options or rt.RtOptions()
        self._rt_options = opts
        self.rt_report: dict[str, Any] = {}
        self._refused: list[str] = []
        self._ready = threading.Event()
        self._go = threading.Event()
        self._quit = False
        self._thread = threading.Thread(target=self._loop_main, name='rt-loop', daemon=True)
        ts = float(ctl.Ts)
        # a drive that cannot pause (wall_clock): late starts are periods held
        self.pacer = Pacer(ts, min(LOOP_SPIN_MARGIN, drv.spin_margin), drv.wall_clock)
        # per-period timings [us], over the whole run in fixed memory: the drive's period
        # (state k published), the controller's answer, the whole period's work, and how
        # late the period started
        self.durations = DurationHistograms(('drive', 'answer', 'work', 'late'))
        self._periods = 0
        self._seen_periods = 0
        self.answers_missed = 0  #: periods whose state the controller had no answer for
        self.gc_runs = 0
        self.publishers: list[PublisherThread] = []
        self._switch_interval = sys.getswitchinterval()
        self._thread.start()
        self._ready.wait(10.0)
        for line in self._refused:
            print(f'warning: {line}', file=sys.stderr, flush=True)
        if host_check is not None:
            self.rt_report['host_check'] = host_check
        if self.rt_report.get('policy') == 'SCHED_FIFO':
            # The loop waits for the GIL whenever this (serving) thread holds it: if busy
            # processes beside it pushed this thread off the CPU while it held the GIL,
            # the FIFO loop would wait with it (a priority inversion). A nice of -10
            # keeps it ahead of normal processes; permitted wherever FIFO was.
            try:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), SERVING_NICE)
                self.rt_report['serving_thread_nice'] = SERVING_NICE
            except OSError:
                self.rt_report['serving_thread_nice'] = os.getpriority(os.PRIO_PROCESS, 0)
            # and a thread that parks the loop runs its turn just below the loop
            # (LoopGate.boost: priority inheritance)
            if os.environ.get('IM_LOOP_GATE_BOOST', '1') != '0':
                self.lock.boost = max(1, int(self.rt_report.get('priority', 1)) - 1)
            self.rt_report['gate_boost'] = self.lock.boost
        run_before_start(self, before_start)
        self._t0 = time.perf_counter()
        self._next_status = self._t0 + 1.0
        gc.collect()
        gc.freeze()  # the set-up's objects: never scanned again
        gc.disable()  # young-generation collections by hand, in the serving thread
        warm_up = getattr(drv, 'warm_up', None)
        if callable(warm_up):
            warm_up()  # numba compiles here, not in the first period
        drv.start()
        # state 0 answered before the clock starts: the first period is driven fresh
        ctl.offer(drv.latest_state())
        ctl.answer()
        drv.take_commands()
        #: the simulator's periods compiled (after the recorder's tap rings were made)
        self.compiled: CompiledPeriods | None = None
        # the simulator's model, or a power stage given by address (a C library, a
        # compiled class); a Python hardware class runs its periods as Python
        kind: type[CompiledPeriods] | None = CompiledPeriods if compiled else None
        if compiled and getattr(drv, 'sim', None) is None:  # (an ExampleDrive)
            kind = CompiledHardwarePeriods if drv.hardware_entry() else None
        if kind is not None:
            self.compiled = kind(drv, ctl, self.outbox, self.durations, self.pacer, self.lock)
            self.compiled.warm_up()
        self.publishers = PublisherThread.per_channel(self.outbox)
        # one serving round now: the first of each is slow (an executor's first spin, the
        # first status), never beside a live loop
        self._service()
        self._next_status = time.perf_counter() + 1.0
        self._pending_requests(0.0)
        self.executor.spin_once(timeout_sec=0.0)
        # a stop signal reaches the loop through its gate without Python (stop_signal)
        self._stop_watch = StopWatcher(self.lock.gate, G_STOP, self.should_stop)
        sys.setswitchinterval(SWITCH_INTERVAL)
        self._go.set()

    # -- the loop thread --------------------------------------------------------------------
    def _loop_main(self) -> None:
        opts = self._rt_options
        try:
            self._refused = rt.apply(opts)  # (and the CPU latency request, always)
            self.rt_report = rt.report(opts, self._refused)
            _precise_sleep()
        finally:
            self._ready.set()
        self._go.wait()
        if self._quit:
            return
        self.pacer.restart()
        compiled = self.compiled
        try:
            if compiled is not None:
                compiled.start()
                try:
                    compiled.run()  # until stop_loop: no GIL, no Python lock
                finally:
                    self.lock.loop_ended(compiled)
            gate = self.lock.gate
            while not self._quit:
                self.step()
                if gate[G_STOP] != 0 and not self.safe_stopped:  # (the stop watcher's)
                    self.safe_stop()
        except BaseException as exc:
            self.safe_stop()  # an exception in the loop: zero current before anything else
            at = traceback.extract_tb(exc.__traceback__)[-1]  # the innermost frame
            self.failed = DriveLoopError(
                f'the real-time loop stopped on {type(exc).__name__}: {exc} (in '
                f'{at.filename}:{at.lineno} in {at.name}); zero current and zero load were '
                'written to the drive'
            )
            self.failed.__cause__ = exc

    @property
    def periods(self) -> int:
        """Periods the loop ran."""
        if self.compiled is not None:
            return self.compiled.periods()
        return self._periods

    def step(self) -> bool:
        """One real-time period (module docstring), in the loop thread. Returns True."""
        drive, ctl, pacer = self.drive, self.controller, self.pacer
        pacer.wait(time.sleep, _nothing)
        # the work is timed from the actual start; how late that start was is the
        # pacer's lateness (histogram, overruns), not the period's work
        t0 = time.perf_counter()
        with self.lock:
            c = drive.counters
            c.overruns, c.max_lateness_us = pacer.overruns, pacer.max_lateness_us
            if pacer.missed:
                drive.period(pacer.missed)  # periods that went by, the old command held
            else:
                drive.period()
            t1 = time.perf_counter()
            ctl.offer(drive.latest_state())
            answered = ctl.answer()
            t2 = time.perf_counter()
            if answered:
                drive.take_commands()  # fresh for the next period
            else:
                self.answers_missed += 1
        t3 = time.perf_counter()
        self.durations.add(
            (1e6 * (t1 - t0), 1e6 * (t2 - t1), 1e6 * (t3 - t0), 1e6 * pacer.lateness_s)
        )
        self._periods += 1
        return True

    # -- the serving thread -----------------------------------------------------------------
    def add_poller(self, poll: Callable[[], Any], period_steps: int = 16) -> None:
        """Call ``poll()`` from the serving thread at least every ``period_steps`` periods
        of time (the recorder: it drains the outbox's tap rings and its subscriptions)."""
        if not 1 <= period_steps <= 1000:
            raise ValueError(f'period_steps must be in [1, 1000], got {period_steps}')
        self._pollers.append((poll, period_steps * float(self.controller.Ts)))
        self._polled.append(0.0)

    def _service(self) -> None:
        """The serving thread's round: experiment results, pollers, status, gc."""
        if self.compiled is not None:
            self.compiled.poll_events()  # the experiment ends the compiled loop left
            periods = self.compiled.periods()
            if periods != self._seen_periods:  # the controller's state watchdog
                self._seen_periods = periods
                self.controller.state_seen()
        self.controller.flush_deferred()
        self.controller.tuner_watchdog()
        now = time.perf_counter()
        for j, (poll, every) in enumerate(self._pollers):
            if now - self._polled[j] >= every:
                poll()
                self._polled[j] = now
        if now >= self._next_status:
            if self.compiled is not None:
                self.compiled.sync_figures()
            self.drive.publish_status()
            self._next_status = now + 1.0
        if gc.get_count()[0] > 2000:
            gc.collect(0)
            self.gc_runs += 1
        for p in self.publishers:
            if p.error is not None:
                raise DriveLoopError(f'an outbox publisher stopped: {p.error!r}')

    def _serve(self, timeout: float) -> None:
        """Wait up to ``timeout`` [s] for a request or a response (on a prebuilt WaitSet,
        far cheaper than an executor spin: research/NOTES.md, "From the source of
        im_tuner/bench/realtime.py"), then serve it."""
        if self._pending_requests(timeout):
            self.executor.spin_once(timeout_sec=0.0)

    def _pending_requests(self, timeout: float) -> bool:
        now = time.monotonic()
        if now >= self._entities_checked:
            # the nodes' entities, looked at twice a second (walking them holds the GIL:
            # too long for every millisecond)
            self._entities_checked = now + 0.5
            nodes = list(self.executor.get_nodes())
            services = [s for n in nodes for s in n.services]
            clients = [c for n in nodes for c in n.clients]
            subs = [s for n in nodes for s in n.subscriptions]
            self._spin_always = any(list(n.timers) or list(n.guards) for n in nodes)
            count = len(services) + len(clients) + len(subs)
            if count != self._service_count:
                self._service_count = count
                self._entities = (services, clients, subs)
                self._service_ws = _rclpy.WaitSet(
                    len(subs), 0, 0, len(clients), len(services), 0, self.drive.context.handle
                )
        if self._spin_always:
            return True  # something this wait does not cover (a timer): spin every time
        if now >= self._next_spin:
            self._next_spin = now + 0.05  # and every 50 ms (an entity made since we looked)
            return True
        services, clients, subs = self._entities
        ws = self._service_ws
        ws.clear_entities()
        for s in subs:
            ws.add_subscription(s.handle)
        for c in clients:
            ws.add_client(c.handle)
        for s in services:
            ws.add_service(s.handle)
        ws.wait(int(timeout * 1e9))
        return (
            any(ws.is_ready('subscription', i) for i in range(len(subs)))
            or any(ws.is_ready('client', i) for i in range(len(clients)))
            or any(ws.is_ready('service', i) for i in range(len(services)))
        )

    def final_status(self) -> None:
        """Stop the loop (zero current), publish everything it handed over and the drive's
        counters at exit (before a recorder in this process is closed)."""
        self.stop_loop()
        self.controller.flush_deferred()
        self.drive.publish_status()
        deadline = time.monotonic() + 2.0  # a topic a reader keeps blocked: bounded
        for p in self.publishers:
            p.stop(timeout=max(0.05, deadline - time.monotonic()))

    def spin_until(self, predicate: Callable[[], bool], timeout: float | None = None) -> bool:
        """Serve requests, results and pollers until ``predicate()`` (checked about every
        millisecond) or the timeout [s]; the loop runs in its thread meanwhile."""
        deadline = None if timeout is None else time.monotonic() + timeout
        try:
            while not self.stop_requested and rclpy.ok(context=self.drive.context):
                if self.failed is not None:
                    raise self.failed
                if not self.safe_stopped and self.should_stop():
                    self.safe_stop()
                self._service()
                if predicate():
                    return True
                if deadline is not None and time.monotonic() > deadline:
                    return False
                self._serve(SERVE_WAIT)
        except BaseException as exc:
            if not isinstance(exc, DriveLoopError):
                self.safe_stop()  # anything else on the way out: zero current first
            raise
        return predicate()

    def safe_stop(self) -> None:
        """Zero current and zero load torque to the drive now, latched for every later
        period (the loop may still run to serve the tuner's last calls). Every way out of
        a run comes here: :attr:`should_stop` (a signal), an exception in the loop,
        :meth:`destroy` (the run's end, a failure)."""
        with getattr(self, 'lock', None) or LoopGate():
            self.safe_stopped = True
            self.drive.safe_stop()

    def stop_loop(self, timeout: float = 2.0) -> None:
        """Zero current, then end the loop thread (idempotent). The loop is told to quit
        first, so at most the period under way runs after the safe stop."""
        self._quit = True
        self.lock.gate[G_QUIT] = 1  # a compiled loop returns after the safe stop's turn
        self.safe_stop()
        watch = getattr(self, '_stop_watch', None)
        if watch is not None:
            watch.close()
        thread = getattr(self, '_thread', None)
        if thread is None:
            return  # the bench failed before its loop was made
        self._go.set()
        if thread.is_alive() and thread is not threading.current_thread():
            thread.join(timeout)
        sys.setswitchinterval(self._switch_interval)

    def run(self) -> None:
        self.spin_until(lambda: False)

    # -- figures ---------------------------------------------------------------------------
    def timing(self) -> dict[str, Any]:
        """Per-period figures of the loop (us; over the whole run) and what the outbox
        could not deliver."""
        if self.compiled is not None:
            self.compiled.sync_figures()
        c = self.drive.counters
        counts = self.outbox.counts()
        out: dict[str, Any] = {
            'periods': self.periods,
            'overruns': int(self.pacer.overruns),
            # a drive that cannot pause: whole periods the late starts skipped (held)
            'missed_periods': int(self.pacer.missed_total),
            'max_lateness_us': round(float(self.pacer.max_lateness_us), 1),
            # period starts by lateness (pacing.LATENESS_BINS)
            'lateness_histogram': dict(zip(LATENESS_BINS, self.pacer.lateness_hist, strict=True)),
            'answers_missed': self.answers_missed,
            # the simulator's periods compiled (compiled_loop), or run as Python
            'compiled': self.compiled is not None,
            **(self.compiled.lateness_figures(self._t0) if self.compiled is not None else {}),
            'gc_young_runs': self.gc_runs,
            'gate_turns_boosted': self.lock.boosted,
            'realtime': self.rt_report,
            'drive': {k: getattr(c, k) for k in ('fresh', 'held', 'late', 'watchdog_trips')},
            # per topic: handed over, published, lost (a full ring), refused by rcl
            'outbox': counts,
            'outbox_lost': self.outbox.lost(),
        }
        d = self.durations
        out['drive_period_us'] = d.summary('drive')
        out['controller_answer_us'] = d.summary('answer')
        out['period_work_us'] = d.summary('work')
        out['lateness_us'] = d.summary('late')
        return out

    def destroy(self) -> None:
        """Zero current to the drive and close its hardware first, then the nodes."""
        try:
            self.stop_loop()
            self.drive.close_hardware()
        finally:
            gc.enable()
            gc.unfreeze()
            for p in getattr(self, 'publishers', []):
                p.stop(timeout=0.5)
            outbox = getattr(self, 'outbox', None)
            for ch in outbox.channels if outbox is not None else []:
                ROUTES.pop(id(ch.publisher), None)
            self.executor.shutdown()
            self.controller.destroy_node()
            self.drive.destroy_node()


def _nothing() -> None:
    pass
