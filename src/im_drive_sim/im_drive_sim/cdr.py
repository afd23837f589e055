"""Pre-serialised ``std_msgs/Float64MultiArray`` for the 5 kHz topics.

Publishing CDR bytes skips rclpy's per-call message conversion; the wire format is
identical, so subscribers and recorders see ordinary messages. Layout (XCDR1, little
endian) of a message with an empty ``layout.dim``, ``data_offset = 0`` and n values::

    [0:4]   encapsulation header 00 01 00 00 (CDR_LE)
    [4:8]   layout.dim length = 0
    [8:12]  layout.data_offset = 0
    [12:16] data length = n
    [16:20] padding (float64 aligned to 8 within the body)
    [20:]   n little-endian float64 values
"""

from __future__ import annotations

from typing import Any

import numpy as np

_HEADER = bytes([0, 1, 0, 0])
_DATA_OFFSET = 20


class Float64ArrayWire:
    """A reusable serialised Float64MultiArray of fixed length n.

    Write the values through :attr:`values` (a float64 view of the buffer), then publish
    :meth:`payload`.
    """

    def __init__(self, n: int) -> None:
        self.n = n
        self._buf = bytearray(_DATA_OFFSET + 8 * n)
        self._buf[0:4] = _HEADER
        self._buf[12:16] = int(n).to_bytes(4, 'little')
        self.values = np.frombuffer(self._buf, dtype='<f8', count=n, offset=_DATA_OFFSET)
        #: the whole message as a uint8 view (no copy): what an ``outbox.Outbox`` takes
        self.raw = np.frombuffer(self._buf, dtype=np.uint8)

    def payload(self) -> bytes:
        """The message as CDR bytes (a copy: rclpy requires ``bytes``)."""
        return bytes(self._buf)


def parse_float64_array(raw: bytes, n: int) -> np.ndarray | None:
    """The n values of a serialised Float64MultiArray in our layout, as a read-only view.

    Returns None when ``raw`` is not exactly that layout (big-endian, a non-empty
    ``layout.dim``, another length): the caller then deserialises it the slow, general way.
    """
    if (
        len(raw) != _DATA_OFFSET + 8 * n
        or raw[0:4] != _HEADER
        or raw[4:12] != bytes(8)
        or int.from_bytes(raw[12:16], 'little') != n
    ):
        return None
    return np.frombuffer(raw, dtype='<f8', count=n, offset=_DATA_OFFSET)


def read_float64_array(raw: bytes, n: int) -> Any:
    """The values of a serialised Float64MultiArray: in our layout of n values a read-only
    view (:func:`parse_float64_array`), in another deserialised the slow, general way."""
    data = parse_float64_array(raw, n)
    if data is None:
        from rclpy.serialization import deserialize_message
        from std_msgs.msg import Float64MultiArray

        data = deserialize_message(raw, Float64MultiArray).data
    return data


class PatchWire:
    """A serialised message of fixed layout whose numeric fields are patched in place.

    Built from a template serialisation in which each field to patch holds a sentinel
    value that occurs once; :meth:`field` returns a one-element numpy view at that
    sentinel's offset. Publishing :attr:`raw` (or :meth:`payload`) then costs no message
    conversion."""

    def __init__(self, template: bytes) -> None:
        self._buf = bytearray(template)
        self.raw = np.frombuffer(self._buf, dtype=np.uint8)

    def field(self, sentinel: float | int, dtype: str) -> np.ndarray:
        """The view of the one field holding ``sentinel`` (dtype '<f8', '<i4' or '<u4')."""
        needle = np.array([sentinel], dtype=dtype).tobytes()
        at = self._buf.find(needle)
        if at < 0 or self._buf.find(needle, at + 1) >= 0:
            raise ValueError(f'sentinel {sentinel!r} not found exactly once in the template')
        return np.frombuffer(self._buf, dtype=dtype, count=1, offset=at)

    def payload(self) -> bytes:
        return bytes(self._buf)


# sentinels of the templates below: values no real field of theirs holds at build time
_SEC, _NSEC = 1_234_567_891, 987_654_321
_POS, _VEL, _EFF = 1.2345678901234567e-300, 2.3456789012345678e-300, 3.4567890123456789e-300


class JointStateWire(PatchWire):
    """``sensor_msgs/JointState`` of one joint, pre-serialised: set :attr:`sec`,
    :attr:`nanosec` (the header stamp), :attr:`position`, :attr:`velocity`,
    :attr:`effort` (``[0] = value``), then publish."""

    def __init__(self, joint_name: str, frame_id: str = '') -> None:
        from rclpy.serialization import serialize_message
        from sensor_msgs.msg import JointState

        m = JointState(name=[joint_name], position=[_POS], velocity=[_VEL], effort=[_EFF])
        m.header.frame_id = frame_id
        m.header.stamp.sec, m.header.stamp.nanosec = _SEC, _NSEC
        super().__init__(serialize_message(m))
        self.sec = self.field(_SEC, '<i4')
        self.nanosec = self.field(_NSEC, '<u4')
        self.position = self.field(_POS, '<f8')
        self.velocity = self.field(_VEL, '<f8')
        self.effort = self.field(_EFF, '<f8')
        self.sec[0] = self.nanosec[0] = 0
        self.position[0] = self.velocity[0] = self.effort[0] = 0.0


class ClockWire(PatchWire):
    """``rosgraph_msgs/Clock``, pre-serialised: set :attr:`sec`, :attr:`nanosec`."""

    def __init__(self) -> None:
        from rclpy.serialization import serialize_message
        from rosgraph_msgs.msg import Clock

        m = Clock()
        m.clock.sec, m.clock.nanosec = _SEC, _NSEC
        super().__init__(serialize_message(m))
        self.sec = self.field(_SEC, '<i4')
        self.nanosec = self.field(_NSEC, '<u4')
        self.sec[0] = self.nanosec[0] = 0
