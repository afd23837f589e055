"""A deliberately broken drive for test_check_drive.py: the example drive with breakages.

    python test/broken_drive.py --break rate,joint_type [--ros-args ...]

Each breakage violates one item of docs/interfaces.md (the conformance check must fail
exactly that item):

=============  ======================================================  =============
breakage       what it does                                            item
=============  ======================================================  =============
rate           publishes every 250 us instead of 200 us                rate
watchdog       no command watchdog: holds the last command forever     watchdog
degrees        theta_meas (and joint_states position) in degrees       fields
late           applies each command 3 periods late                     latency
slower         acts with command delay 2, declares (and labels) 1       latency
sign           torque opposite to isq (torque sign inverted)           step_response
slow_current   current loop 10 times too slow                          step_response
joint_type     Float64MultiArray on drive/joint_states                 topics
=============  ======================================================  =============
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import deque

from rclpy.utilities import remove_ros_args
from std_msgs.msg import Float64MultiArray

from im_drive_sim.contract import JOINT_STATE_TOPIC
from im_drive_sim.example_drive import ExampleDrive, Hardware, main

BREAKAGES = (
    'rate',
    'watchdog',
    'degrees',
    'late',
    'slower',
    'sign',
    'slow_current',
    'joint_type',
)


class SignInverted(Hardware):
    def torque_of(self, isq: float) -> float:
        return -self.kt * isq


class SlowCurrent(Hardware):
    def __init__(self, config) -> None:
        super().__init__(config)
        self.a_i = math.exp(-self.ts * config.control.current_bandwidth / 10.0)


def broken_class(breaks: set[str]) -> type:
    """An ExampleDrive subclass with the given breakages."""

    class BrokenDrive(ExampleDrive):
        def __init__(self) -> None:
            self._late = deque([(0.0, 0.0)] * 3)
            super().__init__('broken_drive')
            if 'rate' in breaks:
                self.period_s = 250e-6
            if 'slower' in breaks:  # the hardware acts with delay 2; the node says 1
                self.command_delay = 1
                self.wire.values[13] = 1
            self.get_logger().warn(f'BROKEN drive: {",".join(sorted(breaks))}')

        def make_hardware(self) -> Hardware:
            cls = Hardware
            if 'sign' in breaks:
                cls = SignInverted
            elif 'slow_current' in breaks:
                cls = SlowCurrent
            hw = cls(self.config)
            if 'slower' in breaks:  # a power stage that latches its command (delay 2)
                hw.command_delay = 2
            return hw

        def make_joint_publisher(self):
            if 'joint_type' in breaks:
                return self.create_publisher(Float64MultiArray, JOINT_STATE_TOPIC, 10)
            return super().make_joint_publisher()

        def publish_joint_state(self) -> None:
            if 'joint_type' in breaks:
                v = self.wire.values
                self.joint_pub.publish(Float64MultiArray(data=[v[2], v[3], v[4]]))
            else:
                super().publish_joint_state()

        def apply_command(self, isq_ref: float, load_torque: float) -> None:
            if 'late' in breaks:  # a 3-period delay line
                self._late.append((isq_ref, load_torque))
                isq_ref, load_torque = self._late.popleft()
            super().apply_command(isq_ref, load_torque)

        def watchdog(self) -> None:
            if 'watchdog' not in breaks:
                super().watchdog()

        def fill_state(self, m) -> None:
            super().fill_state(m)
            if 'degrees' in breaks:
                v = self.wire.values
                v[2] = math.degrees(v[2])
                v[10] = v[2]

    return BrokenDrive


if __name__ == '__main__':
    ap = argparse.ArgumentParser()
    ap.add_argument(
        '--break', dest='breaks', required=True, help='comma-separated: ' + ','.join(BREAKAGES)
    )
    ns = ap.parse_args(remove_ros_args(sys.argv)[1:])
    chosen = set(ns.breaks.split(','))
    if not chosen <= set(BREAKAGES):
        ap.error(f'unknown breakage(s) {sorted(chosen - set(BREAKAGES))}')
    sys.exit(main(node_class=broken_class(chosen)))
