"""What a real-time loop publishes, taken out of its period: a bounded ring per topic and
per consumer (the DDS publisher; the run's recorder, :meth:`Outbox.tap`), a
:class:`PublisherThread` per topic that publishes its ring without the GIL, losses counted
(:meth:`Outbox.counts`). Why and what is recorded: docs/real-drive.md, "How the composed
loop runs".

Ordering: the producer writes the slot, then (from Python, after the kernel returned)
the head; the consumer reads the head, then the slots below it. The recorder's tap is
read under the GIL (its hand-over is a full memory barrier); the publisher loop reads
the head after a syscall and relies on x86-64 keeping stores in order (a weakly ordered
CPU would need a release fence in :meth:`Ring.put`). The consumer's tail is written only
by the consumer; a stale tail read by the producer only makes a ring look fuller.

Struct layout (ROS 2 Jazzy headers, as in im_tuner.record.take):
``rcl_serialized_message_t`` = {uint8* buffer; size_t length; size_t capacity;
rcutils_allocator_t (5 pointers)}: rcl only reads buffer and length for a publish.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import llvmlite.binding as llb
import numba
import numpy as np
import rclpy.impl.implementation_singleton  # noqa: F401  (loads librcl into the process)
from numba import types


def loaded_library(name: str) -> str:
    """Path of a shared library already mapped into this process (by rclpy)."""
    with open('/proc/self/maps', encoding='ascii', errors='replace') as f:
        for line in f:
            path = line.rstrip().split(' ')[-1]
            if path.endswith('/' + name):
                return path
    raise RuntimeError(f'{name} is not loaded in this process (is rclpy installed?)')


llb.load_library_permanently(loaded_library('librcl.so'))

# Pointers are passed as 64-bit integers: same registers in the x86-64 and AArch64 ABIs.
_publish = types.ExternalFunction(
    'rcl_publish_serialized_message',
    types.int32(types.uint64, types.uint64, types.uint64),
)

_usleep = types.ExternalFunction('usleep', types.int32(types.uint32))

# ring control words
R_HEAD = 0  #: messages written (producer)
R_TAIL = 1  #: messages consumed (consumer)
R_LOST = 2  #: messages dropped: the ring was full (producer)
R_FAILED = 3  #: messages rcl refused to publish (consumer; DDS rings only)
R_TOO_BIG = 4  #: messages larger than a slot (producer; counted in lost too)
R_SIZE = 5

#: default ring capacity [messages]: 2 s of a 5 kHz topic
DEFAULT_CAPACITY = 10_000


@numba.njit(cache=True)
def put_slot(buf: np.ndarray, lens: np.ndarray, stamps: np.ndarray, ctrl: np.ndarray,
         src: np.ndarray, stamp: int) -> bool:  # fmt: skip
    """Copy ``src`` (uint8) into the next slot; False (and counted) when full or too big.
    The head is advanced by the caller, after this returns (module docstring)."""
    cap = buf.shape[0]
    h = ctrl[R_HEAD]
    n = src.shape[0]
    if n > buf.shape[1]:
        ctrl[R_LOST] += 1
        ctrl[R_TOO_BIG] += 1
        return False
    if h - ctrl[R_TAIL] >= cap:
        ctrl[R_LOST] += 1
        return False
    i = h % cap
    buf[i, :n] = src
    lens[i] = n
    stamps[i] = stamp
    return True


@numba.njit(cache=True, nogil=True)
def _publish_ring(
    pub: int, buf: np.ndarray, lens: np.ndarray, ctrl: np.ndarray, head: int, ser: np.ndarray
) -> int:
    """Publish the slots [tail, head) on the rcl publisher at address ``pub``, without
    the GIL. Returns how many were handed to rcl (refused ones counted ``failed``)."""
    cap = buf.shape[0]
    t = ctrl[R_TAIL]
    done = 0
    base = np.uint64(buf.ctypes.data)
    stride = np.uint64(buf.shape[1])
    ser_p = np.uint64(ser.ctypes.data)
    while t < head:
        i = t % cap
        ser[0] = base + np.uint64(i) * stride
        ser[1] = np.uint64(lens[i])
        ser[2] = np.uint64(lens[i])
        if _publish(np.uint64(pub), ser_p, np.uint64(0)) != 0:
            ctrl[R_FAILED] += 1
        else:
            done += 1
        t += 1
        ctrl[R_TAIL] = t  # the slot is free from here on
    return done


@numba.njit(cache=True, nogil=True)
def _publisher_loop(
    pub: int,
    buf: np.ndarray,
    lens: np.ndarray,
    ctrl: np.ndarray,
    ser: np.ndarray,
    stop: np.ndarray,
    period_us: int,
) -> int:
    """A publisher thread's whole life, without the GIL: publish what the ring holds,
    sleep ``period_us``, until ``stop[0]`` is set (then publish what is left, if
    ``stop[0]`` is 1, and return how many were published). The head is read after a
    syscall (the sleep; ordering: module docstring)."""
    total = 0
    while True:
        s = stop[0]
        head = ctrl[R_HEAD]
        if head > ctrl[R_TAIL] and s != 2:
            total += _publish_ring(pub, buf, lens, ctrl, head, ser)
        if s != 0:
            return total
        _usleep(np.uint32(period_us))


class Ring:
    """A single-producer single-consumer ring of messages of at most ``slot`` bytes."""

    def __init__(self, slot: int, capacity: int) -> None:
        if slot < 1 or capacity < 1:
            raise ValueError(f'slot and capacity must be >= 1, got {slot}, {capacity}')
        self.buf = np.zeros((capacity, slot), np.uint8)
        self.lens = np.zeros(capacity, np.int64)
        self.stamps = np.zeros(capacity, np.int64)  #: wall time [ns] of each put
        self.ctrl = np.zeros(R_SIZE, np.int64)
        for a in (self.buf, self.lens, self.stamps):
            a.fill(1)  # touch every page now: no page fault in a period (first lap)
            a.fill(0)

    def put(self, src: np.ndarray, stamp: int) -> bool:
        if put_slot(self.buf, self.lens, self.stamps, self.ctrl, src, stamp):
            self.ctrl[R_HEAD] += 1  # after the bytes (module docstring)
            return True
        return False

    @property
    def pending(self) -> int:
        return int(self.ctrl[R_HEAD] - self.ctrl[R_TAIL])


class Channel:
    """One topic of the outbox: its rcl publisher and its rings (DDS, and the tap)."""

    def __init__(
        self, topic: str, type_name: str, publisher: Any, slot: int, capacity: int
    ) -> None:
        self.topic = topic
        self.type_name = type_name  #: 'pkg/msg/Type'
        self.publisher = publisher  #: the rclpy Publisher (graph identity, QoS)
        self.address = int(publisher.handle.pointer)  #: its rcl_publisher_t
        self.slot = slot
        self.capacity = capacity
        self.dds = Ring(slot, capacity)
        self.tap: Ring | None = None  #: the recorder's ring (Outbox.tap)
        self.put_count = 0

    def put(self, src: np.ndarray) -> None:
        """Hand a message (uint8 CDR bytes) over: never blocks; a full ring counts it lost."""
        stamp = time.time_ns()
        self.put_count += 1
        self.dds.put(src, stamp)
        if self.tap is not None:
            self.tap.put(src, stamp)


class Outbox:
    """The channels of a loop's publishers (module docstring).

    ``add(publisher, type_name, slot)`` makes a channel; :meth:`emit` is the drop-in for a
    node's ``publish_lossless(pub, msg)``: bytes, a uint8 array, a ``Float64ArrayWire`` or
    a message object (serialised here) -- a publisher without a channel is published as
    before (None: the caller does it)."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY) -> None:
        self.capacity = int(capacity)
        self.channels: list[Channel] = []
        self._by_pub: dict[int, Channel] = {}
        # compile (or load) the kernels now, never in a period: a put into a scratch ring
        # and a publish of nothing (head == tail: rcl is not called)
        scratch = Ring(8, 4)
        scratch.put(np.zeros(4, np.uint8), 0)  # a wire's bytes
        scratch.put(np.frombuffer(bytes(4), np.uint8), 0)  # serialize_message's (read-only)
        scratch.ctrl[R_TAIL] = scratch.ctrl[R_HEAD]  # nothing to publish: rcl is not called
        _publisher_loop(
            0,
            scratch.buf,
            scratch.lens,
            scratch.ctrl,
            np.zeros(8, np.uint64),
            np.ones(1, np.int64),
            0,
        )

    def add(self, publisher: Any, type_name: str, slot: int, capacity: int = 0) -> Channel:
        ch = Channel(publisher.topic_name, type_name, publisher, slot, capacity or self.capacity)
        self.channels.append(ch)
        self._by_pub[id(publisher)] = ch
        return ch

    def channel(self, publisher: Any) -> Channel | None:
        return self._by_pub.get(id(publisher))

    def tap(self, factor: int = 5) -> dict[str, Channel]:
        """Give every channel a second ring, for the run's recorder (before any put),
        ``factor`` times the DDS ring: the bag must outlast a serving thread held off."""
        for ch in self.channels:
            if ch.tap is None:
                ch.tap = Ring(ch.slot, ch.capacity * factor)
        return {ch.topic: ch for ch in self.channels}

    def emit(self, publisher: Any, msg: Any) -> bool:
        """Put ``msg`` on ``publisher``'s channel; False when it has none."""
        ch = self._by_pub.get(id(publisher))
        if ch is None:
            return False
        raw = getattr(msg, 'raw', None)
        if raw is not None:  # a Float64ArrayWire: its bytes, no copy
            ch.put(raw)
        elif isinstance(msg, bytes | bytearray):
            ch.put(np.frombuffer(msg, np.uint8))
        else:
            from rclpy.serialization import serialize_message

            ch.put(np.frombuffer(serialize_message(msg), np.uint8))
        return True

    def pending(self) -> int:
        return sum(ch.dds.pending for ch in self.channels)

    def counts(self) -> dict[str, dict[str, int]]:
        """Per topic: messages put, published to DDS, lost (a full ring: DDS side and
        recorder side), refused by rcl, too big for a slot."""
        out = {}
        for ch in self.channels:
            d = ch.dds.ctrl
            row = {
                'put': ch.put_count,
                'published': int(d[R_TAIL] - d[R_FAILED]),
                'lost_dds': int(d[R_LOST]),  # the ring was full
                'publish_failed': int(d[R_FAILED]),
                'too_big': int(d[R_TOO_BIG]),
            }
            if ch.tap is not None:
                row['lost_recorder'] = int(ch.tap.ctrl[R_LOST])
            out[ch.topic] = row
        return out

    def lost_by_topic(self) -> dict[str, int]:
        """Per topic, messages that did not reach DDS or the recorder (0 normally)."""
        return {
            topic: r['lost_dds'] + r['publish_failed'] + r.get('lost_recorder', 0)
            for topic, r in self.counts().items()
        }

    def lost(self) -> int:
        """Messages that did not reach DDS or the recorder (0 in normal operation)."""
        return sum(self.lost_by_topic().values())


