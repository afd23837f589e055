"""MCAP v0 records spelled as bytes (https://mcap.dev/spec), pure (no numba, no rclpy):
strings, maps, records, the Message Index, Chunk Index and Statistics records, and the
summary section with its offsets and footer. The writer (:mod:`im_tuner.record.writer`)
and the repair (:mod:`im_tuner.record.repair`) both end a file with
:func:`summary_and_footer`, so a repaired file ends exactly as a recorded one."""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np

from .mcap_format import (
    MAGIC,
    OP_ATTACHMENT_INDEX,
    OP_CHANNEL,
    OP_CHUNK_INDEX,
    OP_FOOTER,
    OP_MESSAGE_INDEX,
    OP_METADATA_INDEX,
    OP_SCHEMA,
    OP_STATISTICS,
    OP_SUMMARY_OFFSET,
)

_U64 = struct.Struct('<Q')


def prefixed(b: bytes) -> bytes:
    """MCAP bytes: u32 length, the bytes."""
    return struct.pack('<I', len(b)) + b


def string(s: str) -> bytes:
    """An MCAP string: u32 byte length, UTF-8 bytes."""
    return prefixed(s.encode('utf-8'))


def string_map(d: dict[str, str]) -> bytes:
    """An MCAP map<string, string>: u32 byte length, the pairs sorted by key."""
    return prefixed(b''.join(string(k) + string(v) for k, v in sorted(d.items())))


def record(op: int, body: bytes) -> bytes:
    """A record: opcode u8, body length u64, body."""
    return struct.pack('<BQ', op, len(body)) + body


def schema_record(sid: int, name: str, encoding: str, data: bytes) -> bytes:
    """A Schema record (id ``sid``, the schema text ``data``)."""
    return record(
        OP_SCHEMA, struct.pack('<H', sid) + string(name) + string(encoding) + prefixed(data)
    )


def channel_record(cid: int, sid: int, topic: str, encoding: str, meta: dict[str, str]) -> bytes:
    """A Channel record (id ``cid`` on schema ``sid``, message ``encoding``)."""
    return record(
        OP_CHANNEL,
        struct.pack('<HH', cid, sid) + string(topic) + string(encoding) + string_map(meta),
    )


def message_index_records(idx: np.ndarray) -> list[tuple[int, bytes]]:
    """The Message Index records of a chunk whose messages are ``idx`` (int64 rows: channel
    id, log time [ns], offset): (channel id, record) each, entries sorted by (log time,
    offset)."""
    sidx = idx[np.lexsort((idx[:, 2], idx[:, 1], idx[:, 0]))]
    cids, starts = np.unique(sidx[:, 0], return_index=True)
    ends = [*starts[1:].tolist(), len(sidx)]
    out = []
    for cid, a, b in zip(cids.tolist(), starts.tolist(), ends, strict=True):
        entries = np.ascontiguousarray(sidx[a:b, 1:3]).astype('<u8').tobytes()
        out.append((cid, record(OP_MESSAGE_INDEX, struct.pack('<HI', cid, len(entries)) + entries)))
    return out


def metadata_index_record(at: int, length: int, name: str) -> bytes:
    """A Metadata Index record: the Metadata record at byte ``at``, ``length`` bytes long."""
    return record(OP_METADATA_INDEX, struct.pack('<QQ', at, length) + string(name))


@dataclass
class ChunkInfo:
    """What the summary needs to know of a written chunk (byte offsets, times [ns])."""

    start: int
    end: int
    offset: int
    length: int
    index_offsets: dict[int, int]
    index_length: int
    compression: str
    compressed_size: int
    uncompressed_size: int


def chunk_index_record(c: ChunkInfo) -> bytes:
    """The Chunk Index record of a written chunk."""
    offs = b''.join(struct.pack('<HQ', k, v) for k, v in sorted(c.index_offsets.items()))
    return record(
        OP_CHUNK_INDEX,
        struct.pack('<QQQQ', c.start, c.end, c.offset, c.length)
        + struct.pack('<I', len(offs))
        + offs
        + _U64.pack(c.index_length)
        + string(c.compression)
        + struct.pack('<QQ', c.compressed_size, c.uncompressed_size),
    )


def statistics_record(
    messages: int,
    n_schemas: int,
    n_channels: int,
    n_attachments: int,
    n_metadata: int,
    n_chunks: int,
    time_range: tuple[int, int],
    channel_counts: dict[int, int],
) -> bytes:
    """The Statistics record: counts, the message time range [ns], messages per channel."""
    counts = b''.join(struct.pack('<HQ', c, k) for c, k in sorted(channel_counts.items()))
    return record(
        OP_STATISTICS,
        struct.pack(
            '<QHIIIIQQ',
            messages,
            n_schemas,
            n_channels,
            n_attachments,
            n_metadata,
            n_chunks,
            *time_range,
        )
        + struct.pack('<I', len(counts))
        + counts,
    )


def summary_and_footer(
    summary_start: int,
    *,
    schemas: list[bytes],
    channels: list[bytes],
    statistics: bytes,
    metadata_index: list[bytes],
    chunk_index: list[bytes],
    attachment_index: list[bytes] | None = None,
) -> bytes:
    """What follows DataEnd at byte ``summary_start``: the summary (its groups of records
    in this order, empty ones left out), a Summary Offset per group, the Footer (with the
    summary's CRC-32) and the closing magic."""
    groups = (
        (OP_SCHEMA, schemas),
        (OP_CHANNEL, channels),
        (OP_STATISTICS, [statistics]),
        (OP_METADATA_INDEX, metadata_index),
        (OP_ATTACHMENT_INDEX, attachment_index or []),
        (OP_CHUNK_INDEX, chunk_index),
    )
    out = bytearray()
    offsets: list[tuple[int, int, int]] = []
    for op, records in groups:
        if records:
            at = summary_start + len(out)
            out.extend(b''.join(records))
            offsets.append((op, at, summary_start + len(out) - at))
    offsets_start = summary_start + len(out)
    for op, at, n in offsets:
        out.extend(record(OP_SUMMARY_OFFSET, struct.pack('<BQQ', op, at, n)))
    footer_head = struct.pack(
        '<BQQQ', OP_FOOTER, 20, summary_start if offsets else 0, offsets_start if offsets else 0
    )
    crc = zlib.crc32(bytes(out) + footer_head)
    return bytes(out) + footer_head + struct.pack('<I', crc) + MAGIC
