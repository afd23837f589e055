"""A chunked MCAP writer for rosbag2 bags, fast enough for 5 kHz traffic (docs/recorder.md).

The ``mcap`` library's ``Writer.add_message`` is one Python call per message; here the open
chunk is a numpy buffer that a numba kernel (:mod:`im_tuner.record.take`) fills with Message
records straight from the DDS reader, and Python runs once per chunk (compress, index,
write). The layout is rosbag2's MCAP storage's: Schema and Channel records outside chunks
as soon as a topic is added, Metadata records, each chunk followed by its Message Index
records and handed to the OS (after SIGKILL, :func:`im_tuner.record.repair.repair_bag`
rewrites the summary). A chunk is closed at ``chunk_size`` bytes, before a message that
would make it span more than ``max_span`` of log time, or when the caller flushes it. With
``background=True`` every file operation runs in order on one worker thread (zstd/lz4 and
file writes release the GIL); the chunk bytes are copied out first. No rclpy here."""

from __future__ import annotations

import contextlib
import fcntl
import os
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numba
import numpy as np
from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, Header, Metadata, Schema

from .mcap_encode import (
    chunk_head,
    encode,
    file_end,
    indexed_chunk,
)
from .mcap_format import COMPRESSIONS, MAGIC, MESSAGE_HEADER_BYTES

# Columns of the chunk state vector shared with the numba kernels.
ST_POS = 0  #: bytes used in the chunk buffer
ST_COUNT = 1  #: Message records in the chunk (rows used in the index)
ST_TMIN = 2  #: smallest log_time in the chunk [ns]
ST_TMAX = 3  #: largest log_time in the chunk [ns]
ST_SIZE = 4
_OP_MESSAGE = int(Opcode.MESSAGE)  # (a plain int in the numba kernels)


class McapWriteError(Exception):
    """The bag could not be written (path, permission, a closed writer)."""


@numba.njit(cache=True, inline='always')
def put_header(
    buf: np.ndarray,
    idx: np.ndarray,
    st: np.ndarray,
    channel_id: int,
    sequence: int,
    log_time: int,
    publish_time: int,
    n: int,
    max_span_ns: int,
) -> int:
    """Open a Message record of ``n`` data bytes at the end of the open chunk: write its
    31-byte header (little endian), index it, advance the chunk state; the offset in
    ``buf`` its data go to. -1 (nothing written) when it does not fit, or when the chunk
    would then span more than ``max_span_ns`` of log time (0: no limit; an empty chunk
    takes any message).

    ``buf`` is the uint8 chunk buffer, ``idx`` the int64 index rows (channel_id, log_time
    [ns], offset [bytes]), ``st`` the chunk state vector (``ST_*``); see :class:`ChunkState`.
    The one writer of a Message record: :meth:`McapWriter.add_message` and the take
    kernels (:mod:`im_tuner.record.take`) copy the data."""
    pos, k = st[ST_POS], st[ST_COUNT]
    if pos + MESSAGE_HEADER_BYTES + n > buf.shape[0] or k >= idx.shape[0]:
        return -1
    limited = max_span_ns > 0 and k > 0
    if limited and (log_time - st[ST_TMIN] > max_span_ns or st[ST_TMAX] - log_time > max_span_ns):
        return -1
    buf[pos] = _OP_MESSAGE
    length = 22 + n
    for b in range(8):
        buf[pos + 1 + b] = (length >> (8 * b)) & 0xFF
    buf[pos + 9] = channel_id & 0xFF
    buf[pos + 10] = (channel_id >> 8) & 0xFF
    for b in range(4):
        buf[pos + 11 + b] = (sequence >> (8 * b)) & 0xFF
    for b in range(8):
        buf[pos + 15 + b] = (log_time >> (8 * b)) & 0xFF
        buf[pos + 23 + b] = (publish_time >> (8 * b)) & 0xFF
    idx[k, 0] = channel_id
    idx[k, 1] = log_time
    idx[k, 2] = pos
    if k == 0 or log_time < st[ST_TMIN]:
        st[ST_TMIN] = log_time
    if k == 0 or log_time > st[ST_TMAX]:
        st[ST_TMAX] = log_time
    st[ST_COUNT] = k + 1
    st[ST_POS] = pos + MESSAGE_HEADER_BYTES + n
    return pos + MESSAGE_HEADER_BYTES


