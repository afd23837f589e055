"""``ros2 run im_tuner recorder``, the executable's node side: a :class:`~.node.Recorder`
polled every millisecond until SIGINT/SIGTERM, and its status topic (:mod:`.status`).

Its command line is checked first by :mod:`.recorder_main`, before rclpy is imported.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node

from im_drive_sim.cli import UsageError, parse_cli
from im_drive_sim.qos import qos_profile
from im_drive_sim.runtime import RosSession, unknown_overrides, warn_unknown_overrides

from .live import live_settings
from .metadata import BagError
from .node import Recorder, RecorderError
from .recorder_main import parser
from .run_info import default_out_dir
from .status import STATUS_PERIOD_S, STATUS_QOS, STATUS_TOPIC, TopicStatus, to_msg


class StatusPublisher:
    """The recorder child's ``~/status`` (:mod:`.status`): published when it changed, at
    most every ``STATUS_PERIOD_S``; its own topic is not recorded."""

    def __init__(self, node: Node, rec: Recorder) -> None:
        self.rec = rec
        self.pub = node.create_publisher(DiagnosticArray, STATUS_TOPIC, qos_profile(STATUS_QOS))
        rec.own_topics.add(self.pub.topic_name)
        self.bag = str(Path(rec.out).resolve())
        self._last: dict[str, TopicStatus] | None = None
        self._next = 0.0

    def poll(self) -> None:
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + STATUS_PERIOD_S
        topics = self.rec.topic_status()
        if topics != self._last:
            self._last = topics
            self.pub.publish(to_msg(self.bag, topics, time.time_ns()))


def main(args: list[str] | None = None) -> int:
    argv = sys.argv if args is None else args
    try:
        cli = parse_cli(parser(), argv)
        live = live_settings(cli.live, cli.live_host, cli.live_rate, no_record=False)
    except UsageError as exc:
        print(f'error: recorder: {exc}', file=sys.stderr)
        return 2
    if cli.repair is not None:
        from .repair import RepairError, repair_bag

        try:
            report = repair_bag(cli.repair)
        except RepairError as exc:
            print(f'error: recorder --repair: {exc}', file=sys.stderr)
            return 2
        print(report.summary())
        return 0
    out = cli.out if cli.out is not None else default_out_dir()
    # A short DDS lease, so that writers forget a killed recorder within about a second
    # instead of blocking on it (config/recorder_fastdds.xml says why).
    os.environ.setdefault(
        'FASTRTPS_DEFAULT_PROFILES_FILE',
        str(Path(__file__).parent.parent / 'config' / 'recorder_fastdds.xml'),
    )
    session = RosSession(argv)
    node = None
    rec = None
    try:
        node = Node('recorder', start_parameter_services=False)
        try:
            rec = Recorder(
                node,
                out,
                compression=cli.compression,
                chunk_size=cli.chunk_size,
                max_chunk_age=cli.max_chunk_age,
                command=argv,
                exclude=sorted(set(cli.exclude_topics)),  # (fully qualified by the parser)
                live=live,
            )
        except (BagError, RecorderError) as exc:
            print(f'error: recorder: {exc}', file=sys.stderr)
            return 2
        warn_unknown_overrides(node, unknown_overrides(node))  # it has no parameters
        node.get_logger().info(f'recording to {rec.out} (compression {cli.compression})')
        status = StatusPublisher(node, rec)
        while not session.stopped:
            if rec.poll() == 0:
                time.sleep(0.001)
            status.poll()
        rec.close(settle=0.1)
        return 0
    finally:
        if rec is not None and not rec.writer.closed:
            rec.close()
        if node is not None:
            node.destroy_node()
        session.close()


if __name__ == '__main__':
    os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    sys.exit(main())
