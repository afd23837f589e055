"""check_drive's probe: the check's participant on the graph. It takes every state,
joint state and status the drive publishes (with their DDS time stamps), sends the
commands the procedure (:mod:`.procedure`) asks for, and keeps all of it in arrays for
the evaluation; it leaves the drive at zero current (:meth:`Probe.safe_stop`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ..cdr import read_float64_array
from ..contract import (
    COMMAND_TOPIC,
    JOINT_STATE_TOPIC,
    NS_PER_S,
    STATE_FIELDS,
    STATE_INDEX as F,
    STATE_TOPIC,
    STATUS_TOPIC,
    QosSpec,
)


class Interrupted(Exception):
    """SIGINT/SIGTERM during the check."""


class DriveLost(Exception):
    """The drive stopped publishing states in the middle of the check: exit code 1."""


class Probe:
    """Records every drive/state (with its DDS time stamps), joint state and command."""

    def __init__(self, node, capacity: int = 60000) -> None:
        # ROS imports here, not at module level: the judging functions need none.
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray

        from im_drive_sim.qos import qos_profile

        self.node = node
        self._Float64MultiArray, self._JointState = Float64MultiArray, JointState
        self._DiagnosticArray = DiagnosticArray

        # Best-effort readers: what the network loses is lost (the publication sequence
        # numbers show it), never held back (a reliable reader would hold every later
        # state until a lost one was repaired). Deep keep-last: a stall of this process up
        # to 1 s loses nothing.
        def best_effort(depth: int) -> Any:
            return qos_profile(QosSpec('keep_last', depth, 'best_effort'))

        noop = lambda _m: None  # noqa: E731 (taken by hand, never by an executor)
        self.state_sub = node.create_subscription(
            Float64MultiArray, STATE_TOPIC, noop, best_effort(5000)
        )
        self.joint_sub = node.create_subscription(
            JointState, JOINT_STATE_TOPIC, noop, best_effort(1000)
        )
        self.status_sub = node.create_subscription(
            DiagnosticArray, STATUS_TOPIC, noop, best_effort(10)
        )
        self.cmd_pub = None
        self.stopped = False
        self.waitset = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, node.context.handle)
        n = capacity
        self.states = np.full((n, len(STATE_FIELDS)), np.nan)
        self.lengths = np.zeros(n, dtype=np.int64)
        self.source_ns = np.zeros(n, dtype=np.int64)  # drive's publication time [ns, wall]
        self.recv_ns = np.zeros(n, dtype=np.int64)  # DDS reception time [ns, wall]
        self.take_ns = np.zeros(n, dtype=np.int64)  # when this process took it [ns, wall]
        self.seq = np.zeros(n, dtype=np.int64)
        self.n = 0
        self.cmd = np.zeros((n, 3))  # answers_step, isq*, load
        self.cmd_ns = np.zeros(n, dtype=np.int64)  # published at [ns, wall]
        self.m = 0
        self.joints: list[tuple[float, float, float, float]] = []
        self.status: dict[str, str] = {}
        self.answered = -1  # newest step index we answered
        self.created = time.monotonic()  # when this participant joined
        self.stop: Callable[[], bool] = lambda: False

    def open_command(self) -> None:
        from im_drive_sim.qos import RECORDED_QOS

        self.cmd_pub = self.node.create_publisher(
            self._Float64MultiArray, COMMAND_TOPIC, RECORDED_QOS
        )
        self._cmd_msg = self._Float64MultiArray(data=[0.0, 0.0, 0.0])

    def poll(self, timeout_s: float) -> int:
        """Wait up to ``timeout_s`` for states; take every pending message. Returns the
        number of new states."""
        if self.stop():
            raise Interrupted
        ws = self.waitset
        ws.clear_entities()
        ws.add_subscription(self.state_sub.handle)
        ws.wait(int(max(0.0, timeout_s) * NS_PER_S))
        got = 0
        width = len(STATE_FIELDS)
        while self.n < len(self.states):
            r = self.state_sub.handle.take_message(self._Float64MultiArray, True)
            if r is None:
                break
            raw, info = r
            data = np.asarray(read_float64_array(raw, width))  # our compact layout: no copy
            i = self.n
            self.lengths[i] = len(data)
            if len(data) == width:
                self.states[i] = data
            self.source_ns[i] = info['source_timestamp']
            self.recv_ns[i] = info.get('received_timestamp') or time.time_ns()
            self.take_ns[i] = time.time_ns()
            self.seq[i] = info.get('publication_sequence_number') or 0
            self.n += 1
            got += 1
        while (r := self.joint_sub.handle.take_message(self._JointState, False)) is not None:
            j = r[0]
            if len(j.position) and len(j.velocity) and len(j.effort):
                self.joints.append(
                    (
                        j.header.stamp.sec * NS_PER_S + j.header.stamp.nanosec,
                        j.position[0],
                        j.velocity[0],
                        j.effort[0],
                    )
                )
        while (r := self.status_sub.handle.take_message(self._DiagnosticArray, False)) is not None:
            for st in r[0].status:
                self.status = {kv.key: kv.value for kv in st.values}
        return got

    def newest(self) -> np.ndarray | None:
        """The newest complete state taken (a view), or None."""
        for i in range(self.n - 1, -1, -1):
            if self.lengths[i] == len(STATE_FIELDS):
                return self.states[i]
        return None

    def command(self, answers: int, isq: float, load: float = 0.0) -> None:
        msg = self._cmd_msg
        msg.data[0], msg.data[1], msg.data[2] = float(answers), float(isq), float(load)
        self.cmd_pub.publish(msg)
        if self.m < len(self.cmd):
            self.cmd[self.m] = (answers, isq, load)
            self.cmd_ns[self.m] = time.time_ns()
            self.m += 1
        self.answered = max(self.answered, answers)

    def run(
        self,
        policy: Callable[[int, np.ndarray], float | None],
        done: Callable[[], bool],
        max_wall: float,
    ) -> bool:
        """Answer each new state k with isq* = policy(k, state) (None: stay silent) until
        ``done()``; False when ``max_wall`` s passed first."""
        deadline = time.monotonic() + max_wall
        while not done():
            if time.monotonic() > deadline:
                return False
            if self.poll(min(0.05, max(0.0, deadline - time.monotonic()))) == 0:
                continue
            s = self.newest()
            if s is None:
                continue
            k = int(s[F['step_index']])
            if k <= self.answered:
                continue  # a re-sent state (lock-step) or one already answered
            isq = policy(k, s)
            if isq is not None:
                self.command(k, isq)
        return True

    def safe_stop(self) -> None:
        """Leave the drive commanding zero current (and no load); once."""
        if self.cmd_pub is None or self.stopped:
            return
        self.stopped = True
        from rclpy.duration import Duration

        s = self.newest()
        k = int(s[F['step_index']]) if s is not None else -1
        self.command(k if k > self.answered else -1, 0.0)
        self.command(-1, 0.0)
        # Delivered before this process goes (reliable only promises it while we live).
        self.cmd_pub.wait_for_all_acked(Duration(seconds=0.3))
