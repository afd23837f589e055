"""Take serialised messages from rcl subscriptions in a numba loop, straight into a chunk.

The kernel calls rcl's ``rcl_take_serialized_message`` on the ``rcl_subscription_t`` that
rclpy created (``sub.handle.pointer``) and copies the CDR bytes into the open MCAP chunk
(:mod:`im_tuner.record.writer`) as a Message record: no Python object per message, and the
publisher's GID, which rclpy's message info hides, for the per-publisher (channel, GID)
first and last ``publication_sequence_number``, count and gaps (docs/recorder.md, "Nothing
lost, and the proof"). The subscriptions stay owned by the rclpy node.

Struct layouts (ROS 2 Jazzy headers; test/test_recorder.py checks the kernel's bytes and
sequence numbers against rclpy's own take):
``rcl_serialized_message_t`` = ``rcutils_uint8_array_t`` {uint8* buffer; size_t length;
size_t capacity; rcutils_allocator_t allocator (5 pointers)} = 8 x 64-bit words;
``rmw_message_info_t`` {int64 source_timestamp; int64 received_timestamp; uint64
publication_sequence_number; uint64 reception_sequence_number; rmw_gid_t {const char*
implementation_identifier; uint8 data[16]}; bool from_intra_process} = 8 words."""

from __future__ import annotations

import ctypes

import llvmlite.binding as llb
import numba
import numpy as np
import rclpy.impl.implementation_singleton  # noqa: F401  (loads librcl into the process)
from numba import types

from im_drive_sim.outbox import R_TAIL, loaded_library

from .writer import put_header

_RCL = loaded_library('librcl.so')
_RCUTILS = loaded_library('librcutils.so')
llb.load_library_permanently(_RCL)

# Pointers are passed as 64-bit integers: same registers in the x86-64 and AArch64 ABIs.
_take = types.ExternalFunction(
    'rcl_take_serialized_message',
    types.int32(types.uint64, types.uint64, types.uint64, types.uint64),
)
_memcpy = types.ExternalFunction('memcpy', types.uint64(types.uint64, types.uint64, types.uint64))

RCL_RET_OK = 0
RCL_RET_SUBSCRIPTION_TAKE_FAILED = 401

# drain() results
DONE = 0  #: every subscription is empty
FULL = 1  #: the chunk is full; the message taken last is pending in ``ser``/``info``
PUBS_FULL = 2  #: the publisher table is full (grow it and call again)
ERROR = 4  #: rcl returned an error (code in ``ctrl[C_ERROR]``)

# ctrl vector
C_PENDING = 0  #: 1: a taken message waits in ser/info to be written
C_PENDING_SUB = 1  #: subscription row of the pending message
C_NPUBS = 2  #: rows used in the publisher table
C_ERROR = 3  #: last rcl error code
#: most log time [ns] one chunk may span (0: no limit): a message that would stretch the
#: open chunk beyond it closes the chunk first (FULL), so that a backlog taken late (a
#: recorder polled after seconds of start-up) still makes chunks of at most this span
C_MAX_SPAN_NS = 4
C_SIZE = 5

# publisher table columns
P_CHANNEL = 0
P_GID0 = 1
P_GID1 = 2
P_FIRST = 3  #: first publication sequence number seen
P_LAST = 4  #: highest publication sequence number seen
P_COUNT = 5  #: messages recorded
P_GAPS = 6  #: sequence numbers skipped (messages lost between publisher and recorder)
P_SIZE = 7

# message info words
I_SOURCE_TS = 0
I_RECEIVED_TS = 1
I_PUB_SEQ = 2
I_GID0 = 5
I_GID1 = 6


@numba.njit(cache=True)
def _track(
    pubs: np.ndarray, ctrl: np.ndarray, channel: int, gid0: int, gid1: int, seq: int
) -> bool:
    n = ctrl[C_NPUBS]
    for r in range(n):
        if pubs[r, P_GID0] == gid0 and pubs[r, P_GID1] == gid1 and pubs[r, P_CHANNEL] == channel:
            last = pubs[r, P_LAST]
            if seq > last:  # (one not above the last came late: not a gap)
                pubs[r, P_GAPS] += seq - last - 1
                pubs[r, P_LAST] = seq
            pubs[r, P_COUNT] += 1
            return True
    if n >= pubs.shape[0]:
        return False
    pubs[n, P_CHANNEL] = channel
    pubs[n, P_GID0] = gid0
    pubs[n, P_GID1] = gid1
    pubs[n, P_FIRST] = seq
    pubs[n, P_LAST] = seq
    pubs[n, P_COUNT] = 1
    pubs[n, P_GAPS] = 0
    ctrl[C_NPUBS] = n + 1
    return True


@numba.njit(cache=True)
def _place(
    ser: np.ndarray,
    info: np.ndarray,
    channel: int,
    buf: np.ndarray,
    idx: np.ndarray,
    st: np.ndarray,
    ctrl: np.ndarray,
) -> bool:
    n = np.int64(ser[1])
    at = put_header(
        buf,
        idx,
        st,
        channel,
        np.int64(info[I_PUB_SEQ] & 0xFFFFFFFF),
        np.int64(info[I_RECEIVED_TS]),
        np.int64(info[I_SOURCE_TS]),
        n,
        ctrl[C_MAX_SPAN_NS],
    )
    if at < 0:
        return False
    _memcpy(np.uint64(buf.ctypes.data + at), ser[0], np.uint64(n))
    return True


