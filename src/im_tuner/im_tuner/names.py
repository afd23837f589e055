"""The controller's ROS names as the tuner reaches them, and the tuner's fault policies.

Pure (no rclpy): the tuner parses and checks its command line with these before it imports
anything of ROS (a refusal comes at once); :mod:`im_tuner.link` uses the same.
"""

from __future__ import annotations

import posixpath

from im_controller import contract as C
from im_drive_sim.contract import STATUS_TOPIC

__all__ = ['FAULT_POLICIES', 'controller_topics']

#: after a safety fault: reset it and go on, or stop the run (``--fault-policy``)
FAULT_POLICIES = ('reset', 'stop')


def controller_topics(controller: str) -> dict[str, str]:
    """Fully qualified names of the controller's services and loss topic."""
    if not controller.startswith('/'):
        controller = '/' + controller
    ns = posixpath.dirname(controller)
    return {
        'start': f'{controller}/{C.START_SERVICE}',
        'reset': f'{controller}/{C.RESET_SERVICE}',
        'set_atomic': f'{controller}/set_parameters_atomically',
        'loss': posixpath.join(ns, C.LOSS_TOPIC),
        'node': controller,
        'drive_status': posixpath.join(ns, STATUS_TOPIC),
    }
