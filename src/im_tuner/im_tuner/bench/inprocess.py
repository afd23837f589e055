"""The in-process lock-step bench: the drive simulator and the controller in one process.

Both nodes in one thread; each step the controller takes state k and answers, the drive
takes the command, steps and publishes state k+1 -- real DDS traffic, but no executor in
the per-step path (parameters and services are served every ``service_period_steps``
steps and whenever idle). Pollers (the recorder) run between steps, so not a message is
lost. The same seed gives bit-identical losses to the two-process bench.
"""

from __future__ import annotations

import dataclasses
import json
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor

from im_controller.controller_node import ControllerNode
from im_drive_sim.drive_sim_node import DriveSimNode

NS_PER_S = 1_000_000_000


def compose(drive, make_controller) -> tuple[ControllerNode, SingleThreadedExecutor]:
    """The controller (``make_controller()``) composed with ``drive`` in this process:
    a failed controller destroys the drive (``make_controller`` builds it
    ``composed_with=drive``: an override neither declares is refused); one executor
    serves both nodes' services."""
    try:
        controller = make_controller()
    except Exception:
        drive.destroy_node()
        raise
    executor = SingleThreadedExecutor(context=drive.context)
    executor.add_node(drive)
    executor.add_node(controller)
    return controller, executor


def run_before_start(bench, before_start) -> None:
    """``before_start(bench)`` (None: nothing), the bench destroyed if it raises."""
    if before_start is None:
        return
    try:
        before_start(bench)
    except Exception:
        bench.destroy()
        raise


class InProcessBench:
    """Drive simulator + controller in one process, stepped lock-step by hand.

    ``spin_until(predicate, timeout)`` advances the bench (steps when the controller
    answers, serves services when idle) until ``predicate()`` is true -- usable by tests
    and by the tuner running in the same process.
    """

    def __init__(
        self,
        *,
        context=None,
        drive_overrides: list | None = None,
        controller_overrides: list | None = None,
        before_start=None,
    ) -> None:
        """``before_start(bench)`` runs once both nodes exist and match, before state 0 is
        published: the place to start a recorder that must not miss the first message."""
        self.drive = DriveSimNode(
            context=context, parameter_overrides=drive_overrides, warn_unknown=False
        )
        self.controller, self.executor = compose(
            self.drive,
            lambda: ControllerNode(
                context=context,
                parameter_overrides=controller_overrides,
                composed_with=self.drive,
            ),
        )
        self.stop_requested = False
        self._since_service = 0
        #: (callable, period in steps): run every ``period`` lock-step round trips and at
        #: every idle iteration -- the recorder's poll goes here (see add_poller).
        self._pollers: list[tuple[object, int]] = []
        self._steps = 0
        # State 0 must not be published before the controller's subscription matches.
        if not self.controller.client.wait_for_drive(10.0):
            self.destroy()
            raise RuntimeError('controller and drive_sim did not match within 10 s')
        run_before_start(self, before_start)
        self.drive.start()
        # drive/status about once a second, as the drive's own loop publishes it
        self._t0 = time.perf_counter()
        self._next_status = self._t0 + 1.0

    def _status(self) -> None:
        now = time.perf_counter()
        if now >= self._next_status:
            self.drive.publish_status(now - self._t0)
            self._next_status = now + 1.0

    def final_status(self) -> None:
        """The drive's counters at exit (before a recorder in this process is closed)."""
        self.drive.publish_status(time.perf_counter() - self._t0)

    def add_poller(self, poll, period_steps: int = 16) -> None:
        """Call ``poll()`` every ``period_steps`` lock-step steps and whenever idle.

        For a recorder in this process: it must take its messages between steps (an
        executor callback would serve one message per spin). Fast DDS holds at most 5000
        samples per reader, so ``period_steps`` must stay far below that."""
        if not 1 <= period_steps <= 1000:
            raise ValueError(f'period_steps must be in [1, 1000], got {period_steps}')
        self._pollers.append((poll, int(period_steps)))

    def step(self, idle_timeout: float = 0.01) -> bool:
        """One bench iteration: a lock-step round trip if the controller steps, otherwise
        serve services for up to ``idle_timeout`` s. True if the drive stepped."""
        ctl = self.controller
        ctl.take()
        if ctl.answer():
            if not self.drive.lockstep_poll(NS_PER_S):
                raise RuntimeError('drive did not receive the command within 1 s')
            self._steps += 1
            for poll, period in self._pollers:
                if self._steps % period == 0:
                    poll()
            self._since_service += 1
            if self._since_service >= ctl.service_period_steps:
                self._since_service = 0
                self.executor.spin_once(timeout_sec=0.0)
                self._status()
            return True
        self._status()
        for poll, _period in self._pollers:
            poll()
        self.executor.spin_once(
            timeout_sec=idle_timeout if not self._pollers else min(idle_timeout, 0.002)
        )
        return False

    def spin_until(self, predicate, timeout: float | None = None) -> bool:
        """Run the bench until ``predicate()`` (checked between iterations) or timeout [s]."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self.stop_requested and rclpy.ok(context=self.drive.context):
            if predicate():
                return True
            if deadline is not None and time.monotonic() > deadline:
                return False
            self.step()
        return predicate()

    def run(self) -> None:
        self.spin_until(lambda: False)

    def destroy(self) -> None:
        self.executor.shutdown()
        self.controller.destroy_node()
        self.drive.destroy_node()


def bench_metadata(bench) -> dict[str, dict]:
    """What the bag should say about this bench: the drive's configuration and seed, and
    the controller's parameters at start."""
    d = bench.drive
    # any drive of the composed bench: the simulator, the example drive, a user's hardware
    # class or drive node (only the simulator has a seed and a model)
    hw = getattr(d, 'hw', None)
    cls = type(hw if hw is not None else d)
    # the delay the drive runs with: a hardware's declared one (its class or library),
    # else the drive file's; the config recorded is the one the drive runs with, so the
    # two agree (a library's declaration overrides the file's command_delay)
    delay = int(getattr(d, 'command_delay', d.config.command_delay))
    config = dataclasses.asdict(d.config) | {'command_delay': delay}
    drive = {
        'class': f'{cls.__module__}.{cls.__qualname__}',
        'config_file': (
            d.get_parameter('config_file').value if d.has_parameter('config_file') else ''
        )
        or '(packaged default)',
        'model': getattr(d.config, 'model', '-'),
        'config': json.dumps(config, sort_keys=True),
        'command_delay': delay,
    }
    probe = getattr(d, 'delay_probe', None)
    if probe is not None:  # the declared delay as measured at start (hardware_probe)
        drive['delay_probe'] = probe.text()
    if d.has_parameter('seed'):
        drive['seed'] = d.get_parameter('seed').value
    ctl = {
        name: p.value for name, p in sorted(bench.controller.get_parameters_by_prefix('').items())
    }
    out = {
        'im_tuner.drive': drive,
        'im_tuner.controller': {'parameters': json.dumps(ctl, sort_keys=True, default=str)},
    }
    rt_report = getattr(bench, 'rt_report', None)
    if rt_report is not None:  # the composed real-time loop's scheduling
        out['im_tuner.realtime'] = dict(rt_report)  # (an MCAP metadata record: JSON values)
    return out
