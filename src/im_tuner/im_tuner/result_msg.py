"""The tuner's result topic (``names.RESULT_TOPIC``): a results.jsonl record as
``diagnostic_msgs/DiagnosticArray``, and the publisher the tuner node fills.

One ``DiagnosticStatus`` per record: its kind as ``name``, its status as ``level`` and
``message``, its fields as key/value strings in results.jsonl's order (floats with ``repr``:
they read back bit for bit), ``header.stamp`` the experiment's end in sim time; the fields
in full: docs/interfaces.md, "tuner/result".
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from im_controller.config import GAIN_NAMES

from .runlog.records import RIPPLE_KEYS, Record

if TYPE_CHECKING:
    from rclpy.node import Node


NS_PER_S = 1_000_000_000


def _text(v: Any) -> str:
    """One value as the message writes it (docs/interfaces.md, "tuner/result")."""
    if isinstance(v, bool):
        return 'true' if v else 'false'
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, int | str):
        return str(v)
    if isinstance(v, list):
        return ' '.join(_text(x) for x in v)
    return json.dumps(v, allow_nan=False, separators=(',', ':'))


def record_values(rec: Record) -> list[tuple[str, str]]:
    """The record's fields as the message's key/value strings (docs/interfaces.md,
    "tuner/result")."""
    out: list[tuple[str, str]] = []
    for k, v in rec.to_dict().items():
        if v is None:
            continue
        if k == 'gains':
            out += [(n, repr(float(v[n]))) for n in GAIN_NAMES if n in v]
        elif k == 'periods':
            out += [(p, str(v[p])) for p in ('fresh', 'held', 'late') if p in v]
        elif k == 'ripple':
            nan = float('nan')  # a window not measured
            out.append((k, ' '.join(repr(nan if v[r] is None else v[r]) for r in RIPPLE_KEYS)))
        else:
            out.append((k, _text(v)))
    return out


def record_to_msg(rec: Record, node_name: str) -> DiagnosticArray:
    """The message of one results.jsonl record (module docstring)."""
    st = DiagnosticStatus(name=rec.kind, hardware_id=node_name)
    why = rec.reason or ''
    if rec.status == 'ok':
        st.level, st.message = DiagnosticStatus.OK, 'ok'
    elif rec.status == 'aborted':
        st.level = DiagnosticStatus.ERROR if rec.fault else DiagnosticStatus.WARN
        st.message = f'aborted (penalised loss): {why}'
    elif rec.status == 'timing':
        st.level, st.message = DiagnosticStatus.WARN, f'timing, no loss: {why}'
    else:
        st.level, st.message = DiagnosticStatus.STALE, f'lost, no loss: {why}'
    st.values = [KeyValue(key=k, value=v) for k, v in record_values(rec)]
    msg = DiagnosticArray(status=[st])
    if rec.t_end_ns is not None:
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(rec.t_end_ns), NS_PER_S)
    return msg


class ResultPublisher:
    """Publishes each record on the tuner's result topic (``names.RESULT_QOS``): the
    sink :attr:`im_tuner.tuning.TuningRun.on_record` calls; :attr:`published` counts
    them (the bag must hold as many: ``bench.recorder_watch``)."""

    def __init__(self, node: Node, topic: str) -> None:
        from im_drive_sim.qos import qos_profile

        from .names import RESULT_QOS

        self.topic = topic
        self.node_name = node.get_fully_qualified_name()
        self.pub = node.create_publisher(DiagnosticArray, topic, qos_profile(RESULT_QOS))
        self.published = 0

    def __call__(self, rec: Record) -> None:
        self.pub.publish(record_to_msg(rec, self.node_name))
        self.published += 1
