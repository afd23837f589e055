"""ROS 2 node of the cascaded controller: ``ros2 run im_controller controller``.

A thin node around :class:`im_controller.runner.ExperimentRunner` (docs/controller.md,
section 8): it answers every drive state with ``drive/command`` through a WaitSet on a
hidden io node (no executor in the 5 kHz path); its parameters are declared by
``declarations``, made configuration by ``parameters`` and refused by ``refusals``.
"""

from __future__ import annotations

import collections
import contextlib
import math
import sys
import time
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.service_introspection import ServiceIntrospectionState
from std_msgs.msg import Float64MultiArray, Header
from std_srvs.srv import Trigger

from im_drive_sim.cdr import Float64ArrayWire
from im_drive_sim.cli import parse_cli, run_cli
from im_drive_sim.client import DriveClient
from im_drive_sim.contract import STATE_FIELDS
from im_drive_sim.qos import RECORDED_QOS, SERVICES_QOS
from im_drive_sim.runtime import (
    IoNodeOwner,
    LenientDoubles,
    parameter_hygiene,
    publish_lossless,
    run_stepped_node,
    start_overrides,
)

from . import contract as C
from .config import GAIN_NAMES, ControllerConfigError, ExperimentConfig, Gains
from .contract import INTERNALS_TOPIC, LOSS_TOPIC
from .controller_main import parser
from .declarations import declare_structure, declare_tunables
from .kernel import N_ANSWER_WORDS, W_ANSWERED, W_DECIMATION, W_INTERNALS_DUE, answer_state
from .layout import (
    INTERNALS_FIELDS,
    REASON_DRIVE_TIMEOUT,
    REASON_TUNER_LOST,
    STATUS_ABORTED,
    STATUS_DONE,
    STATUS_FAULT,
)
from .messages import result_to_msg
from .parameters import ControllerError, configuration
from .refusals import change_refusal, reset_refusal, start_refusal
from .reset_fault import reset_command, service_name
from .result import LossResult
from .runner import ExperimentRunner

#: Shortest time between two logged refusals of one kind [s] (all are counted).
REFUSAL_LOG_PERIOD = 1.0