class PublisherThread:
    """The non-real-time side of one :class:`Channel`: a thread that spends its whole life
    in :func:`_publisher_loop` (no GIL), publishing the channel's DDS ring every
    ``period`` s. One per topic (:meth:`per_channel`): a writer that a reader keeps
    blocked (Fast DDS waits up to its max blocking time for room) holds back its own
    topic only -- the experiment results the tuner waits for go on."""

    def __init__(self, channel: Channel, period: float = 0.005) -> None:
        self.channel = channel
        self.period = float(period)
        self._ser = np.zeros(8, np.uint64)
        #: 0 run, 1 publish what is left and end, 2 end now (the GIL-free loop's flag)
        self._stop = np.zeros(1, np.int64)
        self.published = 0
        self.error: BaseException | None = None
        self._thread = threading.Thread(
            target=self._run, name=f'outbox {channel.topic}', daemon=True
        )
        self._thread.start()

    @classmethod
    def per_channel(cls, outbox: Outbox, period: float = 0.005) -> list[PublisherThread]:
        """One publisher thread for each channel of ``outbox``."""
        return [cls(ch, period) for ch in outbox.channels]

    def pending(self) -> int:
        return self.channel.dds.pending

    def _run(self) -> None:
        ch = self.channel
        r = ch.dds
        try:
            self.published += _publisher_loop(
                ch.address, r.buf, r.lens, r.ctrl, self._ser, self._stop, int(self.period * 1e6)
            )
        except BaseException as exc:
            self.error = exc

    def stop(self, timeout: float = 2.0) -> None:
        """Publish what is left (bounded by ``timeout``) and end the thread."""
        deadline = time.monotonic() + timeout
        while self.pending() and time.monotonic() < deadline and self.error is None:
            time.sleep(0.001)
        self._stop[0] = 1 if not self.pending() else 2
        self._thread.join(timeout)
