"""MCAP records read back: the walk over records, a cursor over a record body, chunk
decompression, and the Schema/Channel definitions -- what the fast reader and the repair
both parse (the MCAP
specification's little-endian layouts; constants in ``writer``)."""

from __future__ import annotations

import mmap
import struct
import zlib

import numpy as np
from mcap.opcode import Opcode

_OP_LEN = struct.Struct('<BQ')  # a record's opcode and body length


class Cursor:
    """Reads little-endian fields from a record body; raises ValueError past its end."""

    def __init__(self, b: bytes, p: int = 0) -> None:
        self.b, self.p = b, p

    def u(self, fmt: str) -> tuple:
        v = struct.unpack_from('<' + fmt, self.b, self.p)
        self.p += struct.calcsize('<' + fmt)
        return v

    def raw(self, n: int) -> bytes:
        if self.p + n > len(self.b):
            raise ValueError('field past the end of its record')
        self.p += n
        return self.b[self.p - n : self.p]

    def s(self) -> str:
        return self.raw(self.u('I')[0]).decode('utf-8')

    def map(self) -> dict[str, str]:
        (n,) = self.u('I')
        end = self.p + n
        out = {}
        while self.p < end:
            k = self.s()
            out[k] = self.s()
        if self.p != end:
            raise ValueError('bad map length')
        return out


class ChunkDamage(ValueError):
    """A whole Chunk record whose records do not decompress, or fail its size or CRC."""


def chunk_records(comp: str, data: bytes, usize: int, crc: int) -> bytes:
    """A chunk's decompressed records, checked against its header's size and CRC (MCAP
    ``uncompressed_crc``; 0: the writer computed none); :class:`ChunkDamage` saying what
    is wrong otherwise (its bytes were changed)."""
    try:
        if comp == 'zstd':
            import zstandard

            raw = zstandard.ZstdDecompressor().decompress(data, max_output_size=usize)
        elif comp == 'lz4':
            import lz4.frame

            raw = lz4.frame.decompress(data)
        elif comp == '':
            raw = data
        else:
            raise ValueError(f'unknown compression {comp!r}')
    except Exception as exc:  # zstd/lz4 raise their own types on corrupt data
        raise ChunkDamage(f'does not decompress: {exc}') from None
    if len(raw) != usize:
        raise ChunkDamage(f'{len(raw)} bytes of records where its header states {usize}')
    got = zlib.crc32(raw)
    if crc and got != crc:
        raise ChunkDamage(f'CRC 0x{crc:08x} stored, 0x{got:08x} computed from its records')
    return raw


def parse_definition(op: int, rec: bytes, schemas: dict, channels: dict) -> None:
    """A Schema or Channel record into ``schemas``/``channels`` (the first one of an id wins)."""
    c = Cursor(rec, 9)
    if op == Opcode.SCHEMA:
        (sid,) = c.u('H')
        name, _enc = c.s(), c.s()
        c.raw(c.u('I')[0])
        schemas.setdefault(sid, (name, rec))
    else:
        cid, sid = c.u('HH')
        topic, _enc = c.s(), c.s()
        channels.setdefault(cid, (topic, sid, c.map(), rec))


def walk(
    buf: mmap.mmap | np.ndarray, start: int, end: int, stop_op: int
) -> tuple[list[tuple[int, int, int]], int]:
    """The records of ``buf[start:end]`` (up to and including one of opcode ``stop_op``; -1:
    none) before the first incomplete one: (op, body offset, body length) each, and where
    the walk stopped."""
    view = buf.data if isinstance(buf, np.ndarray) else buf  # uint8: one byte per index
    out = []
    p = start
    while p + 9 <= end:
        op, ln = _OP_LEN.unpack_from(view, p)
        if op == 0 or p + 9 + ln > end:
            break
        out.append((op, p + 9, ln))
        p += 9 + ln
        if op == stop_op:
            break
    return out, p
