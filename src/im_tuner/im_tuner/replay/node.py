"""The live side of ``ros2 run im_tuner replay``: a real controller re-driven from a bag.

:func:`replay` starts ``ros2 run im_controller controller`` as a child process with the
recorded parameters, in a namespace of its own (``/replay_<pid>``), and plays the drive's
side of the wire from the :class:`~.plan.ReplayPlan`, one state at a time, each once the
answer to the one before came (docs/replay.md, "How it works")."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import rclpy
import yaml
from rclpy.executors import SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from im_controller import contract as C
from im_controller.config import GAIN_NAMES
from im_drive_sim.cdr import Float64ArrayWire, parse_float64_array
from im_drive_sim.cli import spawn_child
from im_drive_sim.contract import COMMAND_FIELDS, COMMAND_TOPIC, NS_PER_S, STATE_TOPIC
from im_drive_sim.qos import LOCKSTEP_QOS, RECORDED_QOS
from im_drive_sim.runtime import publish_lossless

from ..patience import IDLE_S, Patience
from .plan import ReplayPlan

# The replay waits for the controller while it works (im_tuner.patience); an answer missing
# while it idles for IDLE_S ends the replay (exit 1), READY_IDLE_S of idleness before it is
# on the graph makes it inconclusive (exit 3).
READY_IDLE_S = 30.0  #: [s] idle before it is on the graph
#: parameters not passed on (the node's own layout), and the watchdog raised: requests
#: between two states must not trip it (docs/replay.md, "How it works")
NOT_PASSED = ('internals_fields',)
OVERRIDES = {'state_timeout': 60.0}


class ReplayFailed(Exception):
    """The live controller did not do what the recorded one did (exit 1)."""


class ReplayInconclusive(Exception):
    """The live controller never came up, or died: nothing compared (exit 3)."""


def controller_executable() -> Path:
    """``<prefix>/lib/im_controller/controller``: what ``ros2 run im_controller controller``
    runs, found as ros2cli finds it (this Python's prefix first, then the ament index)."""
    prefixes = [sys.prefix, *os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)]
    for p in prefixes:
        exe = Path(p) / 'lib' / 'im_controller' / 'controller'
        if p and exe.is_file() and os.access(exe, os.X_OK):
            return exe
    raise ReplayInconclusive('no im_controller controller executable installed')


