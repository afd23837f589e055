"""The drive's own counters for the run summary: ``drive/status`` read and compared.

A drive (simulated, composed or external) publishes its counters (overruns, late and
held commands, watchdog trips...) on ``drive/status`` about once a second
(docs/interfaces.md). :func:`drive_report` turns one status into the summary's numbers,
:func:`drive_delta` gives a long-lived drive's share of one session, and
:class:`DriveMonitor` keeps the newest status a drive published (the child-process and
external benches). Pure but for :class:`DriveMonitor`, which imports rclpy when built.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from im_drive_sim.contract import STATUS_COUNTERS


def drive_report(
    values: dict[str, str], level: int | None = None, message: str = ''
) -> dict[str, Any]:
    """The summary's view of a drive's status key/values: the mode, the counters
    (``contract.STATUS_COUNTERS``, docs/interfaces.md) as numbers (unknown or
    unparsable ones left out: a real drive may report fewer)."""
    out: dict[str, Any] = {'mode': values.get('mode', 'unknown'), 'model': values.get('model')}
    for k in (*STATUS_COUNTERS, 'command_delay', 'real_time_factor', 'sim_time_s'):
        try:
            v = float(values[k])
        except (KeyError, ValueError):
            continue
        out[k] = int(v) if v.is_integer() and k not in ('real_time_factor', 'sim_time_s') else v
    if level is not None:
        out['level'], out['message'] = int(level), message
    return out


def drive_delta(start: dict[str, Any] | None, end: dict[str, Any] | None) -> dict[str, Any] | None:
    """A long-lived (external) drive's counters over one session: ``end`` minus
    ``start`` (two :func:`drive_report` results), marked ``per_session``. The worst
    lateness is a maximum, not a count: kept when it grew in the session, else given as
    a bound (``max_lateness_us_at_most``). No ``start``: ``end`` as it is (the drive's
    counters since it started, marked ``per_session: False``); a counter that went down
    (the drive restarted in the session): ``end`` as it is, marked ``restarted``."""
    if end is None:
        return None
    if start is None:
        return {**end, 'per_session': False}
    out = {k: v for k, v in end.items() if k not in STATUS_COUNTERS}
    for k in STATUS_COUNTERS:
        if k not in end:
            continue
        if k == 'max_lateness_us':  # a maximum, not a count
            if k not in start or end[k] > start[k]:
                out[k] = end[k]
            else:
                out['max_lateness_us_at_most'] = start[k]
            continue
        if k not in start:
            continue  # (unknown at the start: the session's share is unknown)
        if end[k] < start[k]:
            return {**end, 'per_session': False, 'restarted': True}
        out[k] = end[k] - start[k]
    if 'sim_time_s' in end and 'sim_time_s' in start:
        out['sim_time_s'] = end['sim_time_s'] - start['sim_time_s']
    out['per_session'] = True
    return out


class DriveMonitor:
    """The drive's own counters (overruns, late and held commands, watchdog trips...),
    from the newest ``drive/status`` it publishes (about 1 Hz)."""

    def __init__(self, node: Any, topic: str) -> None:
        """``node``: an rclpy node that subscribes to ``topic`` (a drive's status)."""
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

        self.topic = topic
        self.received = 0
        self.last: dict[str, Any] | None = None
        #: the report the session started from (:meth:`mark`; None: not marked)
        self.start: dict[str, Any] | None = None
        qos = QoSProfile(
            depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE
        )
        self.sub = node.create_subscription(DiagnosticArray, topic, self._on_status, qos)

    def _on_status(self, msg: Any) -> None:
        for st in msg.status:
            values = {kv.key: kv.value for kv in st.values}
            if 'mode' not in values:
                continue  # some other diagnostic on the topic
            lvl = (
                int.from_bytes(st.level, 'little') if isinstance(st.level, bytes) else int(st.level)
            )
            self.last = drive_report(values, lvl, st.message)
            self.received += 1

    def mark(self, spin_until: Callable[[Callable[[], bool], float], bool], timeout: float) -> None:
        """Take the drive's counters at the session's start: a status newer than this
        call, waited for up to ``timeout`` s (the drive reports about once a second);
        else the newest one, if any. None has come yet: up to ``DISCOVERY_S`` more, for
        a subscription made moments ago to meet the drive's publisher (seconds on a
        loaded machine) and its next report."""
        n0 = self.received
        if not spin_until(lambda: self.received > n0, timeout) and self.last is None:
            spin_until(lambda: self.received > n0, self.DISCOVERY_S)
        self.start = None if self.last is None else dict(self.last)

    #: [s] the longer wait of :meth:`mark` for a first report (research/NOTES.md, "From
    #: the source of im_tuner/bench/drive_status.py")
    DISCOVERY_S = 5.0
