"""The live side of ``ros2 run im_tuner replay``: a real controller re-driven from a bag.

:func:`replay` starts ``ros2 run im_controller controller`` as a child process (the
installed executable, as a user runs it) with the recorded parameters, in a namespace of
its own (``/replay_<pid>``, so a bench running on the same ROS domain is not touched), and
plays the drive's side of the wire (docs/interfaces.md) from the :class:`~.plan.ReplayPlan`:
for each fed state, the requests due before it (gains through
``set_parameters_atomically``, ``start_experiment``, as the tuner makes them), the
recorded ``/clock`` messages up to its time, the state itself, then a wait for the
command answering it. States go one at a time (lock-step pacing, whatever the recorded
mode): a state is sent once the answer to the one before came, so the controller sees
exactly the recorded sequence and nothing depends on this machine's speed.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
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
from im_drive_sim.contract import COMMAND_FIELDS, COMMAND_TOPIC, NS_PER_S, STATE_TOPIC
from im_drive_sim.qos import LOCKSTEP_QOS, RECORDED_QOS
from im_drive_sim.runtime import publish_lossless

from ..bench.forms import die_with_parent
from .plan import ReplayPlan

__all__ = ['ANSWER_TIMEOUT', 'READY_TIMEOUT', 'ReplayFailed', 'ReplayInconclusive', 'replay']

#: [s] the controller has to come up (import, numba cache, discovery) on a loaded machine
READY_TIMEOUT = 60.0
#: [s] for one answer or one service call; a controller that diverged (paused where the
#: recorded one stepped) never answers: the replay ends there
ANSWER_TIMEOUT = 10.0
#: parameters not passed on: the layout the node reports (read-only, its own), and the
#: watchdog, raised to its maximum: the replay's service calls between two states take
#: milliseconds, and a real-time controller's 0.25 s must not trip on a loaded machine
#: (it changes no command)
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
            self.proc = subprocess.Popen(
                self.cmd,
                stdout=out,
                stderr=subprocess.STDOUT,
                preexec_fn=die_with_parent,  # noqa: PLW1509 (only prctl, async-signal-safe)
            )

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

    def __init__(self, ns: str, context, width: int, child: _Child) -> None:
        self.child = child
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

    def wait_ready(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while not self.ready():
            self.child.check()
            if time.monotonic() > deadline:
                raise ReplayInconclusive(
                    f'the controller was not on the graph within {timeout:g} s'
                )
            self.executor.spin_once(timeout_sec=0.05)

    def _call(self, future, what: str):
        deadline = time.monotonic() + ANSWER_TIMEOUT
        while not future.done():
            self.child.check()
            if time.monotonic() > deadline:
                raise ReplayFailed(f'{what}: no answer within {ANSWER_TIMEOUT:g} s')
            self.executor.spin_once(timeout_sec=0.05)
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

    def wait_command(self, k: int, timeout: float) -> np.ndarray | None:
        """The command answering state ``k`` (others are skipped), or None at the timeout."""
        deadline = time.monotonic() + timeout
        n = len(COMMAND_FIELDS)
        while True:
            while (r := self.cmd_sub.handle.take_message(Float64MultiArray, True)) is not None:
                v = parse_float64_array(r[0], n)
                if v is not None and int(v[0]) == k:
                    return v.copy()
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self._ws.clear_entities()
            self._ws.add_subscription(self.cmd_sub.handle)
            self._ws.wait(int(min(left, 0.5) * NS_PER_S))
            self.child.check()

    def close(self) -> None:
        self.executor.shutdown()
        self.svc.destroy_node()
        self.io.destroy_node()


def replay(plan: ReplayPlan, progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """Re-drive a live controller through ``plan``; returns its commands, one row per fed
    state (NaN where none came: the replay stopped there, ReplayFailed is raised with the
    rows so far in ``exc.args[1]``)."""
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
            drive = _Drive(ns, context, plan.states.shape[1], child)
            drive.wait_ready(READY_TIMEOUT)
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
                    deadline = time.monotonic() + ANSWER_TIMEOUT
                    while not drive.start(int(what), k):  # type: ignore[call-overload]
                        if time.monotonic() > deadline:
                            raise ReplayFailed(
                                f'the start before step {k} was refused until the timeout'
                            )
                        drive.executor.spin_once(timeout_sec=0.02)
                if not sent:
                    drive.publish_state(state)
                cmd = drive.wait_command(k, ANSWER_TIMEOUT)
                if cmd is None:
                    raise ReplayFailed(
                        f'no command answering step {k} within {ANSWER_TIMEOUT:g} s '
                        '(the recorded controller answered it)',
                        out,
                    )
                out[i] = cmd
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
