"""The record walk of a bag whose index is missing or does not match (numba: a whole
bag's records, one pass, no Python per record). Its own module so that reading an
indexed bag -- the common case -- never imports numba (half a second)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def walk(
    buf: np.ndarray,
    start: int,
    stop_op: int,
    ops: np.ndarray,
    offs: np.ndarray,
    lens: np.ndarray,
    cids: np.ndarray,
    times: np.ndarray,
) -> tuple[int, int]:
    """Walk MCAP records in ``buf[start:]``; fills the arrays (op, body offset, body length,
    channel id and log time of Message records).  Stops after a record with opcode
    ``stop_op``, at the end, or before an incomplete record.  Returns (records, end)."""
    p = start
    n = 0
    size = buf.size
    cap = ops.size
    while p + 9 <= size and n < cap:
        op = buf[p]
        ln = np.int64(0)
        for j in range(8):
            ln |= np.int64(buf[p + 1 + j]) << (8 * j)
        if op == 0 or ln < 0 or p + 9 + ln > size:
            break
        ops[n] = op
        offs[n] = p + 9
        lens[n] = ln
        if op == 5 and ln >= 22:
            cids[n] = np.int64(buf[p + 9]) | (np.int64(buf[p + 10]) << 8)
            t = np.int64(0)
            for j in range(8):
                t |= np.int64(buf[p + 15 + j]) << (8 * j)
            times[n] = t
        else:
            cids[n] = -1
            times[n] = 0
        n += 1
        p += 9 + int(ln)
        if op == stop_op:
            break
    return n, p