@dataclass
class ChunkState:
    """The open chunk: record bytes and an index row (channel, log_time, offset) each."""

    buf: np.ndarray
    idx: np.ndarray
    st: np.ndarray = field(default_factory=lambda: np.zeros(ST_SIZE, np.int64))

    @classmethod
    def create(cls, chunk_size: int) -> ChunkState:
        # Headroom so that a chunk is closed by size, not by a message that does not fit.
        return cls(
            np.zeros(chunk_size + (64 << 10), np.uint8),
            np.zeros((max(1024, chunk_size // 32), 3), np.int64),
        )

    @property
    def used(self) -> int:
        return int(self.st[ST_POS])

    @property
    def count(self) -> int:
        return int(self.st[ST_COUNT])

    @property
    def first_log_time(self) -> int:
        """Smallest log time in the chunk [ns] (meaningless when it is empty)."""
        return int(self.st[ST_TMIN])

    def grow(self, need_bytes: int) -> None:
        """Make room for a record of ``need_bytes`` (the chunk must be empty)."""
        assert self.count == 0
        if need_bytes > self.buf.shape[0]:
            self.buf = np.zeros(need_bytes + (64 << 10), np.uint8)


class McapWriter:
    """Writes one MCAP file. Not thread-safe; one writer per file.

    ``compression`` is ``'none'``, ``'zstd'`` or ``'lz4'`` (per chunk).
    """

    def __init__(
        self,
        path: Path,
        *,
        compression: str = 'zstd',
        chunk_size: int = 1 << 20,
        library: str = 'im_tuner',
        profile: str = 'ros2',
        background: bool = False,
        max_span: float = 0.0,
    ) -> None:
        """``max_span`` [s]: most log time one chunk may span (0: no limit); a message
        that would stretch the open chunk beyond it closes the chunk first."""
        if compression not in COMPRESSIONS:
            raise McapWriteError(
                f'compression must be one of {", ".join(COMPRESSIONS)}, got {compression!r}'
            )
        self.path = Path(path)
        self.compression = compression
        self.chunk_size = int(chunk_size)
        self.max_span_ns = round(max_span * 1e9)
        self._compress = _compressor(compression)
        try:
            # 'xb': never overwrite an existing file.
            self._f: BinaryIO | None = open(self.path, 'xb')  # noqa: SIM115
        except OSError as exc:
            raise McapWriteError(f'cannot create {self.path}: {exc.strerror}') from None
        # held until the file is closed or this process ends: `recorder --repair` and
        # replay tell a bag being recorded from a killed recorder's (rundir.writer_of);
        # a file system without locks (ENOLCK) records all the same, unguarded
        with contextlib.suppress(OSError):
            fcntl.flock(self._f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        self._pos = 0
        self.chunk = ChunkState.create(self.chunk_size)
        self.schemas: dict[int, tuple[str, str, bytes]] = {}
        self.channels: dict[int, tuple[str, int, str, dict[str, str]]] = {}
        self.chunks: list[ChunkIndex] = []
        self.metadata_index: list[tuple[int, int, str]] = []
        self.channel_counts: dict[int, int] = {}
        self.message_count = 0
        self.t_start: int | None = None
        self.t_end: int | None = None
        #: called with the chunk buffer and the index rows of the Message records it got
        #: since the last call (:meth:`observe`): the live view (``record.live``)
        self.observer: Callable[[np.ndarray, np.ndarray], None] | None = None
        self._observed = 0  #: index rows of the open chunk handed to the observer
        self._pool = ThreadPoolExecutor(1, 'mcap_writer') if background else None
        #: background writes not yet seen finished, oldest first (their errors are
        #: raised at the next submit or at close)
        self.pending: deque[Future] = deque()
        self._write(MAGIC + encode(Header(profile, library)))
        self.flush()

    # -- low level ---------------------------------------------------------------------
    def _write(self, b: bytes) -> int:
        if self._f is None:
            raise McapWriteError(f'{self.path}: writer is closed')
        at = self._pos
        self._f.write(b)
        self._pos += len(b)
        return at

    def flush(self) -> None:
        """Hand what is written to the OS (survives SIGKILL of this process)."""
        if self._f is not None:
            self._f.flush()

    def _submit(self, job) -> None:
        """Run a file operation now, or in order on the worker thread (background)."""
        if self._pool is None:
            job()
            return
        # The worker runs the jobs in order, so finished futures are at the front. "done"
        # is read once per look and only a done future is asked for its exception: a write
        # may finish at any instant on the worker thread (a future seen running stays and
        # is looked at again at the next submit or at close).
        while self.pending and self.pending[0].done():
            exc = self.pending.popleft().exception()
            if exc is not None:
                raise McapWriteError(f'{self.path}: background write failed: {exc!r}')
        self.pending.append(self._pool.submit(job))

    def _drain_pool(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
            errors = [f.exception() for f in self.pending if f.exception()]
            self.pending.clear()
            if errors:
                raise McapWriteError(f'{self.path}: background write failed: {errors[0]!r}')

    @property
    def closed(self) -> bool:
        return self._f is None

    # -- data section ------------------------------------------------------------------
    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        sid = len(self.schemas) + 1
        self.schemas[sid] = (name, encoding, data)
        rec = encode(Schema(sid, data, encoding, name))
        self._submit(lambda: self._write(rec))
        return sid

    def add_channel(
        self,
        topic: str,
        schema_id: int,
        message_encoding: str,
        metadata: dict[str, str] | None = None,
    ) -> int:
        cid = len(self.channels) + 1
        if cid > 0xFFFF:
            raise McapWriteError('more than 65535 channels')
        meta = dict(sorted((metadata or {}).items()))
        self.channels[cid] = (topic, schema_id, message_encoding, meta)
        self.channel_counts[cid] = 0
        rec = encode(Channel(cid, topic, message_encoding, meta, schema_id))
        self._submit(lambda: self._write(rec))
        return cid

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A Metadata record (name + string map), written at once, indexed in the summary."""
        rec = encode(Metadata(name, dict(sorted(data.items()))))

        def job() -> None:
            self.metadata_index.append((self._write(rec), len(rec), name))

        self._submit(job)

    def add_message(
        self, channel_id: int, sequence: int, log_time: int, publish_time: int, data: bytes
    ) -> None:
        """Slow path (one Python call per message) for low-rate messages and tests."""
        n = len(data)

        def put() -> int:
            ch = self.chunk
            seq = sequence & 0xFFFFFFFF
            return put_header(
                ch.buf, ch.idx, ch.st, channel_id, seq, log_time, publish_time, n, self.max_span_ns
            )

        at = put()
        if at < 0:
            self.flush_chunk()
            self.chunk.grow(MESSAGE_HEADER_BYTES + n)
            at = put()
            assert at >= 0
        self.chunk.buf[at : at + n] = np.frombuffer(data, np.uint8)
        if self.chunk.used >= self.chunk_size:
            self.flush_chunk()

    def observe(self) -> None:
        """Hand the Message records the open chunk got since the last call to the
        observer (every record reaches it once, in order: :meth:`flush_chunk` calls this
        first)."""
        ch = self.chunk
        n = ch.count
        if self.observer is not None and n > self._observed:
            self.observer(ch.buf, ch.idx[self._observed : n])
        self._observed = n

    def flush_chunk(self) -> int:
        """Close the open chunk: compress, write it and its message indexes, flush.

        Returns the number of messages in it. With ``background``, the bytes are copied
        out and written by the worker thread; the chunk buffer is free again at once."""
        self.observe()
        self._observed = 0
        ch = self.chunk
        n = ch.count
        if n == 0:
            return 0
        if self._f is None:
            raise McapWriteError(f'{self.path}: writer is closed')
        raw = ch.buf[: ch.used].tobytes()
        idx = ch.idx[:n].copy()
        t0, t1 = int(ch.st[ST_TMIN]), int(ch.st[ST_TMAX])
        ch.st[:] = 0
        for cid, k in zip(*np.unique(idx[:, 0], return_counts=True), strict=True):
            self.channel_counts[int(cid)] = self.channel_counts.get(int(cid), 0) + int(k)
        self.message_count += n
        self.t_start = t0 if self.t_start is None else min(self.t_start, t0)
        self.t_end = t1 if self.t_end is None else max(self.t_end, t1)
        self._submit(lambda: self._write_chunk(raw, idx, t0, t1))
        return n

    def _write_chunk(self, raw: bytes, idx: np.ndarray, t0: int, t1: int) -> None:
        payload = self._compress(raw)
        comp = '' if self.compression == 'none' else self.compression
        head = chunk_head(t0, t1, raw, comp, len(payload))
        sizes = (len(payload), len(raw))
        self.chunks.append(indexed_chunk(self._write, (head, payload), idx, t0, t1, comp, sizes))
        self.flush()

    # -- finishing ---------------------------------------------------------------------
    def close(self) -> None:
        """Flush the open chunk, write DataEnd, the summary and the footer; close."""
        if self._f is None:
            return
        self.flush_chunk()
        self._drain_pool()
        schemas = [encode(Schema(sid, d, enc, n)) for sid, (n, enc, d) in self.schemas.items()]
        channels = [
            encode(Channel(cid, topic, enc, meta, sid))
            for cid, (topic, sid, enc, meta) in self.channels.items()
        ]
        self._write(
            file_end(
                self._pos,
                schemas=schemas,
                channels=channels,
                metadata_index=self.metadata_index,
                chunks=self.chunks,
                counts=self.channel_counts,
                time_range=(self.t_start or 0, self.t_end or 0),
            )
        )
        f, self._f = self._f, None
        f.flush()
        os.fsync(f.fileno())
        f.close()

    def abandon(self) -> None:
        """Close the file as it is (no summary): what a crash leaves, for tests."""
        with contextlib.suppress(McapWriteError):
            self._drain_pool()
        if self._f is not None:
            self._f.close()
            self._f = None


def _compressor(name: str):
    if name == 'zstd':
        import zstandard

        z = zstandard.ZstdCompressor(level=1)
        return z.compress
    if name == 'lz4':
        import lz4.frame

        return lambda b: lz4.frame.compress(b, compression_level=0)
    return lambda b: b
