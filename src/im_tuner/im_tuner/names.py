"""The controller's ROS names as the tuner reaches them, and the tuner's fault policies.

Pure (no rclpy): the tuner parses and checks its command line with these before it imports
anything of ROS (a refusal comes at once); :mod:`im_tuner.link` uses the same.
"""

from __future__ import annotations

import posixpath

from im_controller import contract as C
from im_drive_sim.contract import (
    COMMAND_TOPIC,
    JOINT_STATE_TOPIC,
    STATE_TOPIC,
    STATUS_TOPIC,
    QosSpec,
)

#: [periods] held or late drive periods an experiment may have and still count, by
#: default (the tuner's --timing-tolerance, the drive host's): within the bench's own
#: noise (docs/real-drive.md, "Timing tolerance")
DEFAULT_TIMING_TOLERANCE = 10

#: The node a drive host (``ros2 run im_tuner drive_host``) puts on the graph: a tuner
#: that sees it leaves the host's 5 kHz topics to the host's own bag.
DRIVE_HOST_NODE = 'drive_host'
#: A drive host's loop-rate topics (relative to the namespace; /clock absolute): the
#: 5 kHz ones and the drive's clock (200 Hz), recorded by the host itself; a tuner on
#: another computer does not pull them across the network (``recorder --exclude-topics``).
HOST_LOOP_TOPICS = (
    STATE_TOPIC,
    COMMAND_TOPIC,
    JOINT_STATE_TOPIC,
    C.INTERNALS_TOPIC,
    '/clock',
)

#: The tuner's results (relative: in the controller's namespace, as its loss topic): one
#: ``diagnostic_msgs/DiagnosticArray`` per results.jsonl record as it is appended
#: (:mod:`im_tuner.result_msg`; docs/interfaces.md, "tuner/result"), recorded in the bag.
RESULT_TOPIC = 'tuner/result'
#: Its publisher: reliable KEEP_ALL (every record reaches the recorder, as the other
#: recorded topics), transient local (a recorder or viewer that joins later gets the
#: session's records so far; a run's records are a few hundred small messages).
RESULT_QOS = QosSpec('keep_all', 0, 'reliable', 'transient_local')

#: after a safety fault: reset it and go on, or stop the run (``--fault-policy``)
FAULT_POLICIES = ('reset', 'stop')


def controller_topics(controller: str) -> dict[str, str]:
    """Fully qualified names of the controller's services and loss topic, and of the
    tuner's result topic in the controller's namespace (``result``)."""
    if not controller.startswith('/'):
        controller = '/' + controller
    ns = posixpath.dirname(controller)
    return {
        'start': f'{controller}/{C.START_SERVICE}',
        'reset': f'{controller}/{C.RESET_SERVICE}',
        'heartbeat': f'{controller}/{C.HEARTBEAT_TOPIC}',
        'set_atomic': f'{controller}/set_parameters_atomically',
        'loss': posixpath.join(ns, C.LOSS_TOPIC),
        'node': controller,
        'drive_status': posixpath.join(ns, STATUS_TOPIC),
        'result': posixpath.join(ns, RESULT_TOPIC),
    }
