"""ROS plumbing both drive nodes share (``drive_sim`` and ``example_drive``).

* :class:`DriveNode`: the base of a drive node -- its topics (``drive/state``,
  ``drive/joint_states``, ``drive/status``, the 5 kHz command path that never goes
  through an executor), its layout parameters, a command checked and read, the
  watchdog's period, the status message.
* :func:`run_drive_node`: a drive node's ``main()`` body (``runtime.run_stepped_node``
  with the counters' summary logged at exit).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, ClassVar

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from .contract import (
    CMD_ISQ,
    CMD_LOAD,
    CMD_STEP,
    COMMAND_FIELDS,
    COMMAND_TOPIC,
    JOINT_STATE_TOPIC,
    NS_PER_S,
    STATE_FIELDS,
    STATE_TOPIC,
    STATUS_TOPIC,
)
from .pacing import CommandSource, CommandWatchdog
from .params import ConfigError
from .qos import LOCKSTEP_QOS, RECORDED_QOS
from .rt import RtOptions
from .runtime import IoNodeOwner, LenientDoubles, publish_lossless, run_stepped_node


class DriveNode(IoNodeOwner, LenientDoubles, Node):
    """The base of a drive node (``drive_sim``, ``example_drive``): :meth:`open_topics`
    makes its topics. Every drive topic is recorded, so every publisher is reliable
    KEEP_ALL (``qos.RECORDED_QOS``): a recorder that stalls (a loaded real-time machine)
    back-pressures, it never loses a sample. The 5 kHz command path lives on a hidden node
    no executor spins. A subclass has ``counters`` (``commands``, ``watchdog_trips``,
    ``watchdog_steps``, ``backpressure``)."""

    #: the layouts a drive node reports as read-only parameters
    #: (``runtime.parameter_hygiene``'s facts: an override may not advertise another one)
    LAYOUTS: ClassVar[dict[str, list[str]]] = {
        'state_fields': list(STATE_FIELDS),
        'command_fields': list(COMMAND_FIELDS),
    }

    counters: Any
    #: the loop's real-time scheduling (``--thread-priority`` ...; :mod:`.rt`), applied by
    #: ``run`` on the thread that runs the loop; ``rt_report`` says the result
    rt_options: RtOptions = RtOptions()
    rt_report: dict | None = None
    #: set by SIGINT/SIGTERM: the loop stops at the next period boundary, so the context
    #: is never shut down under a publish
    stop_requested = False

    def open_topics(self, node_name: str) -> None:
        """``state_pub``, ``joint_pub`` (:meth:`make_joint_publisher`), ``status_pub``, and
        the command input: ``cmd_sub`` on ``io_node`` (``_<name>_io``: hidden, in this
        node's namespace and context, never spun), taken through a hand-rolled WaitSet
        (:meth:`wait_command`); ``commands`` (``pacing.CommandSource``) takes from it, or
        from a composed controller that hands its commands over in memory."""
        self.state_pub = self.create_publisher(Float64MultiArray, STATE_TOPIC, RECORDED_QOS)
        self.joint_pub = self.make_joint_publisher()
        self.status_pub = self.create_publisher(DiagnosticArray, STATUS_TOPIC, RECORDED_QOS)
        ns = self.get_namespace()
        self.io_node = Node(f'_{node_name}_io', context=self.context, namespace=ns)
        self.cmd_sub = self.io_node.create_subscription(
            Float64MultiArray, COMMAND_TOPIC, lambda _m: None, LOCKSTEP_QOS
        )
        self.commands = CommandSource(self.cmd_sub, len(COMMAND_FIELDS))
        self._cmd_waitset = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, self.context.handle)

    def wait_command(self, timeout_s: float) -> bool:
        """Sleep up to ``timeout_s`` [s] in rcl_wait; True when a command is pending."""
        ws = self._cmd_waitset
        ws.clear_entities()  # rcl_wait nulls entries that were not ready: re-add every time
        ws.add_subscription(self.cmd_sub.handle)
        ws.wait(int(timeout_s * NS_PER_S))
        return ws.is_ready('subscription', 0)

    def make_joint_publisher(self) -> Any:
        """``drive/joint_states``' publisher (a hook: a test drive may publish none)."""
        return self.create_publisher(JointState, JOINT_STATE_TOPIC, RECORDED_QOS)

    def read_command(self, data: Any) -> tuple[int, float, float] | None:
        """``drive/command``'s values ``data`` (``COMMAND_FIELDS``) as (answers_step,
        isq_ref [A], load torque [N m]), counted; None for a message of another length or
        with a value not finite, which the drive ignores (said on the log, at most once a
        second)."""
        n = len(COMMAND_FIELDS)
        # (each value by index: no generator made per command on the drive's Python path)
        if len(data) != n or not (
            math.isfinite(data[CMD_STEP])
            and math.isfinite(data[CMD_ISQ])
            and math.isfinite(data[CMD_LOAD])
        ):
            self.get_logger().error(
                f'{COMMAND_TOPIC}: expected {n} finite values {COMMAND_FIELDS}, got '
                f'{len(data)} values or a value not finite; ignored',
                throttle_duration_sec=1.0,
            )
            return None
        self.counters.commands += 1
        return int(data[CMD_STEP]), float(data[CMD_ISQ]), float(data[CMD_LOAD])

    def watchdog_expired(self, watchdog: CommandWatchdog, step: int, consequence: str) -> bool:
        """Once a period, after the commands were taken: True while ``watchdog`` has
        expired (the drive then zeroes its command; counted ``watchdog_steps``). The first
        period of a trip counts ``watchdog_trips`` and says so on the log, with the
        ``step`` index and the drive's ``consequence``; a command then resumes the drive
        (``CommandWatchdog.resume``)."""
        if not watchdog.expired():
            return False
        if watchdog.trip():
            self.counters.watchdog_trips += 1
            self.get_logger().warn(
                f'watchdog: no command on {COMMAND_TOPIC} for {watchdog.timeout_s:g} s at '
                f'step {step}: {consequence}'
            )
        self.counters.watchdog_steps += 1
        return True

    def send_status(self, status: DiagnosticStatus, values: dict[str, str]) -> None:
        """Publish ``status`` (name, hardware id, level and message set) with ``values``
        as its key/values, stamped now, on ``drive/status`` without loss (the
        back-pressure retries counted)."""
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.counters.backpressure += publish_lossless(self.status_pub, msg, self.context)


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