@numba.njit(cache=True, nogil=True)
def drain(
    subs: np.ndarray,
    chans: np.ndarray,
    ser: np.ndarray,
    info: np.ndarray,
    buf: np.ndarray,
    idx: np.ndarray,
    st: np.ndarray,
    pubs: np.ndarray,
    ctrl: np.ndarray,
) -> tuple[int, int]:
    """Take every available message of every subscription into the chunk.

    ``subs`` rcl_subscription_t addresses (uint64), ``chans`` their MCAP channel ids.
    Returns (result code, messages taken). On FULL the caller closes the chunk (growing
    the buffer if the pending message is larger than it) and calls again: the pending
    message is written first, so nothing taken is ever dropped.
    """
    taken = 0
    ser_p = np.uint64(ser.ctypes.data)
    info_p = np.uint64(info.ctypes.data)
    if ctrl[C_PENDING]:
        if not _place(ser, info, chans[ctrl[C_PENDING_SUB]], buf, idx, st, ctrl):
            return FULL, 0
        ctrl[C_PENDING] = 0
    for i in range(subs.shape[0]):
        if subs[i] == 0:
            continue
        while True:
            r = _take(subs[i], ser_p, info_p, np.uint64(0))
            if r == RCL_RET_SUBSCRIPTION_TAKE_FAILED:
                break
            if r != RCL_RET_OK:
                ctrl[C_ERROR] = r
                return ERROR, taken
            taken += 1
            ok = _track(
                pubs,
                ctrl,
                chans[i],
                np.int64(info[I_GID0]),
                np.int64(info[I_GID1]),
                np.int64(info[I_PUB_SEQ]),
            )
            if not _place(ser, info, chans[i], buf, idx, st, ctrl):
                ctrl[C_PENDING] = 1
                ctrl[C_PENDING_SUB] = i
                return FULL, taken
            if not ok:
                return PUBS_FULL, taken
    return DONE, taken


class _Allocator(ctypes.Structure):
    _fields_ = [
        ('allocate', ctypes.c_void_p),
        ('deallocate', ctypes.c_void_p),
        ('reallocate', ctypes.c_void_p),
        ('zero_allocate', ctypes.c_void_p),
        ('state', ctypes.c_void_p),
    ]


class TakeBuffers:
    """The rcl serialized-message buffer and message-info struct the kernel reuses.

    The serialized buffer is allocated by rcutils (rmw grows it with the same allocator
    when a message is larger) and freed by :meth:`close`.
    """

    def __init__(self, capacity: int = 64 << 10) -> None:
        self._rcutils = ctypes.CDLL(_RCUTILS)
        self._rcutils.rcutils_get_default_allocator.restype = _Allocator
        self._rcutils.rcutils_uint8_array_init.argtypes = [
            ctypes.c_void_p,
            ctypes.c_size_t,
            ctypes.c_void_p,
        ]
        self._rcutils.rcutils_uint8_array_fini.argtypes = [ctypes.c_void_p]
        self._alloc = self._rcutils.rcutils_get_default_allocator()
        self.ser = np.zeros(8, np.uint64)
        self.info = np.zeros(8, np.uint64)
        self._ser_addr = int(self.ser.ctypes.data)
        ret = self._rcutils.rcutils_uint8_array_init(
            self._ser_addr, capacity, ctypes.addressof(self._alloc)
        )
        if ret != 0:
            raise RuntimeError(f'rcutils_uint8_array_init failed ({ret})')
        self._open = True

    @property
    def pending_size(self) -> int:
        """Bytes of the message currently in the serialized buffer."""
        return int(self.ser[1])

    def close(self) -> None:
        if self._open:
            self._open = False
            self._rcutils.rcutils_uint8_array_fini(self._ser_addr)

    def __del__(self) -> None:
        self.close()


def new_publisher_table(rows: int = 256) -> np.ndarray:
    return np.zeros((rows, P_SIZE), np.int64)


def new_ctrl() -> np.ndarray:
    return np.zeros(C_SIZE, np.int64)


@numba.njit(cache=True, nogil=True)
def drain_ring(
    rbuf: np.ndarray,
    rlens: np.ndarray,
    rstamps: np.ndarray,
    rctrl: np.ndarray,
    head: int,
    channel: int,
    buf: np.ndarray,
    idx: np.ndarray,
    st: np.ndarray,
    max_span_ns: int,
) -> int:
    """Copy the messages [tail, head) of an ``im_drive_sim.outbox.Ring`` (the loop's tap
    for the recorder) into the chunk as Message records: log and publish time = the wall
    time the loop handed each over, sequence = its index in the ring's stream. Stops
    early when the chunk is full, or when the next message would make it span more than
    ``max_span_ns`` of log time (0: no limit) -- the caller closes it and calls again.
    Returns how many were copied; the ring's tail advances past each."""
    cap = rbuf.shape[0]
    t = rctrl[R_TAIL]
    t_start = t
    while t < head:
        i = t % cap
        n = rlens[i]
        stamp = rstamps[i]
        at = put_header(buf, idx, st, channel, t & 0xFFFFFFFF, stamp, stamp, n, max_span_ns)
        if at < 0:
            break
        buf[at : at + n] = rbuf[i, :n]
        t += 1
        rctrl[R_TAIL] = t
    return t - t_start
