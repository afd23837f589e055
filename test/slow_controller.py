"""A controller slowed on purpose, for test_realtime_bench.py: the controller node whose
answer takes ``--delay-us`` longer, run in its own process next to a real-time drive, so
that it falls behind the 5 kHz drive whatever the machine.

The delay is a sleep, not a busy wait: on a 2-core machine a busy-waiting controller
took the drive's core, the drive's own periods stretched past the delay (2403 overruns,
one of 333 ms, in a CI run) and the controller then answered every state in time: the
experiment was on the paper's timing and the test's premise was gone. Sleeping 2 ms
(10 drive periods) leaves the drive its core and keeps the controller behind unless the
drive is 10x slower than real time.

    python test/slow_controller.py --delay-us 2000 [--ros-args ...]
"""

from __future__ import annotations

import argparse
import sys
import time

from rclpy.utilities import remove_ros_args

from im_controller.controller_node import ControllerError, ControllerNode
from im_drive_sim.params import ConfigError
from im_drive_sim.runtime import run_stepped_node


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument('--delay-us', type=float, default=2000.0)
    cli = ap.parse_args(remove_ros_args(sys.argv)[1:])
    delay = cli.delay_us * 1e-6

    class SlowController(ControllerNode):
        def answer(self) -> bool:
            time.sleep(delay)
            return super().answer()

    from rclpy.parameter import Parameter

    return run_stepped_node(
        sys.argv,
        lambda: SlowController(parameter_overrides=[Parameter('mode', value='realtime')]),
        (ConfigError, ControllerError),
        'slow_controller',
    )


if __name__ == '__main__':
    sys.exit(main())
