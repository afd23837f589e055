"""The drive contract's QoS profiles as rclpy ``QoSProfile`` objects.

The contract (:mod:`.contract`) holds them as plain data (``QosSpec``) so that it stays
free of rclpy; this module is the one place they become rclpy profiles. It imports only
``rclpy.qos`` -- neither a node module nor the numba kernels -- so the controller, the
tuner and a user's drive get the profiles without loading the simulator.
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from . import contract
from .contract import QosSpec


def qos_profile(spec: QosSpec) -> QoSProfile:
    """The rclpy ``QoSProfile`` of a contract ``QosSpec`` (contract.LOCKSTEP, RECORDED)."""
    return QoSProfile(
        history=HistoryPolicy[spec.history.upper()],
        depth=spec.depth,
        reliability=ReliabilityPolicy[spec.reliability.upper()],
        durability=DurabilityPolicy[spec.durability.upper()],
    )


#: the 5 kHz lock-step path's readers and the command subscription (contract.LOCKSTEP)
LOCKSTEP_QOS = qos_profile(contract.LOCKSTEP)
#: every recorded topic's publisher: reliable KEEP_ALL (contract.RECORDED)
RECORDED_QOS = qos_profile(contract.RECORDED)
#: the controller's experiment services and their introspection (contract.SERVICES)
SERVICES_QOS = qos_profile(contract.SERVICES)
