"""The controller side of the drive interface (docs/interfaces.md), for lock-step loops.

:class:`DriveClient` takes ``drive/state`` and publishes ``drive/command`` with a
hand-rolled WaitSet -- no executor in the 5 kHz path -- reusing its messages. The node
it lives on must not be spun by an executor (an executor would take the states).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from .cdr import Float64ArrayWire, read_float64_array
from .contract import (
    COMMAND_FIELDS,
    COMMAND_TOPIC,
    NS_PER_S,
    STATE_FIELDS,
    STATE_TOPIC,
)
from .qos import LOCKSTEP_QOS, RECORDED_QOS
from .runtime import publish_lossless


class DriveClient:
    """Take drive states and answer them with commands, lock-step.

    ``wait_state(timeout)`` returns the newest state as a float64 array laid out as
    ``STATE_FIELDS`` (or None on timeout); ``command(k, isq_ref, load_torque)`` answers
    state k. ``answered`` remembers the last answered step, so a state the drive re-sends
    (see "Lock-step" in docs/interfaces.md) is not answered twice unless asked.
    """

    def __init__(self, node: Node) -> None:
        self.node = node
        self.state_sub = node.create_subscription(
            Float64MultiArray, STATE_TOPIC, lambda _m: None, LOCKSTEP_QOS
        )
        self.command_pub = node.create_publisher(Float64MultiArray, COMMAND_TOPIC, RECORDED_QOS)
        self._waitset = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, node.context.handle)
        #: the command message, preallocated (its values are written in place)
        self.command_wire = Float64ArrayWire(len(COMMAND_FIELDS))
        self.state = np.zeros(len(STATE_FIELDS))
        self.answered: int = -1
        #: publish retries while a reliable reader (the recorder) was full
        self.backpressure: int = 0
        #: Publisher-side time stamp [ns, wall] of the newest state taken.
        self.source_timestamp_ns: int = 0
        #: composed with the drive in one loop: ``hand_over(values)`` gives each command
        #: to the drive in memory (``pacing.CommandSource.hand_over``), then it is
        #: published as before (the outbox: for the graph and the recorder)
        self.hand_over: Callable[[np.ndarray], None] | None = None

    def take_state(self) -> np.ndarray | None:
        """Take every pending state without waiting; return the newest (or None)."""
        got = None
        n = len(STATE_FIELDS)
        while True:
            # Raw CDR: our own layout is read straight into numpy (no message object).
            r = self.state_sub.handle.take_message(Float64MultiArray, True)
            if r is None:
                return got
            data = read_float64_array(r[0], n)
            if len(data) != n:  # not the contract's state (check_drive names what is wrong)
                continue
            self.state[:] = data
            self.source_timestamp_ns = r[1]['source_timestamp']
            got = self.state

    def wait_state(self, timeout: float) -> np.ndarray | None:
        """Block up to ``timeout`` seconds for a state; return the newest one or None."""
        got = self.take_state()
        if got is not None:
            return got
        ws = self._waitset
        ws.clear_entities()  # rcl_wait nulls entries that were not ready: re-add every time
        ws.add_subscription(self.state_sub.handle)
        ws.wait(int(timeout * NS_PER_S))
        return self.take_state()

    def wait_new_state(self, timeout: float) -> np.ndarray | None:
        """Like :meth:`wait_state` but skip states already answered (re-sent ones)."""
        deadline = time.monotonic() + timeout
        while True:
            s = self.wait_state(max(0.0, deadline - time.monotonic()))
            if s is not None and int(s[0]) > self.answered:
                return s
            if time.monotonic() >= deadline:
                return None

    def command(self, answers_step: int, isq_ref: float, load_torque: float = 0.0) -> None:
        """Publish the command answering state ``answers_step``."""
        v = self.command_wire.values
        v[0] = answers_step
        v[1] = isq_ref
        v[2] = load_torque
        if self.hand_over is not None:
            self.hand_over(v)
        self.backpressure += publish_lossless(
            self.command_pub, self.command_wire, self.node.context
        )
        if answers_step > self.answered:
            self.answered = answers_step

    def wait_for_drive(self, timeout: float) -> bool:
        """True once a drive's state publisher is matched to our subscription."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if (
                self.state_sub.get_publisher_count() > 0
                and self.command_pub.get_subscription_count() > 0
            ):
                return True
            ws = self._waitset
            ws.clear_entities()
            ws.add_subscription(self.state_sub.handle)
            ws.wait(int(0.01 * NS_PER_S))
        return False
