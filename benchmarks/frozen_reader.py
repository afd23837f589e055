"""A reliable KEEP_ALL reader of every drive and controller topic, to be frozen (SIGSTOP).

    python benchmarks/frozen_reader.py

Prints ``ready`` on stdout once it has taken 100 drive states (so it is matched with every
publisher), then takes whatever comes until it is stopped -- a visualiser or a ``ros2 topic
echo`` suspended with Ctrl-Z is such a reader. bench_realtime.py's ``realtime-frozen-reader``
freezes it with SIGSTOP during a composed run and measures the loop's overruns and
lateness and the tuner's memory growth.
"""

from __future__ import annotations

import contextlib
import sys

import rclpy
import rclpy.executors
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

TOPICS = (
    ('/drive/state', Float64MultiArray),
    ('/drive/command', Float64MultiArray),
    ('/drive/joint_states', JointState),
    ('/drive/status', DiagnosticArray),
    ('/clock', Clock),
    ('/controller/internals', Float64MultiArray),
    ('/controller/loss', DiagnosticArray),
)


def main() -> int:
    rclpy.init()
    node = rclpy.create_node('frozen_reader')
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    taken = {'states': 0}

    def on_state(_msg) -> None:
        taken['states'] += 1
        if taken['states'] == 100:
            print('ready', flush=True)

    for name, typ in TOPICS:
        cb = on_state if name == '/drive/state' else (lambda _m: None)
        node.create_subscription(typ, name, cb, qos)
    with contextlib.suppress(KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        rclpy.spin(node)
    return 0


if __name__ == '__main__':
    sys.exit(main())
