"""The composed real-time bench: a drive and the controller in ONE process, one loop.

Why: a Python controller in its own process, woken by DDS, cannot hold 5 kHz on a 2-core
machine (a bare two-process rclpy round trip is 150-235 us, more than the 200 us period;
docs/real-drive.md). ros2_control loads controllers into the process that owns the
hardware for the same reason. Here both stay separate rclpy nodes -- their own topics,
parameters and services on the graph, the same classes as ``drive_sim``/``example_drive``
and ``controller`` -- composed into one process (as rclcpp_components does), and one
real-time loop runs them, every Ts = 200 us on the wall clock (:class:`pacing.Pacer`):

1. at the period start, the drive takes the command(s), runs its watchdog, steps the
   model or writes/reads the hardware, and publishes state k (``applied_step`` = the
   command it applied);
2. the controller takes state k and answers (``drive/command``, internals, and a loss at
   the end of an experiment);
3. the drive takes that command at once: it drives the next period (fresh);
4. then, in the rest of the period: the recorder takes its messages (in a period with
   slack; at least every ``RECORD_POLL_STEPS`` periods), parameter and service requests
   are served (every
   ``service_period_steps`` periods, when any is pending), the drive status once a second.

The drive side is pluggable (:func:`make_drive`): the simulator in real time (the default),
the example drive, or a user's class named ``package.module:Class`` -- a hardware class
like ``example_drive.Hardware`` (``Class(config)`` with ``read()``/``write()``) run inside
the example drive's ROS side, or a whole drive node class (an ``ExampleDrive`` subclass);
:mod:`.drive_spec` checks a class against that contract.

Python's own jitter is kept out of the loop: nothing is allocated per period by the loop
itself (the per-period timings go into preallocated arrays), no logging on the hot path,
and the garbage collector is frozen at start (``gc.freeze``: the long-lived objects of the
set-up are never scanned again) and run by hand, young generation only, at the end of a
period with time left. :meth:`RealtimeBench.timing` reports the per-period work against
the 200 us budget.
"""

from __future__ import annotations

import gc
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.parameter import Parameter

from im_controller.controller_node import ControllerNode
from im_drive_sim import rt
from im_drive_sim.pacing import LATENESS_BINS, Pacer

from ..tuning import BenchFailure
from .drive_spec import DriveChoice, build_node, resolve
from .inprocess import compose

#: Periods of per-period timings kept (a ring): 10 min at 5 kHz.
TIMING_CAPACITY = 3_000_000


class DriveLoopError(BenchFailure):
    """The real-time loop raised (a hardware class's read/write, a node's period): the
    drive was safe-stopped and the loop runs no more; the run ends as a bench failure
    (the message says where)."""


def _where(exc: BaseException) -> str:
    """``file:line in function`` of the innermost frame of ``exc``'s traceback."""
    tb = exc.__traceback__
    if tb is None:
        return 'unknown'
    while tb.tb_next is not None:
        tb = tb.tb_next
    code = tb.tb_frame.f_code
    return f'{code.co_filename}:{tb.tb_lineno} in {code.co_name}'


def make_drive(spec: str | DriveChoice, context: Any, overrides: list[Parameter]) -> Any:
    """The drive node named by ``spec`` (see the module docstring; a DriveChoice is a
    ``--drive`` already checked, with its hardware built: ``drive_spec.resolve``), in
    real time.

    ``overrides``: the tuner's drive parameters; the simulator takes them all (seed,
    model, config_file), the example drive and a user's drive only ``config_file``."""
    choice = spec if isinstance(spec, DriveChoice) else None
    name = choice.spec if choice is not None else spec
    assert isinstance(name, str)
    if name == 'sim':
        from im_drive_sim.drive_sim_node import DriveSimNode

        return DriveSimNode(
            context=context,
            parameter_overrides=[
                Parameter('mode', value='realtime'),
                Parameter('realtime_wait_for_controller', value=False),
                *overrides,
            ],
            warn_unknown=False,
        )
    from im_drive_sim.example_drive import ExampleDrive

    mine = [p for p in overrides if p.name == 'config_file']
    if name == 'example':
        return ExampleDrive(context=context, parameter_overrides=mine)
    return build_node(choice or resolve(name, None, build=False), context, mine)


