"""What the recorder writes of a topic it finds on the graph, pure (no rclpy): the Python
class of its ROS type, its publishers' QoS (rosbag2's ``offered_qos_profiles``) and its
type hash. The graph's endpoint objects come from the recorder node (duck-typed here)."""

from __future__ import annotations

import importlib
from typing import Any

from .metadata import qos_to_dict


def message_class(type_name: str) -> Any:
    """The Python class of a ROS type string (``pkg/msg/T``, ``pkg/srv/T_Event``...)."""
    parts = type_name.split('/')
    if len(parts) != 3:
        raise ImportError(f'not a ROS type name: {type_name!r}')
    pkg, kind, name = parts
    mod = importlib.import_module(f'{pkg}.{kind}')
    if kind == 'msg':
        return getattr(mod, name)
    for suffix, attr in (('_Event', 'Event'), ('_Request', 'Request'), ('_Response', 'Response')):
        if kind == 'srv' and name.endswith(suffix):
            return getattr(getattr(mod, name[: -len(suffix)]), attr)
    if kind == 'action':
        for suffix, path in (
            ('_FeedbackMessage', ('Impl', 'FeedbackMessage')),
            ('_Feedback', ('Feedback',)),
            ('_Goal', ('Goal',)),
            ('_Result', ('Result',)),
        ):
            if name.endswith(suffix):
                obj = getattr(mod, name[: -len(suffix)])
                for a in path:
                    obj = getattr(obj, a)
                return obj
    return getattr(mod, name)


def _enum_name(value: Any) -> str:
    return getattr(value, 'name', str(value)).lower()


def endpoint_qos(info: Any) -> dict:
    """A publisher's QoS (an rclpy TopicEndpointInfo's ``qos_profile``) as a rosbag2 dict."""
    q = info.qos_profile
    return qos_to_dict(
        _enum_name(q.history),
        q.depth,
        _enum_name(q.reliability),
        _enum_name(q.durability),
        q.deadline.nanoseconds,
        q.lifespan.nanoseconds,
        _enum_name(q.liveliness),
        q.liveliness_lease_duration.nanoseconds,
    )


def endpoint_type_hash(info: Any) -> str:
    """An endpoint's type hash as rosbag2 writes it (``RIHS01_<hex>``; '' if unknown)."""
    h = getattr(info, 'topic_type_hash', None)
    if h is None:
        return ''
    if isinstance(h, dict):
        v, val = h.get('version', 1), h.get('value', b'')
        return f'RIHS{int(v):02d}_' + bytes(val).hex() if val else ''
    return str(h)
