"""ROS plumbing both drive nodes share (``drive_sim``, ``example_drive``): their base
class :class:`DriveNode` (topics, commands taken, watchdog, status), the loops that step
them (:func:`run_lockstep`, :func:`run_realtime`; what a step or a period does is the
node's) and their ``main()`` body (:func:`run_drive_node`).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from typing import Any, ClassVar

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from . import contract, rt
from .cdr import Float64ArrayWire, JointStateWire
from .hardware_abi import HardwareFault
from .pacing import CommandSource, Pacer
from .params import ConfigError
from .qos import LOCKSTEP_QOS, RECORDED_QOS
from .rt import RtOptions
from .runtime import IoNodeOwner, LenientDoubles, publish_lossless, run_stepped_node

#: the state's fields drive/joint_states repeats
_THETA, _OMEGA, _TORQUE = (contract.STATE_INDEX[n] for n in ('theta_meas', 'omega_meas', 'torque'))


class DriveNode(IoNodeOwner, LenientDoubles, Node):
    """The base of a drive node (``drive_sim``, ``example_drive``): :meth:`open_topics`
    makes its topics. Every drive topic is recorded, so every publisher is reliable
    KEEP_ALL (``qos.RECORDED_QOS``): a recorder that stalls (a loaded real-time machine)
    back-pressures, it never loses a sample. The 5 kHz command path lives on a hidden node
    no executor spins. A subclass has ``counters`` (``contract.STATUS_COUNTERS``),
    ``held`` (``command_latch.HeldCommand``), ``latch`` (``command_latch.CommandLatch``),
    ``cmd_watchdog`` (``pacing.CommandWatchdog``), ``safe_stopped``, ``step_index`` (the
    latest published state's), ``ts_ns``, ``period_s``, ``spin_margin``, ``wall_clock`` and the
    methods ``start``, ``step``, ``skip``, ``publish_state``, ``publish_status``,
    ``close_hardware``."""

    #: the layouts a drive node reports as read-only parameters
    #: (``runtime.parameter_hygiene``'s facts: an override may not advertise another one)
    LAYOUTS: ClassVar[dict[str, list[str]]] = {
        'state_fields': list(contract.STATE_FIELDS),
        'command_fields': list(contract.COMMAND_FIELDS),
    }

    counters: Any
    #: the loop's real-time scheduling (``--thread-priority`` ...; :mod:`.rt`), applied by
    #: ``run`` on the thread that runs the loop; ``rt_report`` says the result
    rt_options: RtOptions = RtOptions()
    rt_report: dict | None = None
    #: set by SIGINT/SIGTERM: the loop stops at the next period boundary, so the context
    #: is never shut down under a publish
    stop_requested = False
    mode = 'realtime'  #: the loop :meth:`run` runs (the simulator also has 'lockstep')
    max_steps = 0  #: stop after this many steps (0: never)
    service_period_steps = 250  #: serve parameter requests every N steps (50 ms)
    #: real time: start the clock once a publisher on drive/command is matched
    realtime_wait_for_controller = False

    def open_topics(self, node_name: str) -> None:
        """``state_pub``, ``joint_pub`` (:meth:`make_joint_publisher`), ``status_pub``, their
        messages ``wire`` and ``joint``, and
        the command input: ``cmd_sub`` on ``io_node`` (``_<name>_io``: hidden, in this
        node's namespace and context, never spun), taken through a hand-rolled WaitSet
        (:meth:`wait_command`); ``commands`` (``pacing.CommandSource``) takes from it, or
        from a composed controller that hands its commands over in memory."""
        self.state_pub = self.create_publisher(
            Float64MultiArray, contract.STATE_TOPIC, RECORDED_QOS
        )
        self.joint_pub = self.make_joint_publisher()
        self.status_pub = self.create_publisher(
            DiagnosticArray, contract.STATUS_TOPIC, RECORDED_QOS
        )
        ns = self.get_namespace()
        self.io_node = Node(f'_{node_name}_io', context=self.context, namespace=ns)
        self.cmd_sub = self.io_node.create_subscription(
            Float64MultiArray, contract.COMMAND_TOPIC, lambda _m: None, LOCKSTEP_QOS
        )
        self.commands = CommandSource(self.cmd_sub, len(contract.COMMAND_FIELDS))
        self._cmd_waitset = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, self.context.handle)
        # drive/state and drive/joint_states pre-serialised, patched in place: nothing is
        # built per step (cdr.py)
        self.wire = Float64ArrayWire(len(contract.STATE_FIELDS))
        self.joint = JointStateWire('motor')

    def wait_command(self, timeout_s: float) -> bool:
        """Sleep up to ``timeout_s`` [s] in rcl_wait; True when a command is pending."""
        ws = self._cmd_waitset
        ws.clear_entities()  # rcl_wait nulls entries that were not ready: re-add every time
        ws.add_subscription(self.cmd_sub.handle)
        ws.wait(int(timeout_s * contract.NS_PER_S))
        return ws.is_ready('subscription', 0)

    def make_joint_publisher(self) -> Any:
        """``drive/joint_states``' publisher (a hook: a test drive may publish none)."""
        return self.create_publisher(JointState, contract.JOINT_STATE_TOPIC, RECORDED_QOS)

    def publish_joint_state(self) -> None:
        """drive/joint_states: the latest state's theta_meas, omega_meas, torque, stamped
        k Ts (``ts_ns``)."""
        j, v = self.joint, self.wire.values
        j.sec[0], j.nanosec[0] = divmod(self.step_index * self.ts_ns, contract.NS_PER_S)
        j.position[0], j.velocity[0], j.effort[0] = v[_THETA], v[_OMEGA], v[_TORQUE]
        self.counters.backpressure += publish_lossless(self.joint_pub, j, self.context)

    def period_views(self) -> dict[str, Any]:
        """The preallocated messages a compiled period writes: ``state`` and the
        joint_states fields, and each message's bytes (``*_raw``) for the loop's outbox."""
        j = self.joint
        return {
            'state': self.wire.values,
            'joint_sec': j.sec,
            'joint_nsec': j.nanosec,
            'joint_pos': j.position,
            'joint_vel': j.velocity,
            'joint_eff': j.effort,
            'state_raw': self.wire.raw,
            'joint_raw': j.raw,
        }

    def read_command(self, data: Any) -> tuple[int, float, float] | None:
        """``drive/command``'s values ``data`` (``COMMAND_FIELDS``) as (answers_step,
        isq_ref [A], load torque [N m]), counted; None for a message of another length or
        with a value not finite, which the drive ignores (said on the log, at most once a
        second)."""
        n = len(contract.COMMAND_FIELDS)
        # (each value by index: no generator made per command on the drive's Python path)
        if len(data) != n or not (
            math.isfinite(data[contract.CMD_STEP])
            and math.isfinite(data[contract.CMD_ISQ])
            and math.isfinite(data[contract.CMD_LOAD])
        ):
            self.get_logger().error(
                f'{contract.COMMAND_TOPIC}: expected {n} finite values '
                f'{contract.COMMAND_FIELDS}, got {len(data)} values or a value not finite; ignored',
                throttle_duration_sec=1.0,
            )
            return None
        self.counters.commands += 1
        return (
            int(data[contract.CMD_STEP]),
            float(data[contract.CMD_ISQ]),
            float(data[contract.CMD_LOAD]),
        )

    def next_command(self) -> tuple[int, float, float] | None:
        """The next valid pending command (:meth:`read_command`), None when none is: from
        the subscription (our compact layout read in place), or the composed controller's."""
        while (data := self.commands.next()) is not None:
            command = self.read_command(data)
            if command is not None:
                return command
        return None

    def latest_state(self) -> Any:
        """The state last published (``STATE_FIELDS``; the array is reused each period)."""
        return self.wire.values

    def period(self, missed: int = 0) -> None:
        """One real-time period at its start (docs/interfaces.md, "Real time"): take the
        commands, the watchdog, the latch (``command_latch``), then :meth:`step` -- apply
        the held command (zero after a safe stop), sample, publish state k+1 labelled with
        the acting command's step -- counted fresh or held.

        ``missed`` (a drive that cannot pause, ``wall_clock``; ``pacing.Pacer``): whole
        periods that went by before this one without a period of the loop; :meth:`skip`
        runs them with the command held, unpublished, and they count held and missed (and
        in steps: fresh + held = steps)."""
        c, held = self.counters, self.held
        if missed > 0 and self.wall_clock:
            self.skip(missed)
            held.fresh = False
            c.steps += missed
            c.held += missed
            c.missed += missed
        self.take_commands()
        self.watchdog()
        if self.safe_stopped:  # zero current and no load, labelled as no command
            held.zero()
            held.fresh = False
        acting, fresh = self.latch.latch(held.applied, held.fresh)
        c.fresh += fresh
        c.held += not fresh
        held.fresh = False  # it answered the state before this step
        self.step(held.isq_ref, held.load, acting)

    def take_commands(self) -> None:
        """Take every pending command; the newest becomes the held command
        (docs/interfaces.md, "Real time"): fresh when it answers the latest state or is
        untagged (-1), late when it answers an older one (still held); one answering the
        same or an older state than the held one (a duplicate, out of order) is ignored,
        counted ``stale_ignored`` -- holding it would step back in time. Every valid
        command feeds the watchdog. ``period_kernel.take_command`` is its compiled copy."""
        k = self.step_index
        held = self.held
        while (command := self.next_command()) is not None:
            answers, isq, load = command
            self.cmd_watchdog.command()  # the controller is alive either way
            if self.cmd_watchdog.resume():
                self.get_logger().info(f'watchdog: commands resumed at step {k}')
            if 0 <= answers <= held.answers:
                self.counters.stale_ignored += 1
                continue
            held.isq_ref, held.load = isq, load
            held.applied = max(answers, -1)
            if answers >= 0:
                held.answers = answers
            held.fresh = not 0 <= answers < k
            self.counters.late += not held.fresh

    def watchdog(self) -> None:
        """Once a period, after the commands were taken: no command for ``command_timeout``
        (``pacing.CommandWatchdog`` says when) -> zero current and no load until the next
        command (:meth:`drop_latched` too), counted ``watchdog_steps``; the first period
        of a trip counts ``watchdog_trips`` and says so on the log."""
        w = self.cmd_watchdog
        if not w.expired():
            return
        if w.trip():
            self.counters.watchdog_trips += 1
            self.get_logger().warn(
                f'watchdog: no command on {contract.COMMAND_TOPIC} for {w.timeout_s:g} s at step '
                f'{self.step_index}: zero current and no load until the next command'
            )
        self.counters.watchdog_steps += 1
        self.held.zero()
        self.drop_latched()

    def drop_latched(self) -> None:
        """Zero at once, the latched command too (a hook: a power stage's latch cannot be
        recalled, its zero acts from the next period; the simulator's can)."""

    def run(self, executor: Any) -> None:
        """The node's loop (:func:`run_lockstep` or :func:`run_realtime`, by ``mode``) with
        its real-time scheduling (``rt_options``) applied to the calling thread."""
        log = self.get_logger()
        with rt.for_the_loop(self.rt_options, log.info, log.warn) as self.rt_report:
            (run_lockstep if self.mode == 'lockstep' else run_realtime)(self, executor)

    def send_status(self, status: DiagnosticStatus, values: dict[str, str]) -> None:
        """Publish ``status`` (name, hardware id, level and message set) with ``values``
        as its key/values, stamped now, on ``drive/status`` without loss (the
        back-pressure retries counted)."""
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.counters.backpressure += publish_lossless(self.status_pub, msg, self.context)


def serve(drive: Any, executor: Any, t_start: float, next_status: float) -> float:
    """Between steps: serve pending parameter requests; publish the status once a second.

    Returns the wall time of the next status publication.
    """
    executor.spin_once(timeout_sec=0.0)
    now = time.perf_counter()
    if now >= next_status:
        drive.publish_status(now - t_start)
        return now + 1.0
    return next_status


def run_lockstep(drive: Any, executor: Any) -> None:
    """One step per command answering the current state; see docs/interfaces.md."""
    c = drive.counters
    drive.start()
    since_service = 0
    t_wall0 = last_step = time.perf_counter()
    next_status = t_wall0 + 1.0
    while not drive.stop_requested and rclpy.ok(context=drive.context):
        if drive.max_steps and c.steps >= drive.max_steps:
            break
        wait_s = max(0.0, last_step + drive.republish_period - time.perf_counter())
        if drive.lockstep_poll(int(wait_s * contract.NS_PER_S)):
            last_step = time.perf_counter()
        elif time.perf_counter() - last_step >= drive.republish_period:
            # Idle: serve parameters (and the status: an idle drive still reports),
            # then re-send the state for a late-starting peer.
            next_status = serve(drive, executor, t_wall0, next_status)
            drive.publish_state()
            c.republished += 1
            last_step = time.perf_counter()
            continue
        else:
            continue
        since_service += 1
        if since_service >= drive.service_period_steps:
            since_service = 0
            next_status = serve(drive, executor, t_wall0, next_status)
    drive.publish_status(time.perf_counter() - t_wall0)


def run_realtime(drive: Any, executor: Any) -> None:
    """Period n starts at t0 + n ``period_s`` on the wall clock (``pacing.Pacer``: it sleeps
    in the command wait, taking commands as they come, and busy-waits the last
    ``spin_margin``), then ``drive.period(missed)``: take the commands, the watchdog,
    apply, sample, publish. A start more than a period late is an overrun: a drive that
    cannot pause (``wall_clock``) held its command over the periods it skipped, else the
    schedule is re-anchored. However the loop ends the drive writes zero first
    (``close_hardware``); a ``HardwareFault`` ends the process, one line and exit 1."""
    c = drive.counters
    if drive.realtime_wait_for_controller:
        # A drive with no controller would only hold zero current: the clock starts
        # when one is matched, so it never misses the first periods.
        drive.get_logger().info('real time: waiting for a controller on drive/command')
        while (
            not drive.stop_requested
            and rclpy.ok(context=drive.context)
            and drive.cmd_sub.get_publisher_count() == 0
        ):
            executor.spin_once(timeout_sec=0.01)
    try:
        drive.start()
        pacer = Pacer(drive.period_s, drive.spin_margin, wall_clock=drive.wall_clock)
        t_start = pacer.t0  # (the pacer's own re-anchors on an overrun)
        next_status = t_start + 1.0
        since_service = 0
        while not drive.stop_requested and rclpy.ok(context=drive.context):
            if drive.max_steps and c.steps >= drive.max_steps:
                break
            pacer.wait(drive.wait_command, drive.take_commands)
            c.overruns, c.max_lateness_us = pacer.overruns, pacer.max_lateness_us
            drive.period(pacer.missed)
            since_service += 1
            if since_service >= drive.service_period_steps:
                since_service = 0
                next_status = serve(drive, executor, t_start, next_status)
    except HardwareFault as exc:  # the power stage's negative return: one line, exit 1
        drive.close_hardware()
        drive.get_logger().error(f'{exc}: zero current written, the drive stopped')
        print(f'error: {drive.get_name()}: {exc}; zero current written', file=sys.stderr)
        raise SystemExit(1) from None
    finally:
        drive.close_hardware()  # however the loop ends (a signal, an exception): zero first
    drive.publish_status(time.perf_counter() - t_start)


def run_drive_node(
    argv: list[str],
    make: Callable[[], Any],
    prog: str,
    rt_options: RtOptions | None = None,
) -> int:
    """Run the drive node ``make()`` builds until it stops (``runtime.run_stepped_node``):
    a bad parameter file is one line and exit code 2; the node's ``log_summary()`` runs
    at exit. ``rt_options`` (the loop's real-time scheduling, ``rt.RtOptions.from_cli``)
    become the node's ``rt_options``, applied by its ``run``."""

    def made() -> Any:
        node = make()
        if rt_options is not None:
            node.rt_options = rt_options
        return node

    return run_stepped_node(
        argv,
        made,
        (ConfigError,),
        prog,
        on_exit=lambda node: node.log_summary(),
    )
