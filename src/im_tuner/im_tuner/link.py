"""The tuner's link to a controller node: a :class:`im_tuner.tuning.Measurer` over ROS.

Standard interfaces only (docs/interfaces.md, docs/controller.md):

* gains: ``<controller>/set_parameters_atomically`` (rcl_interfaces) -- all five or none;
* experiment: ``<controller>/start_experiment`` (std_srvs/Trigger), whose answer names
  the experiment id (``"experiment 12 started"``);
* result: ``<namespace>/controller/loss`` (diagnostic_msgs/DiagnosticArray, one status,
  ``im_controller.messages``), matched by experiment id; the gains it echoes must equal
  the gains set (else someone else changed them: the run stops);
* a heartbeat: ``<controller>/heartbeat`` (std_msgs/Header, every 0.1 s from a thread of
  its own, :class:`Heartbeat`), for a controller whose tuner watchdog is on (a drive
  host's, ``tuner_timeout``): the tuner's silence brings its drive to zero current. A
  result aborted ``tuner_lost`` (the link was down, not the drive) is a lost evaluation:
  re-run, never told to the optimiser; a start refused ``[tuner_lost]`` is reset at
  once, whatever the fault policy (the drive is fine);
* safety faults: ``<controller>/reset_fault`` (std_srvs/Trigger), called only with
  ``fault_policy='reset'`` (the default on the simulated bench); with ``'stop'`` the run
  ends and the message names ``ros2 run im_controller reset_fault`` for the person at the
  bench. A fault met at a start that no result reported is counted in ``faults_outside``.

Every wait spins through the given ``spin_until(predicate, timeout)`` -- the in-process
bench's (which steps the simulation) or a plain executor's -- and gives up on a deadline.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from im_controller import contract as C
from im_controller.config import GAIN_NAMES, Gains
from im_controller.layout import LINK_REASONS
from im_controller.messages import SAFETY_REASONS, msg_to_result
from im_controller.reset_fault import reset_command
from im_controller.result import LossResult

from .names import FAULT_POLICIES, controller_topics
from .tuning import BenchFailure, LostEvaluation, Measurement, StopRequested

RETRY_PERIOD = 0.02  # [s] between retries of a refused call
SUPERVISE_PERIOD = 0.2  # [s] between checks of the bench processes


class Heartbeat:
    """The tuner's heartbeat to a controller (``contract.HEARTBEAT_TOPIC``): a thread of
    its own publishes every ``contract.HEARTBEAT_PERIOD`` s, best effort, so a tuner busy
    in its optimiser still beats; only a tuner that is gone (or cut off) falls silent."""

    def __init__(self, node: Node, topic: str, period: float = C.HEARTBEAT_PERIOD) -> None:
        self.node = node
        self.period = float(period)
        self.pub = node.create_publisher(
            Header, topic, QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
        )
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='tuner-heartbeat', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        msg = Header(frame_id=self.node.get_fully_qualified_name())
        while not self._stop.is_set():
            ns = time.time_ns()
            msg.stamp.sec, msg.stamp.nanosec = divmod(ns, 1_000_000_000)
            try:
                self.pub.publish(msg)
                self.sent += 1
            except Exception:  # the context is shutting down: stop beating
                return
            self._stop.wait(self.period)

    def stop(self, goodbye: bool = True) -> None:
        """No more heartbeats (before the node is destroyed); ``goodbye``: say so
        (``contract.HEARTBEAT_TOPIC``: a heartbeat stamped zero), so that a drive host
        goes to zero current now and logs the normal end, not this tuner lost. Best
        effort: a goodbye that is lost ends in the watchdog's trip."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        if goodbye:
            bye = Header(frame_id=self.node.get_fully_qualified_name())
            for _ in range(C.HEARTBEAT_GOODBYES):
                try:
                    self.pub.publish(bye)
                except Exception:  # the context is shutting down: nothing to say it on
                    return


