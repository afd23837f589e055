"""The composed loop's publishers, routed through an outbox (``realtime.RealtimeBench``).

The loop thread never publishes on DDS: every publisher of the drive and the controller
(but :data:`NOT_ROUTED`) is made again with the loop's QoS (``contract.LOOP_PUBLISHED``,
KEEP_LAST 1000: bounded memory) and routed to an :class:`im_drive_sim.outbox.Outbox`,
whose rings the publisher threads empty onto the graph and the recorder taps.
"""

from __future__ import annotations

from typing import Any

from im_drive_sim import contract
from im_drive_sim.outbox import Outbox
from im_drive_sim.qos import qos_profile
from im_drive_sim.runtime import ROUTES

#: Outbox slots [bytes] and capacities [messages] per message type of the loop's topics
#: (other types: OTHER_SLOT, the outbox's default capacity).
SLOTS = {
    'std_msgs/msg/Float64MultiArray': (256, 5000),  # state 132 B, internals 220 B
    'rosgraph_msgs/msg/Clock': (64, 5000),
    'sensor_msgs/msg/JointState': (256, 5000),  # one joint: 84 B
    'diagnostic_msgs/msg/DiagnosticArray': (32768, 64),
}
OTHER_SLOT = (4096, 1000)

#: Topics the loop's nodes publish that stay off the outbox (rclpy publishes them from
#: the serving thread, as any node does).
NOT_ROUTED = ('/parameter_events', '/rosout')


def _type_name(cls: type) -> str:
    """'pkg/msg/Type' of a message class."""
    return f'{cls.__module__.split(".")[0]}/msg/{cls.__name__}'


def _republish(node: Any, old: Any, qos: Any, owners: tuple[Any, ...]) -> Any:
    """``old`` made again with ``qos`` (contract.LOOP_PUBLISHED), before anything was
    published on it; the attributes of ``owners`` that held it hold the new one."""
    pub = node.create_publisher(old.msg_type, old.topic_name, qos)
    for owner in owners:
        if owner is None:
            continue
        for name, value in list(vars(owner).items()):
            if value is old:
                setattr(owner, name, pub)
    node.destroy_publisher(old)
    return pub


def route_through_outbox(drv: Any, ctl: Any, capacity: int | None = None) -> Outbox:
    """The outbox every publisher of the drive ``drv`` and the controller ``ctl`` (and
    their I/O nodes) now goes through, before anything was published. ``capacity``:
    messages per topic ring (None: :data:`SLOTS`)."""
    outbox = Outbox()
    qos = qos_profile(contract.LOOP_PUBLISHED)
    for node in (drv, getattr(drv, 'io_node', None), ctl, ctl.io_node):
        if node is None:
            continue
        for old in list(node.publishers):
            if old.topic_name in NOT_ROUTED:
                continue
            pub = _republish(node, old, qos, (drv, ctl, ctl.client))
            type_name = _type_name(pub.msg_type)
            slot, cap = SLOTS.get(type_name, OTHER_SLOT)
            outbox.add(pub, type_name, slot, capacity or cap)
            ROUTES[id(pub)] = outbox
    return outbox
