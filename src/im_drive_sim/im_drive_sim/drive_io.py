"""ROS plumbing both drive nodes share (``drive_sim`` and ``example_drive``).

* :class:`CommandPath`: the 5 kHz ``drive/command`` path -- a subscription on a hidden
  helper node (``_<name>_io``) that no executor ever spins, taken through a hand-rolled
  WaitSet, so the hot path never goes through an executor.
* :func:`publish_status`: one ``drive/status`` DiagnosticArray from a level, a message
  and the key/values, published without loss.
* :func:`run_drive_node`: a drive node's ``main()`` body (``runtime.run_stepped_node``
  with the counters' summary logged at exit).
"""

from __future__ import annotations

from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from .contract import COMMAND_FIELDS, COMMAND_TOPIC
from .pacing import CommandSource
from .params import ConfigError
from .qos import LOCKSTEP_QOS
from .runtime import publish_lossless, run_stepped_node

__all__ = ['CommandPath', 'publish_status', 'run_drive_node']


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


def run_drive_node(argv: list[str], make: Callable[[], object], prog: str) -> int:
    """Run the drive node ``make()`` builds until it stops (``runtime.run_stepped_node``):
    a bad parameter file is one line and exit code 2; the node's ``log_summary()`` runs
    at exit."""
    return run_stepped_node(
        argv,
        make,
        (ConfigError,),
        prog,
        on_exit=lambda node: node.log_summary(),
    )