class ControllerLink:
    """Set gains, run experiments and collect their losses on one controller node."""

    def __init__(
        self,
        node: Node,
        spin_until: Callable[[Callable[[], bool], float], bool],
        *,
        controller: str = '/controller',
        eval_timeout: float = 60.0,
        call_timeout: float = 10.0,
        fault_policy: str = 'reset',
        should_stop: Callable[[], bool] = lambda: False,
        supervise: Callable[[], None] | None = None,
        owns_controller: bool = False,
    ) -> None:
        """``owns_controller``: the tuner started the controller (a bench of its own), so
        it ends with the tuner and a resumed run starts a fresh one: the fault advice
        says to resume, not to call ``reset_fault`` on a controller that is gone."""
        if fault_policy not in FAULT_POLICIES:
            raise ValueError(f'fault_policy must be one of {FAULT_POLICIES}, got {fault_policy!r}')
        self.node = node
        self.names = controller_topics(controller)
        self._spin = spin_until
        self.eval_timeout = float(eval_timeout)
        self.call_timeout = float(call_timeout)
        self.fault_policy = fault_policy
        self.owns_controller = owns_controller
        self.should_stop = should_stop
        #: called between spins (at most every SUPERVISE_PERIOD s): may raise BenchFailure
        #: (a bench process died) -- so a dead bench ends a wait at once
        self.supervise = supervise
        self._next_supervise = 0.0
        self.params = AsyncParameterClient(node, self.names['node'])
        self.start_cli = node.create_client(Trigger, self.names['start'])
        self.reset_cli = node.create_client(Trigger, self.names['reset'])
        self.results: dict[int, Any] = {}
        self.bad_messages = 0
        #: messages received on the loss topic, malformed ones too (the recorder child's
        #: bag must hold as many: bench.forms.Children.close_recording)
        self.loss_messages = 0
        self.faults_reset = 0
        self.links_reset = 0  #: tuner_lost faults cleared (the link's, not the drive's)
        #: safety faults met at a start that no result of this session reported (a drive
        #: state watchdog between experiments, a fault left from before the session):
        #: the records cannot count them, the summary must (docs/tuner.md)
        self.faults_outside: list[str] = []
        #: the last result was a safety fault that is not cleared yet (the next start
        #: meets it: not another fault)
        self._result_fault = False
        #: the last result that ended in a safety fault (its periods' timing is told)
        self._fault_result: LossResult | None = None
        qos = QoSProfile(
            depth=1000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE
        )
        self.loss_sub = node.create_subscription(
            DiagnosticArray, self.names['loss'], self._on_loss, qos
        )

    # -- plumbing ----------------------------------------------------------------------------
    def _on_loss(self, msg: DiagnosticArray) -> None:
        self.loss_messages += 1
        try:
            r = msg_to_result(msg)
        except ValueError as exc:
            self.bad_messages += 1
            self.node.get_logger().warn(f'ignored a malformed loss message: {exc}')
            return
        self.results[r.experiment_id] = r

    def _check(self) -> bool:
        if self.supervise is not None and time.monotonic() >= self._next_supervise:
            self._next_supervise = time.monotonic() + SUPERVISE_PERIOD
            self.supervise()
        return self.should_stop()

    def _wait(self, pred: Callable[[], bool], timeout: float) -> bool:
        ok = self._spin(lambda: pred() or self._check(), timeout)
        if self.should_stop():
            raise StopRequested()
        return ok and pred()

    def _call(self, fut, what: str):
        if not self._wait(fut.done, self.call_timeout):
            raise LostEvaluation(f'{what}: no answer within {self.call_timeout:g} s')
        return fut.result()

    def reachable(self) -> bool:
        """Services ready and the loss topic published (no waiting)."""
        return (
            self.start_cli.service_is_ready()
            and self.reset_cli.service_is_ready()
            and self.params.services_are_ready()
            and self.node.count_publishers(self.names['loss']) > 0
        )

    def wait_ready(self, timeout: float) -> bool:
        return self._wait(self.reachable, timeout)

    # -- parameters --------------------------------------------------------------------------
    def _call_again(self, make: Callable[[], Any], what: str, tries: int = 3) -> Any:
        """An idempotent call (a read), asked again when no answer came: a service's
        response can be lost while its reply path is still being matched (a client new
        to the graph, a loaded machine), and asking again costs nothing."""
        for _ in range(tries - 1):
            with contextlib.suppress(LostEvaluation):
                return self._call(make(), what)
        return self._call(make(), what)

    def get_parameters(self, names: list[str]) -> dict[str, Any]:
        resp = self._call_again(lambda: self.params.get_parameters(names), 'get_parameters')
        return {n: parameter_value_to_python(v) for n, v in zip(names, resp.values, strict=True)}

    def list_parameters(self) -> dict[str, Any]:
        """Every parameter of the controller with its value (for the run file)."""
        resp = self._call_again(self.params.list_parameters, 'list_parameters')
        names = list(resp.result.names)
        if not names:
            return {}
        return self.get_parameters(sorted(names))

    def set_gains(self, gains: Gains, deadline: float) -> None:
        """All five gains in one atomic call; transient refusals are retried until
        ``deadline`` (monotonic s), anything else stops the run."""
        params = [
            Parameter(n, Parameter.Type.DOUBLE, float(v))
            for n, v in zip(GAIN_NAMES, gains.as_tuple(), strict=True)
        ]
        self._set_between_experiments(params, f'the gains {gains}', deadline)

    def set_timing_tolerance(self, periods: int, deadline: float) -> None:
        """The controller's ``timing_tolerance`` [held + late periods per experiment],
        which judges its next experiments; as :meth:`set_gains`."""
        params = [Parameter('timing_tolerance', Parameter.Type.INTEGER, int(periods))]
        self._set_between_experiments(params, f'timing_tolerance {periods}', deadline)

    def _set_between_experiments(self, params: list[Parameter], what: str, deadline: float) -> None:
        while True:
            res = self._call(
                self.params.set_parameters_atomically(params), 'set_parameters_atomically'
            ).result
            if res.successful:
                return
            if C.refusal_code(res.reason) not in (C.BUSY, C.FINISHING_MOVE):
                raise BenchFailure(f'the controller refused {what}: {res.reason}')
            if time.monotonic() > deadline:
                raise LostEvaluation(f'{what} refused until the timeout: {res.reason}')
            self._wait(lambda: False, RETRY_PERIOD)

    # -- experiments -------------------------------------------------------------------------
    def reset_fault(self) -> str:
        """Clear the controller's fault. A refusal that clears by itself (``no_drive_state``:
        the drive was silent, as a loaded machine can stall a process for seconds) is
        asked again for up to ``call_timeout`` s; any other, or one that outlasts it, stops
        the run (BenchFailure)."""
        deadline = time.monotonic() + self.call_timeout
        while True:
            resp = self._call(self.reset_cli.call_async(Trigger.Request()), 'reset_fault')
            if resp.success:
                break
            if C.refusal_code(resp.message) not in C.TRANSIENT or time.monotonic() > deadline:
                raise BenchFailure(f'reset_fault refused: {resp.message}')
            self._wait(lambda: False, 10 * RETRY_PERIOD)
        self.faults_reset += 1
        self._result_fault = False
        return resp.message

    def _start(self, deadline: float) -> int:
        while True:
            resp = self._call(self.start_cli.call_async(Trigger.Request()), 'start_experiment')
            if resp.success:
                eid = C.started_id(resp.message)
                if eid is None:
                    raise BenchFailure(
                        f'start_experiment answered {resp.message!r}: no experiment id in it'
                    )
                return eid
            msg = resp.message
            code = C.refusal_code(msg)
            if code == C.TUNER_LOST:
                # the drive host lost this tuner's heartbeat (a network outage, a tuner
                # that was killed): the link's fault, not the drive's -- clear it and go on
                self.node.get_logger().warn(f'{msg.split(";")[0]}; resetting it')
                self.reset_fault()
                self.links_reset += 1
                continue
            if code == C.SAFETY_FAULT:
                if not self._result_fault:
                    self.faults_outside.append(msg)
                    self._result_fault = True  # (counted once, however often it is met)
                if self.fault_policy != 'reset':
                    # (the controller's own words up to its advice: 'safety fault (why)')
                    what = msg.split(';')[0].split(' [')[0].strip().removeprefix('refused: ')
                    raise BenchFailure(f'start_experiment refused: {what}; {self.fault_advice()}')
                self.node.get_logger().warn(f'{msg}; resetting it (fault policy: reset)')
                self.reset_fault()
                continue
            if code not in C.TRANSIENT:
                raise BenchFailure(f'start_experiment refused: {msg}')
            if time.monotonic() > deadline:
                raise LostEvaluation(f'start_experiment refused until the timeout: {msg}')
            self._wait(lambda: False, RETRY_PERIOD)

    def fault_advice(self) -> str:
        """What the person at the bench does about a safety fault under the policy
        'stop' -- a command that works on this bench -- and, when the experiment that
        faulted was off the paper's timing, that the host may have caused it (a drive
        that cannot pause held its old current through the host's stalls, which can trip
        the limits on gains that run fine on time)."""
        if self.owns_controller:
            # the controller ran in (or beside) this tuner and ends with it: nothing is
            # left to reset; a resumed run starts a fresh controller, fault-free
            advice = (
                'fault policy stop: check the drive, then resume the run (--resume: the '
                "tuner's controller ended with it, and the resumed run's starts without "
                'the fault)'
            )
        else:
            advice = (
                f'fault policy stop: check the drive, clear the fault with '
                f'`{reset_command(self.names["node"])}`, then resume the run (--resume)'
            )
        r = self._fault_result
        if r is not None and r.timing:
            advice += (
                f' (experiment {r.experiment_id} faulted with {r.held} of its {r.steps} '
                f'periods held and {r.late} late, beyond the timing tolerance: the drive held '
                "its old current through the host's stalls, which may be what tripped it -- "
                'check the host: `ros2 run im_drive_sim host_check`)'
            )
        return advice

    def measure(self, gains: Gains) -> Measurement:
        """Set ``gains``, run one experiment, return its result (see module doc)."""
        t0 = time.perf_counter()
        deadline = time.monotonic() + self.eval_timeout
        if not self.reachable() and not self.wait_ready(min(self.call_timeout, self.eval_timeout)):
            # a call to a vanished server would only time out: say what is wrong
            raise LostEvaluation(
                f'the controller {self.names["node"]} is not reachable (its '
                'services or loss topic are gone: did it stop?)'
            )
        self.set_gains(gains, deadline)
        eid = self._start(deadline)
        if not self._wait(lambda: eid in self.results, max(deadline - time.monotonic(), 0.0)):
            raise LostEvaluation(
                f'no loss for experiment {eid} within {self.eval_timeout:g} s', experiment_id=eid
            )
        r = self.results.pop(eid)
        if r.reason in LINK_REASONS:
            # the link was down (the host's tuner watchdog), not the drive: not a loss
            raise LostEvaluation(
                f'experiment {eid} aborted by the drive host: {r.reason} (no heartbeat '
                'from this tuner within its tuner_timeout: a network outage?)',
                experiment_id=eid,
            )
        ran = r.gains.as_tuple()
        if ran != gains.as_tuple():
            raise BenchFailure(
                f'experiment {eid} ran with gains {ran}, not the ones set '
                f'{gains.as_tuple()}: something else changed them'
            )
        fault = r.reason in SAFETY_REASONS
        self._result_fault = fault
        if fault:
            self._fault_result = r
        if fault and self.fault_policy == 'reset':
            self.node.get_logger().warn(
                f'experiment {eid}: safety fault {r.reason}; resetting it (fault policy: reset)'
            )
            try:
                self.reset_fault()
            except (BenchFailure, LostEvaluation) as exc:
                # keep this result; the next start meets the fault and tries once more
                self.node.get_logger().error(f'experiment {eid}: {exc}')
        return Measurement.of(r, time.perf_counter() - t0)

    def apply(self, gains: Gains) -> None:
        """Leave ``gains`` applied on the controller (the run's final controller); also
        after a stop request (SIGINT): each wait is bounded by the call timeout anyway."""
        should_stop, self.should_stop = self.should_stop, lambda: False
        try:
            if not self.reachable() and not self.wait_ready(
                min(self.call_timeout, self.eval_timeout)
            ):
                raise LostEvaluation(f'the controller {self.names["node"]} is not reachable')
            self.set_gains(gains, time.monotonic() + self.eval_timeout)
        finally:
            self.should_stop = should_stop