class ControllerNode(IoNodeOwner, LenientDoubles, Node):
    """The cascaded controller node. ``warn_unknown``: warn of ``-p`` overrides it does not
    declare; ``composed_with``: the drive node composed with it, whose parameters those
    overrides may name instead (one neither declares: ParameterOverrideError)."""

    def __init__(
        self,
        *,
        node_name: str = 'controller',
        context=None,
        parameter_overrides: list | None = None,
        warn_unknown: bool = True,
        composed_with: Node | None = None,
    ) -> None:
        super().__init__(node_name, context=context, parameter_overrides=parameter_overrides)
        st = declare_structure(self)
        declare_tunables(self)
        self.mode, self.lockstep_idle = st.mode, st.lockstep_idle
        self.Ts, self.isq_max, self.state_timeout = st.Ts, st.isq_max, st.state_timeout
        self.internals_decimation = st.internals_decimation
        self.service_period_steps = st.service_period_steps
        self.timing_tolerance = st.timing_tolerance
        cfg, gains = self._candidate({})
        self.runner = ExperimentRunner(cfg, gains, timing_tolerance=self.timing_tolerance)
        #: refused requests, by kind (logged, throttled; and at exit)
        self.refused = {'start_experiment': 0, 'parameters': 0}
        #: Monotonic time [s] of the last refusal logged, per kind (the log throttle).
        self._refusal_logged = dict.fromkeys(self.refused, -math.inf)
        self.add_pre_set_parameters_callback(self.integers_as_doubles)
        self.add_on_set_parameters_callback(self._on_set)
        self.add_post_set_parameters_callback(self._post_set)

        parameter_hygiene(
            self,
            {'internals_fields': list(INTERNALS_FIELDS)},
            warn_unknown=warn_unknown,
            composed_with=composed_with,
        )

        self.io_node = Node(f'_{node_name}_io', context=context, namespace=self.get_namespace())
        self.client = DriveClient(self.io_node)
        # Reliable KEEP_ALL: every loss and every internals sample reaches the recorder.
        self.loss_pub = self.create_publisher(DiagnosticArray, LOSS_TOPIC, RECORDED_QOS)
        self.internals_pub = self.create_publisher(Float64MultiArray, INTERNALS_TOPIC, RECORDED_QOS)
        self._internals = Float64ArrayWire(len(INTERNALS_FIELDS))
        #: ``kernel.answer_state``'s words and command (W_ANSWERED: ``client.answered``)
        self._words = np.zeros(N_ANSWER_WORDS, np.int64)
        self._words[W_DECIMATION] = self.internals_decimation
        self._cmd = np.zeros(3)
        # The kernel compiled (or loaded from numba's cache) now, on scratch arrays: on a
        # cold cache its seconds of compiling would otherwise trip the state watchdog.
        self._answer(ExperimentRunner(cfg, gains), np.zeros(len(STATE_FIELDS)), self._words.copy())
        self.start_srv = self.create_service(
            Trigger, f'~/{C.START_SERVICE}', self._on_start, qos_profile=SERVICES_QOS
        )
        self.tuner_timeout = st.tuner_timeout
        self._heartbeat_wall: float | None = None  # monotonic [s] of the last heartbeat
        self.heartbeat_from = ''  #: the frame_id (node name) of the last heartbeat
        self.tuner_trips = 0  #: times the tuner watchdog tripped
        self._tuner_tripped = False
        if self.tuner_timeout > 0:
            # best effort, newest only: a lost heartbeat is replaced by the next one
            self.heartbeat_sub = self.create_subscription(
                Header,
                f'~/{C.HEARTBEAT_TOPIC}',
                self._on_heartbeat,
                QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT),
            )
        self.reset_srv = self.create_service(
            Trigger, f'~/{C.RESET_SERVICE}', self._on_reset_fault, qos_profile=SERVICES_QOS
        )
        # Service introspection (contents on <service>/_service_event): the recorder keeps
        # who changed which gain when (get_type_description does not support it).
        for srv in list(self.services):
            if not srv.srv_name.endswith('get_type_description'):
                srv.configure_introspection(
                    self.get_clock(),
                    SERVICES_QOS,
                    ServiceIntrospectionState.CONTENTS,
                )

        self.next_experiment_id = int(st.first_experiment_id)
        #: what the fault messages tell a user to run (the shipped ros2 has only `run`)
        self._reset_command = reset_command(self.get_fully_qualified_name())
        self._reset_service = service_name(self.get_fully_qualified_name())
        self.results = []  #: every LossResult published, in order
        self.stop_requested = False
        self._state: np.ndarray | None = None  # newest state taken
        self._pending = False  # ... and not answered yet
        self._last_state_wall = time.monotonic()
        self._last_msg_wall = time.monotonic()  # any state message, re-sent ones too
        self._timeout_wall: float | None = None  # when the drive-state watchdog tripped
        self._initialised = False  # the hold reference is set from the first state
        self._fault_logged = False
        #: held while a request changes what the loop runs (gains, experiment start, fault
        #: reset): a composed real-time loop (im_tuner.bench.realtime) runs the 5 kHz path
        #: in its own thread under the same lock; alone, there is one thread and no lock
        self.loop_lock: Any = contextlib.nullcontext()
        #: composed loop: experiment ends (status, result) the loop thread leaves for the
        #: serving thread to publish and log (:meth:`flush_deferred`); None: at once
        self.deferred: collections.deque | None = None
        self.get_logger().info(
            f'mode={self.mode} Ts={self.Ts * 1e6:.0f} us isq_max={self.isq_max:g} A '
            f'gains={dict(zip(GAIN_NAMES, gains.as_tuple(), strict=True))}'
        )

    def _candidate(self, changes: dict[str, object]) -> tuple[ExperimentConfig, Gains]:
        """The configuration the node would have with ``changes`` applied: validated
        (``parameters.configuration``; ControllerConfigError names the bad parameter)."""
        return configuration(
            lambda name: changes[name] if name in changes else self.get_parameter(name).value,
            self.Ts,
            self.isq_max,
        )

    def _on_set(self, params: list[Parameter]) -> SetParametersResult:
        """Validate a whole change (one parameter or an atomic set): all or nothing."""
        reason = change_refusal([(p.name, p.value) for p in params], self.runner)
        if reason is None:
            try:
                self._candidate({p.name: p.value for p in params})
            except ControllerConfigError as exc:
                reason = C.refusal(C.INVALID, str(exc))
        if reason is None:
            return SetParametersResult(successful=True)
        self._refusal('parameters', f'parameter change refused: {reason}')
        return SetParametersResult(successful=False, reason=reason)

    def _refusal(self, kind: str, text: str) -> None:
        """Count a refused request and log it at most once a second per kind (per kind, not
        per call site: a flood of refused starts cannot hide a refused parameter change)."""
        self.refused[kind] += 1
        now = time.monotonic()
        if now - self._refusal_logged[kind] >= REFUSAL_LOG_PERIOD:
            self._refusal_logged[kind] = now
            self.get_logger().warn(f'{text} ({self.refused[kind]} {kind} requests refused so far)')

    def _post_set(self, params: list[Parameter]) -> None:
        cfg, gains = self._candidate({})
        tolerance = int(self.get_parameter('timing_tolerance').value)
        with self.loop_lock:
            self.runner.set_config(cfg)
            self.runner.set_gains(gains)
            self.runner.timing_tolerance = tolerance
        if tolerance != self.timing_tolerance:
            self.get_logger().info(
                f'timing tolerance {tolerance} held + late periods per experiment '
                f'(was {self.timing_tolerance}), from the next experiment on'
            )
            self.timing_tolerance = tolerance

    def _on_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        r = self.runner
        reason = start_refusal(
            r,
            self._state is not None,
            f'`{self._reset_command}` (the {self._reset_service} service)',
        )
        if reason is not None:
            response.success = False
            response.message = reason
            self._refusal('start_experiment', f'start_experiment {reason}')
            return response
        eid = self.next_experiment_id
        # The gains were applied when they were set (post-set callback); only after a
        # supervisor stop, whose fallback gains finished the move, do the parameters'
        # gains go back in here. Applied once per evaluation either way.
        gains = Gains(*(self.get_parameter(n).value for n in GAIN_NAMES))
        with self.loop_lock:
            r.start(eid, None if r.gains == gains else gains)
        self.next_experiment_id += 1
        response.success = True
        response.message = C.started(eid)
        self.get_logger().info(f'experiment {eid} started with {gains}')
        return response

    def _on_reset_fault(
        self, request: Trigger.Request, response: Trigger.Response
    ) -> Trigger.Response:
        if not self.runner.faulted:
            response.success, response.message = True, 'no fault'
            return response
        refused = reset_refusal(self._state, self.silent_since_trip())
        if refused is not None:
            response.success, response.message = False, refused
            return response
        reason = self.runner.fault_reason
        self._timeout_wall = None
        with self.loop_lock:
            self.runner.reset(float(self._state[2]))
        self._fault_logged = False
        response.success = True
        response.message = f'fault {reason} cleared; holding {self._state[2]:.4f} rad'
        self.get_logger().warn(response.message)
        return response

    @property
    def last_state(self) -> np.ndarray | None:
        """The newest drive state taken (``STATE_FIELDS``; None before the first)."""
        return self._state

    def silent_since_trip(self) -> float | None:
        """Seconds since the state watchdog tripped if no drive state came since (None:
        one came, or it did not trip): a fault reset waits for the drive."""
        if self._timeout_wall is not None and self._last_msg_wall <= self._timeout_wall:
            return time.monotonic() - self._timeout_wall
        return None

    def _wants_to_step(self) -> bool:
        """Answer states now? In lock-step 'pause', only while something runs."""
        if self.mode == 'realtime' or self.lockstep_idle == 'hold':
            return True
        # Paused in hold and in FAULT (zero current was commanded): sim time stands still
        # until the next start or reset, whatever the wall-clock gap.
        r = self.runner
        return r.running or not (r.ready or r.faulted)

    def take(self, timeout: float = 0.0) -> None:
        """Take the newest state, waiting up to ``timeout`` s if none is there."""
        self.offer(self.client.wait_state(timeout) if timeout > 0.0 else self.client.take_state())

    def offer(self, s: np.ndarray | None) -> None:
        """The newest drive state (``STATE_FIELDS``), from the subscription or -- composed
        in one loop with the drive -- handed over in memory; None: none came."""
        if s is not None:
            self._last_msg_wall = time.monotonic()
        if s is not None and int(s[0]) > self.client.answered:
            self._state = s
            self._pending = True
            self._last_state_wall = time.monotonic()
            if not self._initialised and math.isfinite(s[2]):
                self.runner.reset(float(s[2]))  # hold where the drive is
                self._initialised = True

    def _answer(self, r: ExperimentRunner, state: np.ndarray, words: np.ndarray) -> int:
        cmd, internals = self._cmd, self._internals.values
        return answer_state(r.R, r.Q, r.X, r.C, r.CF, state, r.cout, r.eout, cmd, internals, words)

    def answer(self) -> bool:
        """Answer the pending state if the loop should step (``kernel.answer_state``, the
        answer a compiled loop runs); True if a command went out."""
        if not (self._pending and self._wants_to_step()):
            return False
        self._words[W_ANSWERED] = self.client.answered
        status = self._answer(self.runner, self._state, self._words)
        self.runner.stepped(status)
        self.client.command(int(self._cmd[0]), self._cmd[1], self._cmd[2])
        self._pending = False
        if self._words[W_INTERNALS_DUE]:
            self.client.backpressure += publish_lossless(
                self.internals_pub, self._internals, self.context
            )
        if status >= STATUS_DONE:
            self._on_status(status)
        return True

    # -- the same answer in a composed loop (bench.compiled_loop) runs on these
    def answer_words(self) -> np.ndarray:
        """``kernel.answer_state``'s ``W`` words from this node (then
        :meth:`set_answer_words`)."""
        w = self._words.copy()
        w[W_ANSWERED] = self.client.answered
        return w

    def answer_views(self) -> dict[str, np.ndarray]:
        """The arrays a compiled answer runs on: the runner's (``R Q X C CF cout eout``),
        the command's and the internals' values, and their messages' bytes (``*_raw``)."""
        cmd, internals = self.client.command_wire, self._internals
        return {k: getattr(self.runner, k) for k in ('R', 'Q', 'X', 'C', 'CF', 'cout', 'eout')} | {
            'cmd': cmd.values,
            'internals': internals.values,
            'cmd_raw': cmd.raw,
            'internals_raw': internals.raw,
        }

    def state_seen(self) -> None:
        """A compiled loop answered states just now (the state watchdog's clock)."""
        self._last_msg_wall = self._last_state_wall = time.monotonic()

    def set_answer_words(self, W: np.ndarray) -> None:
        """Take back what a compiled loop answered (:meth:`answer_words`)."""
        self.client.answered = int(W[W_ANSWERED])
        self._words[:] = W
        self._pending = False
        self.state_seen()

    def compiled_event(self, status: int, R: np.ndarray) -> None:
        """An experiment's end in a compiled loop (``status`` >= STATUS_DONE, ``R`` the
        runner's words at that step): handled as :meth:`answer` does (serving thread)."""
        self.runner.stepped(status)
        self._on_status(status, R)

    def _on_status(self, status: int, R: np.ndarray | None = None) -> None:
        if status == STATUS_FAULT and self._fault_logged:
            return  # the kernel answers FAULT every period it stays there: said once
        res = self.runner.result(R) if status in (STATUS_DONE, STATUS_ABORTED) else None
        if self.deferred is not None:  # a composed loop: published and logged off the loop
            self.deferred.append((status, res))
        else:
            self._handle_status(status, res)

    def flush_deferred(self) -> None:
        """Publish and log the experiment ends the composed loop left (serving thread)."""
        while self.deferred:
            status, res = self.deferred.popleft()
            self._handle_status(status, res)

    def _handle_status(self, status: int, res: LossResult | None) -> None:
        if status in (STATUS_DONE, STATUS_ABORTED):
            self._publish_result(res)
        if status == STATUS_FAULT and not self._fault_logged:
            self._fault_logged = True
            self.get_logger().error(
                f'safety fault: {self.runner.fault_reason}; zero current until it is '
                f'cleared: `{self._reset_command}` ({self._reset_service})'
            )

    def _publish_result(self, res: LossResult | None = None) -> None:
        """Publish and log the last experiment's result (``res``: taken by the loop at its
        end; None: the runner's now)."""
        if res is None:
            res = self.runner.result()
        if res is None or (self.results and self.results[-1].experiment_id == res.experiment_id):
            return
        self.results.append(res)
        msg = result_to_msg(res, self.get_name())
        self.client.backpressure += publish_lossless(self.loss_pub, msg, self.context)
        text = (
            f'experiment {res.experiment_id}: loss {res.loss:.6g} terms '
            f'({res.terms[0]:.4g}, {res.terms[1]:.4g}, {res.terms[2]:.4g})'
        )
        if res.timing:
            text += (
                f' TIMING: {res.held} held and {res.late} late of {res.steps} periods '
                f'(tolerance {self.timing_tolerance}): not the paper timing, not a loss'
            )
        # Two call sites: rclpy refuses one call site logging at two severities.
        if res.aborted or res.timing:
            self.get_logger().warn(
                f'{text} ABORTED {res.reason} at step {res.trip_step}' if res.aborted else text
            )
        else:
            self.get_logger().info(text)

    def watchdog(self) -> None:
        """No state for ``state_timeout`` while one is expected: torque off, abort, FAULT."""
        if self._state is None or not self._wants_to_step() or self.runner.faulted:
            return
        if time.monotonic() - self._last_state_wall <= self.state_timeout:
            return
        running = self.runner.running
        t_ns = int(self._state[1])
        self.runner.abort_external(REASON_DRIVE_TIMEOUT, t_ns)
        self._timeout_wall = time.monotonic()
        self.client.command(-1, 0.0, 0.0)  # zero current for whatever step comes next
        self.get_logger().error(
            f'no drive state for {self.state_timeout:g} s: zero current commanded'
            + (f', experiment {self.runner.experiment_id} aborted' if running else '')
            + f'; FAULT until `{self._reset_command}` ({self._reset_service})'
        )
        self._fault_logged = True
        if running:
            self._publish_result()

    def _on_heartbeat(self, msg: Header) -> None:
        if msg.stamp.sec == 0 and msg.stamp.nanosec == 0:
            # the client's goodbye (contract.HEARTBEAT_TOPIC): zero current now, not
            # tuner_timeout later (nobody watches a drive left holding its position),
            # said as the normal end it is unless an experiment was running; ignored
            # unarmed or tripped (the copies of one goodbye, a late one)
            if self._heartbeat_wall is not None and not self._tuner_tripped:
                self.heartbeat_from = msg.frame_id or 'a client'
                self.tuner_watchdog(goodbye=True)
            return
        if self._heartbeat_wall is None:
            self.get_logger().info(
                f'tuner watchdog armed: {msg.frame_id or "a client"} sends heartbeats; '
                f'none for {self.tuner_timeout:g} s -> zero current (tuner_lost)'
            )
        elif self._tuner_tripped:
            self.get_logger().warn(
                f'{msg.frame_id or "a client"} is back after '
                f'{time.monotonic() - self._heartbeat_wall:.1f} s; FAULT (tuner_lost) '
                f'stays until it is cleared: `{self._reset_command}`'
            )
        self._heartbeat_wall = time.monotonic()
        self.heartbeat_from = msg.frame_id
        self._tuner_tripped = False

    def tuner_watchdog(self, goodbye: bool = False) -> None:
        """No heartbeat for ``tuner_timeout`` s, or the tuner's ``goodbye``: FAULT (zero
        current, no load), a running experiment aborted with ``tuner_lost``."""
        last = self._heartbeat_wall
        if self.tuner_timeout <= 0 or last is None or self._tuner_tripped:
            return
        silent = time.monotonic() - last
        if silent <= self.tuner_timeout and not goodbye:
            return
        self._tuner_tripped = True
        self.tuner_trips += 1
        who = self.heartbeat_from or 'the tuner'
        running = self.runner.running
        why = f'no heartbeat from {who} for {silent:.2f} s (tuner_timeout {self.tuner_timeout:g} s)'
        why = f'{who} ended its run (its goodbye)' if goodbye else why
        # one call per severity: rclpy fixes a call's severity at its first use
        log, quiet = self.get_logger(), goodbye and not running
        say = lambda text: log.info(text) if quiet else log.error(text)  # noqa: E731
        if self.runner.faulted:
            say(f'{why}; already in FAULT ({self.runner.fault_reason}): zero current')
            return
        t_ns = int(self._state[1]) if self._state is not None else 0
        with self.loop_lock:
            self.runner.abort_external(REASON_TUNER_LOST, t_ns)
        self._fault_logged = True
        say(
            f'{why}: zero current'
            + (f', experiment {self.runner.experiment_id} aborted' if running else '')
            + f'; FAULT (tuner_lost) until `{self._reset_command}` ({self._reset_service})'
            + (', which the next tuner calls itself' if goodbye and not running else '')
        )
        if running:
            self._publish_result()

    def run(self, executor) -> None:
        """The standalone loop: wait for states, answer them, serve services between."""
        since_service = 0
        while not self.stop_requested and rclpy.ok(context=self.context):
            stepping = self._wants_to_step()
            # Expecting states: wait on them; idle (paused): wait on services instead.
            if stepping:
                if not self._pending:
                    self.take(min(self.state_timeout, 0.05))
                if self.answer():
                    since_service += 1
                    if since_service < self.service_period_steps:
                        continue
                else:
                    self.watchdog()
            else:
                executor.spin_once(timeout_sec=0.01)
                self.take()
                self.tuner_watchdog()
                continue
            since_service = 0
            executor.spin_once(timeout_sec=0.0)
            self.tuner_watchdog()

    def flushed_publishers(self) -> tuple[Any, ...]:
        """Every result and command."""
        return (self.loss_pub, self.internals_pub, self.client.command_pub)


def main(args: list[str] | None = None) -> int:
    argv = sys.argv if args is None else args

    def body() -> int:
        cli = parse_cli(parser(), argv)
        overrides = start_overrides(
            (('mode', cli.mode), ('drive_config_file', cli.drive_config and str(cli.drive_config)))
        )
        return run_stepped_node(
            argv,
            lambda: ControllerNode(parameter_overrides=overrides),
            (ControllerError, ControllerConfigError),
            'controller',
            on_exit=lambda node: node.get_logger().info(
                f'stopped after {len(node.results)} experiments; refused requests: '
                + ', '.join(f'{k} {v}' for k, v in node.refused.items())
            ),
        )

    return run_cli('controller', body)


if __name__ == '__main__':
    sys.exit(main())