class _Child:
    """The controller process: started with the recorded parameters, ended by its PID."""

    def __init__(self, plan: ReplayPlan, ns: str, tmp: Path) -> None:
        params = {k: v for k, v in plan.params.items() if k not in NOT_PASSED} | OVERRIDES
        pfile = tmp / 'controller.yaml'
        pfile.write_text(yaml.safe_dump({'/**': {'ros__parameters': params}}))
        self.log = tmp / 'controller.log'
        self.cmd = [
            str(controller_executable()),
            '--ros-args',
            '--params-file',
            str(pfile),
            '-r',
            f'__ns:={ns}',
            '-r',
            f'/clock:={ns}/clock',
        ]
        with open(self.log, 'wb') as out:
            self.proc = spawn_child(self.cmd, stdout=out, stderr=subprocess.STDOUT)

    def check(self) -> None:
        code = self.proc.poll()
        if code is not None:
            lines = self.log.read_text(errors='replace').strip().splitlines()
            raise ReplayInconclusive(
                f'the controller exited with code {code}: {lines[-1] if lines else "(no output)"}'
            )

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class _Drive:
    """The drive's side of the wire: states and /clock out, commands in (no executor on
    the 5 kHz path: a WaitSet, as ``im_drive_sim.client.DriveClient``), and the tuner's
    requests through an executor of their own."""

    def __init__(
        self, ns: str, context, width: int, child: _Child, note: Callable[[str], None] | None
    ) -> None:
        self.child = child
        self.note = note
        self.io = Node('replay_drive', namespace=ns, context=context)
        self.state_pub = self.io.create_publisher(Float64MultiArray, STATE_TOPIC, RECORDED_QOS)
        self.clock_pub = self.io.create_publisher(Clock, 'clock', RECORDED_QOS)
        self.cmd_sub = self.io.create_subscription(
            Float64MultiArray, COMMAND_TOPIC, lambda _m: None, LOCKSTEP_QOS
        )
        self.wire = Float64ArrayWire(width)
        self._ws = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, context.handle)
        self.svc = Node('replay_tuner', namespace=ns, context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.svc)
        controller = f'{ns}/controller'
        self.params = AsyncParameterClient(self.svc, controller)
        self.start_cli = self.svc.create_client(Trigger, f'{controller}/{C.START_SERVICE}')
        self.context = context

    def ready(self) -> bool:
        return (
            self.state_pub.get_subscription_count() > 0
            and self.cmd_sub.get_publisher_count() > 0
            and self.start_cli.service_is_ready()
            and self.params.services_are_ready()
        )

    def patience(self, what: str, idle_s: float = IDLE_S, error=ReplayFailed) -> Patience:
        return Patience(
            self.child.proc.pid, what, error, idle_s=idle_s, note=self.note, alive=self.child.check
        )

    def spin_until(self, done: Callable[[], bool], wait: Patience, period: float = 0.05) -> None:
        """Spin the requests' executor until ``done()``, as long as ``wait`` allows."""
        while not done():
            wait.check()
            self.executor.spin_once(timeout_sec=period)

    def wait_ready(self) -> None:
        wait = self.patience('the controller on the graph', READY_IDLE_S, ReplayInconclusive)
        self.spin_until(self.ready, wait)

    def _call(self, future, what: str):
        self.spin_until(future.done, self.patience(f'the answer to {what}'))
        return future.result()

    def set_gains(self, gains: tuple[float, ...], step: int) -> None:
        ps = [
            Parameter(n, Parameter.Type.DOUBLE, v) for n, v in zip(GAIN_NAMES, gains, strict=True)
        ]
        res = self._call(self.params.set_parameters_atomically(ps), 'set_parameters_atomically')
        if not res.result.successful:
            raise ReplayFailed(
                f'before step {step} the controller refused the gains: {res.result.reason}'
            )

    def start(self, eid: int, step: int) -> bool:
        """Start experiment ``eid``; False if refused for want of a drive state (the
        first state is not taken yet: ask again)."""
        resp = self._call(self.start_cli.call_async(Trigger.Request()), 'start_experiment')
        if not resp.success:
            if C.refusal_code(resp.message) == C.NO_DRIVE_STATE:
                return False
            raise ReplayFailed(
                f'before step {step} the controller refused the start: {resp.message}'
            )
        got = C.started_id(resp.message)
        if got != eid:
            raise ReplayFailed(
                f'before step {step} the controller started experiment {got}, not {eid}'
            )
        return True

    def publish_state(self, state: np.ndarray) -> None:
        self.wire.values[:] = state
        publish_lossless(self.state_pub, self.wire, self.context)

    def publish_clock(self, raw: bytes) -> None:
        publish_lossless(self.clock_pub, raw, self.context)

    def wait_command(self, k: int) -> np.ndarray:
        """The command answering state ``k`` (others are skipped); ReplayFailed once the
        controller sits idle without it (:class:`_Patience`)."""
        n = len(COMMAND_FIELDS)
        wait = None
        while True:
            while (r := self.cmd_sub.handle.take_message(Float64MultiArray, True)) is not None:
                v = parse_float64_array(r[0], n)
                if v is not None and int(v[0]) == k:
                    return v.copy()
            self._ws.clear_entities()
            self._ws.add_subscription(self.cmd_sub.handle)
            self._ws.wait(int(0.5 * NS_PER_S))
            if wait is None:  # (built only when an answer is slow: /proc is read then)
                wait = self.patience(
                    f'the command answering step {k} (the recorded controller answered it)'
                )
            wait.check()

    def close(self) -> None:
        self.executor.shutdown()
        self.svc.destroy_node()
        self.io.destroy_node()


def replay(
    plan: ReplayPlan,
    progress: Callable[[int, int], None] | None = None,
    note: Callable[[str], None] | None = None,
) -> np.ndarray:
    """Re-drive a live controller through ``plan``; returns its commands, one row per fed
    state (NaN where none came: the replay stopped there, ReplayFailed is raised with the
    rows so far in ``exc.args[1]``). ``note``: a line of what a long wait waits for."""
    ns = f'/replay_{os.getpid()}'
    n = len(plan.states)
    out = np.full((n, len(COMMAND_FIELDS)), np.nan)
    requests = plan.requests()
    context = rclpy.Context()
    # no rclpy signal handlers: Ctrl-C must raise KeyboardInterrupt here (the command
    # then ends the controller and exits 130), not only shut the context down
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    with tempfile.TemporaryDirectory(prefix='im_tuner_replay_') as tmp:
        child = _Child(plan, ns, Path(tmp))
        drive = None
        try:
            drive = _Drive(ns, context, plan.states.shape[1], child, note)
            drive.wait_ready()
            clock_i = 0
            for i in range(n):
                state = plan.states[i]
                k = int(state[0])
                t_ns = int(state[1])
                while clock_i < len(plan.clock_ns) and plan.clock_ns[clock_i] <= t_ns:
                    drive.publish_clock(plan.clock_raw[clock_i])
                    clock_i += 1
                sent = False
                for kind, what in requests.get(i, []):
                    if kind == 'gains':
                        drive.set_gains(what, k)  # type: ignore[arg-type]
                        continue
                    if i == 0:  # a start needs a state taken: the first goes out first
                        drive.publish_state(state)
                        sent = True
                    wait = drive.patience(f'the start before step {k} (refused: no state yet)')
                    start = partial(drive.start, int(what), k)  # type: ignore[call-overload]
                    drive.spin_until(start, wait, 0.02)
                if not sent:
                    drive.publish_state(state)
                out[i] = drive.wait_command(k)
                if progress is not None:
                    progress(i + 1, n)
        except ReplayFailed as exc:
            raise ReplayFailed(exc.args[0], out) from None
        finally:
            if drive is not None:
                drive.close()
            child.stop()
            rclpy.try_shutdown(context=context)
    return out
