"""ROS plumbing both drive nodes share (``drive_sim`` and ``example_drive``).

* :class:`CommandPath`: the 5 kHz ``drive/command`` path -- a subscription on a hidden
  helper node (``_<name>_io``) that no executor ever spins, taken through a hand-rolled
  WaitSet, so the hot path never goes through an executor.
* :func:`watchdog_expired`: the command watchdog's period -- a trip counted and said once.
* :func:`publish_status`: one ``drive/status`` DiagnosticArray from a level, a message
  and the key/values, published without loss.
* :func:`run_drive_node`: a drive node's ``main()`` body (``runtime.run_stepped_node``
  with the counters' summary logged at exit).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from .contract import COMMAND_FIELDS, COMMAND_TOPIC
from .pacing import CommandSource, CommandWatchdog
from .params import ConfigError
from .qos import LOCKSTEP_QOS
from .rt import RtOptions
from .runtime import publish_lossless, run_stepped_node

__all__ = ['CommandPath', 'publish_status', 'run_drive_node', 'watchdog_expired']


class CommandPath:
    """The drive's command input. ``io_node`` (hidden, in the drive node's namespace and
    context) holds ``subscription``; ``source`` (``pacing.CommandSource``) takes from it --
    or from a composed controller that hands its commands over in memory."""

    def __init__(self, node: Node, node_name: str) -> None:
        self.io_node = Node(
            f'_{node_name}_io', context=node.context, namespace=node.get_namespace()
        )
        self.subscription = self.io_node.create_subscription(
            Float64MultiArray, COMMAND_TOPIC, lambda _m: None, LOCKSTEP_QOS
        )
        self.source = CommandSource(self.subscription, len(COMMAND_FIELDS))
        self._waitset = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, node.context.handle)

    def wait(self, timeout_ns: int) -> bool:
        """Sleep up to ``timeout_ns`` [ns] in rcl_wait; True when a command is pending."""
        ws = self._waitset
        ws.clear_entities()  # rcl_wait nulls entries that were not ready: re-add every time
        ws.add_subscription(self.subscription.handle)
        ws.wait(timeout_ns)
        return ws.is_ready('subscription', 0)


def watchdog_expired(
    node: Node, watchdog: CommandWatchdog, counters: Any, step: int, consequence: str
) -> bool:
    """Once a period, after the commands were taken: True while ``watchdog`` has expired
    (the drive then zeroes its command; counted ``watchdog_steps``). The first period of
    a trip counts ``watchdog_trips`` and says so on the log, with the ``step`` index and
    the drive's ``consequence``; a command then resumes the drive
    (``CommandWatchdog.resume``)."""
    if not watchdog.expired():
        return False
    if watchdog.trip():
        counters.watchdog_trips += 1
        node.get_logger().warn(
            f'watchdog: no command on {COMMAND_TOPIC} for {watchdog.timeout_s:g} s at step '
            f'{step}: {consequence}'
        )
    counters.watchdog_steps += 1
    return True


def publish_status(
    node: Node,
    pub,
    status: DiagnosticStatus,
    values: dict[str, str],
) -> int:
    """Publish ``status`` (name, hardware id, level and message set) with ``values`` as its
    key/values, stamped now, on ``pub`` without loss; returns the back-pressure retries."""
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    msg = DiagnosticArray(status=[status])
    msg.header.stamp = node.get_clock().now().to_msg()
    return publish_lossless(pub, msg, node.context)


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
