"""MCAP v0 records spelled as bytes (https://mcap.dev/spec), pure (no numba, no rclpy): the
``mcap`` library's records through :func:`encode`, and what it spells one Python call at a
time or not at all: a chunk's head and Message Index records (numpy), the Chunk Index, and
the summary section with its offsets and footer. The writer (:mod:`im_tuner.record.writer`)
and the repair (:mod:`im_tuner.record.repair`) both end a file with
:func:`file_end`, so a repaired file ends exactly as a recorded one."""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable

import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    ChunkIndex,
    DataEnd,
    McapRecord,
    MetadataIndex,
    Statistics,
    SummaryOffset,
)

from .mcap_format import MAGIC


def encode(*records: McapRecord) -> bytes:
    """The bytes of ``records``, one after the other (a map's pairs in its dict's order)."""
    out = RecordBuilder()
    for r in records:
        r.write(out)
    return out.end()


def chunk_head(start: int, end: int, records: bytes, compression: str, size: int) -> bytes:
    """A Chunk record up to its ``size`` bytes of (compressed) ``records``, which follow it."""
    comp = compression.encode()
    body = struct.pack('<QQQII', start, end, len(records), zlib.crc32(records), len(comp)) + comp
    body += struct.pack('<Q', size)
    return struct.pack('<BQ', Opcode.CHUNK, len(body) + size) + body


def indexed_chunk(
    put: Callable[[bytes], int],
    parts: tuple[bytes, ...],
    idx: np.ndarray,
    start: int,
    end: int,
    compression: str,
    sizes: tuple[int, int],
) -> ChunkIndex:
    """Write a Chunk record (``parts``: its bytes, in order) and the Message Index records of
    its messages ``idx`` (int64 rows: channel id, log time [ns], offset; a record per
    channel, entries sorted by (log time, offset)) through ``put`` (bytes -> the offset
    written at); its Chunk Index record for the summary (``sizes``: of its records
    compressed and uncompressed)."""
    at = put(parts[0])
    for part in parts[1:]:
        put(part)
    sidx = idx[np.lexsort((idx[:, 2], idx[:, 1], idx[:, 0]))]
    cids, starts = np.unique(sidx[:, 0], return_index=True)
    ends = [*starts[1:].tolist(), len(sidx)]
    index = []
    for cid, a, b in zip(cids.tolist(), starts.tolist(), ends, strict=True):
        entries = np.ascontiguousarray(sidx[a:b, 1:3]).astype('<u8').tobytes()
        head = struct.pack('<BQHI', Opcode.MESSAGE_INDEX, 6 + len(entries), cid, len(entries))
        index.append((cid, head + entries))
    return ChunkIndex(
        message_start_time=start,
        message_end_time=end,
        chunk_start_offset=at,
        chunk_length=sum(map(len, parts)),
        message_index_offsets={cid: put(rec) for cid, rec in index},  # (by channel id)
        message_index_length=sum(len(rec) for _cid, rec in index),
        compression=compression,
        compressed_size=sizes[0],
        uncompressed_size=sizes[1],
    )


def file_end(
    data_end: int,
    *,
    schemas: list[bytes],
    channels: list[bytes],
    metadata_index: list[tuple[int, int, str]],
    chunks: list[ChunkIndex],
    counts: dict[int, int],
    time_range: tuple[int, int],
    attachment_index: list[bytes] | None = None,
) -> bytes:
    """What ends a file whose data section ends at byte ``data_end``: DataEnd, the summary
    (its groups of records in this order, empty ones left out; the Statistics of these
    records, ``counts`` messages per channel and the messages' ``time_range`` [ns]; a
    Metadata Index per (offset, length, name), a Chunk Index per chunk), a Summary Offset
    per group, the Footer (with the summary's CRC-32) and the closing magic."""
    head = encode(DataEnd(0))
    summary_start = data_end + len(head)
    statistics = Statistics(
        message_count=sum(counts.values()),
        schema_count=len(schemas),
        channel_count=len(channels),
        attachment_count=len(attachment_index or []),
        metadata_count=len(metadata_index),
        chunk_count=len(chunks),
        message_start_time=time_range[0],
        message_end_time=time_range[1],
        channel_message_counts=dict(sorted(counts.items())),
    )
    groups = (
        (Opcode.SCHEMA, schemas),
        (Opcode.CHANNEL, channels),
        (Opcode.STATISTICS, [encode(statistics)]),
        (Opcode.METADATA_INDEX, [encode(MetadataIndex(*m)) for m in metadata_index]),
        (Opcode.ATTACHMENT_INDEX, attachment_index or []),
        (Opcode.CHUNK_INDEX, [encode(c) for c in chunks]),
    )
    out = bytearray()
    offsets: list[tuple[int, int, int]] = []
    for op, records in groups:
        if records:
            at = summary_start + len(out)
            out.extend(b''.join(records))
            offsets.append((op, at, summary_start + len(out) - at))
    offsets_start = summary_start + len(out)
    out.extend(encode(*(SummaryOffset(*o) for o in offsets)))
    footer_head = struct.pack(
        '<BQQQ', Opcode.FOOTER, 20, summary_start if offsets else 0, offsets_start if offsets else 0
    )
    crc = zlib.crc32(bytes(out) + footer_head)
    return head + bytes(out) + footer_head + struct.pack('<I', crc) + MAGIC
