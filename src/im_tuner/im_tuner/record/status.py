"""The recorder child's status topic, ``~/status``: what it has matched and recorded, per
topic (docs/recorder.md, "The recorder child's status, and the tuner's two waits"). One
``DiagnosticStatus`` per recorded topic: ``name`` the topic, ``hardware_id`` the bag
directory (absolute), ``level`` OK or WARN while a publisher is not matched yet, ``values``
:data:`KEYS`. Pure: message classes only, no rclpy."""

from __future__ import annotations

from dataclasses import dataclass

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from im_drive_sim.contract import QosSpec

#: The status topic, relative to the recorder node (``~/status``).
STATUS_TOPIC = '~/status'
#: Its publisher: the last status, kept for a subscriber that joins later.
STATUS_QOS = QosSpec('keep_last', 1, 'reliable', 'transient_local')
#: How often at most the recorder publishes a changed status [s].
STATUS_PERIOD_S = 0.05
#: How long the tuner waits for the bag to hold every loss it received before it stops
#: the recorder [s]: above Fast DDS's default heartbeat period of a reliable writer (3 s),
#: after which a message lost on the network is resent.
CATCH_UP_S = 5.0
KEYS = ('recorded', 'matched_publishers', 'publishers')


@dataclass(frozen=True)
class TopicStatus:
    """One recorded topic: messages in the bag, publishers matched / on the graph."""

    recorded: int
    matched_publishers: int
    publishers: int

    @property
    def matched(self) -> bool:
        """Every publisher on the graph is matched (and there is one)."""
        return self.publishers > 0 and self.matched_publishers >= self.publishers


def to_msg(bag: str, topics: dict[str, TopicStatus], stamp_ns: int) -> DiagnosticArray:
    """The status message of the recorder writing ``bag`` (``stamp_ns``: wall clock [ns])."""
    msg = DiagnosticArray()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    for name in sorted(topics):
        t = topics[name]
        s = DiagnosticStatus()
        s.level = DiagnosticStatus.OK if t.matched else DiagnosticStatus.WARN
        s.name = name
        s.hardware_id = bag
        s.message = 'recording' if t.matched else 'recording; a publisher is not matched yet'
        s.values = [KeyValue(key=k, value=str(getattr(t, k))) for k in KEYS]
        msg.status.append(s)
    return msg


def from_msg(msg: DiagnosticArray) -> tuple[str, dict[str, TopicStatus]]:
    """(bag, per-topic status) of a status message; ValueError when it is not one."""
    bag = ''
    topics: dict[str, TopicStatus] = {}
    for s in msg.status:
        values = {kv.key: kv.value for kv in s.values}
        try:
            topics[s.name] = TopicStatus(*(int(values[k]) for k in KEYS))
        except (KeyError, ValueError) as exc:
            raise ValueError(f'not a recorder status ({s.name}: {exc!r})') from None
        if bag and s.hardware_id != bag:
            raise ValueError('a recorder status names two bags')
        bag = s.hardware_id
    return bag, topics