class RealtimeBench:
    """A drive + the controller in this process, one real-time loop (module docstring).

    The same interface as the lock-step ``InProcessBench``: ``spin_until(predicate,
    timeout)`` runs periods until ``predicate()``; pollers (the recorder) run between
    periods; the tuner's node can be added to :attr:`executor`.
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
    ) -> None:
        """``before_start(bench)`` runs once both nodes exist and match, before state 0:
        the place to start a recorder that must not miss the first message.
        ``should_stop()``: checked every 5 periods; once True the drive is safe-stopped
        (zero current, latched) -- the tuner's SIGINT/SIGTERM. ``rt_options``: the
        loop thread's real-time scheduling (:mod:`im_drive_sim.rt`), applied here, before
        the recorder starts (its metadata records it); what is not permitted is said in
        one line each on stderr, and the run goes on."""
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
                warn_unknown=False,
            ),
        )
        self.stop_requested = False
        #: called between periods (every 5): True -> :meth:`safe_stop` (the tuner's
        #: SIGINT/SIGTERM: zero current within a millisecond, before anything else)
        self.should_stop: Callable[[], bool] = should_stop or (lambda: False)
        self.safe_stopped = False
        self.failed: DriveLoopError | None = None  #: the loop raised: it runs no more
        self._pollers: list[tuple[Callable[[], Any], int]] = []
        self._polled: list[int] = []  # the period each poller last ran
        self.service_period = int(self.controller.service_period_steps)
        # a cheap test for pending requests: one WaitSet over every service and client of
        # the executor's nodes (built from the nodes' entity lists; rebuilt when they change)
        self._service_ws: Any = None
        self._service_count = -1
        if not self.controller.client.wait_for_drive(10.0):
            self.destroy()
            raise RuntimeError('the controller and the drive did not match within 10 s')
        opts = rt_options or rt.RtOptions()
        refused = rt.apply(opts) if opts.requested else []
        for line in refused:
            print(f'warning: {line}', file=sys.stderr, flush=True)
        #: the loop thread's scheduling (policy, priority, affinity, memory lock, kernel,
        #: CPU): in the summary and the bag's metadata
        self.rt_report: dict[str, Any] = rt.report(opts, refused)
        if before_start is not None:
            try:
                before_start(self)
            except Exception:
                self.destroy()
                raise
        ts = float(self.controller.Ts)
        self.pacer = Pacer(
            ts,
            float(getattr(self.drive, 'spin_margin', 150e-6)),
            # a drive that cannot pause: late starts are periods held (docs/real-drive.md)
            wall_clock=bool(getattr(self.drive, 'wall_clock', False)),
        )
        # per-period timings [us] (a ring): the drive's period done (state k published),
        # the controller's answer out, the command taken by the drive, the whole period
        self.t_state = np.zeros(TIMING_CAPACITY, np.float32)
        self.t_answer = np.zeros(TIMING_CAPACITY, np.float32)
        self.t_work = np.zeros(TIMING_CAPACITY, np.float32)
        self.periods = 0
        self.answers_missed = 0  #: periods whose state the controller had no answer for
        self.gc_runs = 0
        self._t0 = time.perf_counter()
        self._next_status = self._t0 + 1.0
        gc.collect()
        gc.freeze()  # the set-up's objects: never scanned again
        gc.disable()  # young-generation collections by hand, in a period's slack
        self.drive.start()
        # state 0 answered before the clock starts: the first period is driven fresh
        deadline = time.monotonic() + 1.0
        while not self.controller.answer() and time.monotonic() < deadline:
            self.controller.take(0.01)
        self.drive.take_commands()
        self.pacer.restart()

    # -- the loop --------------------------------------------------------------------------
    def add_poller(self, poll: Callable[[], Any], period_steps: int = 16) -> None:
        """Call ``poll()`` at least every ``period_steps`` periods, and earlier (every
        period_steps / 8) in a period with slack: small polls keep each period's work
        under the budget (the recorder: it must take its messages between periods; Fast
        DDS keeps at most 5000 samples per reader)."""
        if not 1 <= period_steps <= 1000:
            raise ValueError(f'period_steps must be in [1, 1000], got {period_steps}')
        self._pollers.append((poll, int(period_steps)))
        self._polled.append(0)

    def step(self) -> bool:
        """One real-time period (module docstring). Returns True."""
        drive, ctl, pacer = self.drive, self.controller, self.pacer
        t0 = pacer.wait(drive.wait_command, drive.take_commands)
        c = drive.counters
        c.overruns, c.max_lateness_us = pacer.overruns, pacer.max_lateness_us
        if pacer.missed:
            drive.period(pacer.missed)  # periods that went by, the old command held
        else:
            drive.period()
        t1 = time.perf_counter()
        ctl.take()
        if not ctl._pending:
            # DDS has not handed the state over yet: wait for it within this period
            ctl.take(max(1e-6, t0 + 0.5 * pacer.ts - time.perf_counter()))
        answered = ctl.answer()
        t2 = time.perf_counter()
        if answered:
            drive.take_commands()  # fresh for the next period
        else:
            self.answers_missed += 1
        i = self.periods % TIMING_CAPACITY
        self.t_state[i] = 1e6 * (t1 - t0)
        self.t_answer[i] = 1e6 * (t2 - t1)
        self.periods += 1
        n = self.periods
        # pollers: in a period with slack, once `every/8` periods passed; always once
        # `every` passed (a reader's backlog stays bounded either way)
        slack = time.perf_counter() - t0 < 0.4 * pacer.ts
        for j, (poll, every) in enumerate(self._pollers):
            since = n - self._polled[j]
            if since >= every or (slack and since >= max(1, every // 8)):
                poll()
                self._polled[j] = n
                slack = False
        if n % self.service_period == 0:
            self._serve()
        if n % 5000 == 0:
            self._status()
        # the young generation, by hand, only with half a period left
        if gc.get_count()[0] > 2000 and time.perf_counter() - t0 < 0.5 * pacer.ts:
            gc.collect(0)
            self.gc_runs += 1
        self.t_work[i] = 1e6 * (time.perf_counter() - t0)
        return True

    def _serve(self) -> None:
        """Serve parameter/service requests and the tuner's responses, if any is pending:
        a full executor spin costs ~400 us, a wait on the prebuilt WaitSet a few."""
        if self._pending_requests():
            self.executor.spin_once(timeout_sec=0.0)

    def _pending_requests(self) -> bool:
        nodes = list(self.executor.get_nodes())
        services = [s for n in nodes for s in n.services]
        clients = [c for n in nodes for c in n.clients]
        subs = [
            s
            for n in nodes
            for s in n.subscriptions
            if n is not self.drive and n is not self.controller
        ]
        timers = [t for n in nodes for t in n.timers]
        guards = [g for n in nodes for g in n.guards]
        count = len(services) + len(clients) + len(subs) + len(timers) + len(guards)
        if timers or guards:
            return True  # something this test does not cover: spin every time
        if count != self._service_count:
            self._service_count = count
            self._entities = (services, clients, subs)
            self._service_ws = _rclpy.WaitSet(
                len(subs), 0, 0, len(clients), len(services), 0, self.drive.context.handle
            )
        services, clients, subs = self._entities
        ws = self._service_ws
        ws.clear_entities()
        for s in subs:
            ws.add_subscription(s.handle)
        for c in clients:
            ws.add_client(c.handle)
        for s in services:
            ws.add_service(s.handle)
        ws.wait(0)
        return (
            any(ws.is_ready('subscription', i) for i in range(len(subs)))
            or any(ws.is_ready('client', i) for i in range(len(clients)))
            or any(ws.is_ready('service', i) for i in range(len(services)))
        )

    def _status(self) -> None:
        now = time.perf_counter()
        if now >= self._next_status:
            self.drive.publish_status()
            self._next_status = now + 1.0

    def final_status(self) -> None:
        """The drive's counters at exit (before a recorder in this process is closed)."""
        self.drive.publish_status()

    def spin_until(self, predicate: Callable[[], bool], timeout: float | None = None) -> bool:
        """Run periods until ``predicate()`` (checked between periods, every 5 periods
        once it was false) or the timeout [s]; requests are served every period here
        (the tuner is waiting on one)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        if self.failed is not None:  # a loop that raised runs no more periods
            raise DriveLoopError('the real-time loop stopped earlier (see above)')
        try:
            while not self.stop_requested and rclpy.ok(context=self.drive.context):
                if not self.safe_stopped and self.should_stop():
                    self.safe_stop()
                if predicate():
                    return True
                if deadline is not None and time.monotonic() > deadline:
                    return False
                for _ in range(5):
                    self.step()
                self._serve()  # the tuner waits on a response: serve it within a ms
        except BaseException as exc:
            self.safe_stop()  # an exception in the loop: zero current before anything else
            if isinstance(exc, Exception) and not isinstance(exc, BenchFailure):
                self.failed = DriveLoopError(
                    f'the real-time loop stopped on {type(exc).__name__}: {exc} (in '
                    f'{_where(exc)}); zero current and zero load were written to the drive'
                )
                raise self.failed from exc
            raise
        return predicate()

    def safe_stop(self) -> None:
        """Zero current and zero load torque to the drive now, latched for every later
        period (the loop may still run to serve the tuner's last calls). Every way out of
        a run comes here: :attr:`should_stop` (a signal), an exception in the loop,
        :meth:`destroy` (the run's end, a failure)."""
        self.safe_stopped = True
        stop = getattr(self.drive, 'safe_stop', None)
        if callable(stop):
            stop()

    def run(self) -> None:
        self.spin_until(lambda: False)

    # -- figures ---------------------------------------------------------------------------
    def timing(self) -> dict[str, Any]:
        """Per-period figures of the loop (us; over the last TIMING_CAPACITY periods)."""
        n = min(self.periods, TIMING_CAPACITY)
        c = self.drive.counters
        out: dict[str, Any] = {
            'periods': self.periods,
            'overruns': int(self.pacer.overruns),
            # a drive that cannot pause: whole periods the late starts skipped (held)
            'missed_periods': int(self.pacer.missed_total),
            'max_lateness_us': round(float(self.pacer.max_lateness_us), 1),
            # period starts by lateness (pacing.LATENESS_BINS)
            'lateness_histogram': dict(zip(LATENESS_BINS, self.pacer.lateness_hist, strict=True)),
            'answers_missed': self.answers_missed,
            'gc_young_runs': self.gc_runs,
            'realtime': self.rt_report,
            'drive': {k: getattr(c, k) for k in ('fresh', 'held', 'late', 'watchdog_trips')},
        }
        for name, arr in (
            ('drive_period_us', self.t_state),
            ('controller_answer_us', self.t_answer),
            ('period_work_us', self.t_work),
        ):
            a = arr[:n]
            out[name] = (
                {
                    'p50': round(float(np.percentile(a, 50)), 1),
                    'p99': round(float(np.percentile(a, 99)), 1),
                    'max': round(float(a.max()), 1),
                }
                if n
                else None
            )
        return out

    def destroy(self) -> None:
        """Zero current to the drive and close its hardware first, then the nodes."""
        gc.enable()
        gc.unfreeze()
        try:
            self.safe_stop()
            close = getattr(self.drive, 'close_hardware', None)
            if callable(close):
                close()
        finally:
            self.executor.shutdown()
            self.controller.destroy_node()
            self.drive.destroy_node()
