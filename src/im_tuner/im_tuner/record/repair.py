"""Repair a bag whose recorder died: rebuild the MCAP summary, index, footer and metadata.yaml
(docs/recorder.md, "Crash safety").

:func:`repair_bag` scans the file up to the first incomplete or invalid record (a damaged
chunk is named, left out, and the scan goes on), then writes ``<file>.repairing``: the
Header, every definition, Metadata and Attachment record, every complete chunk verbatim with
fresh Message Index records (loose messages packed into new uncompressed chunks), and the
summary and footer as ``McapWriter.close`` writes them; only once that file is complete and
synced does it replace the original. A file that already ends in a valid footer is left
untouched (one with a damaged chunk is refused). Either way ``metadata.yaml`` is rewritten
from what the scan found. No rclpy here."""

from __future__ import annotations

import mmap
import os
import shutil
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np
import yaml
from mcap.opcode import Opcode
from mcap.records import AttachmentIndex

from ..rundir import writer_of
from .mcap_encode import (
    chunk_head,
    encode,
    file_end,
    indexed_chunk,
)
from .mcap_format import MAGIC
from .metadata import TopicRecord, bag_metadata, read_metadata_yaml, write_metadata_yaml
from .reader import BagReadError, find_mcap
from .records import ChunkDamage, Cursor, chunk_records, parse_definition, walk

#: Messages found outside chunks are packed into new chunks of at most this many bytes.
LOOSE_CHUNK_BYTES = 1 << 20
_FOOTER_BYTES = 29  # opcode, length, summary_start, summary_offset_start, summary_crc


class RepairError(Exception):
    """The bag cannot be repaired (not a directory, no .mcap file, not MCAP, no header)."""


@dataclass
class ScannedChunk:
    """A complete chunk of the scanned file (or a run of loose messages to chunk)."""

    offset: int  # of the Chunk record in the scanned file
    length: int  # record bytes (opcode + length + body)
    start: int
    end: int
    compression: str
    compressed_size: int
    uncompressed_size: int
    index: np.ndarray  # int64 rows (channel_id, log_time, offset in the records)
    #: Message records found outside chunks: (offset, length, channel_id, log_time) each.
    loose: list[tuple[int, int, int, int]] | None = None


@dataclass
class McapScan:
    """What :func:`scan_mcap` found in the data section, in file order."""

    path: Path
    size: int
    header: bytes  # the Header record
    schemas: dict[int, tuple[str, bytes]] = field(default_factory=dict)  # id: name, record
    # id: topic, schema id, metadata, record
    channels: dict[int, tuple[str, int, dict[str, str], bytes]] = field(default_factory=dict)
    metadata: list[tuple[int, int, str]] = field(default_factory=list)  # offset, length, name
    # offset, length, log_time, create_time, data size, name, media type
    attachments: list[tuple[int, int, int, int, int, str, str]] = field(default_factory=list)
    chunks: list[ScannedChunk] = field(default_factory=list)
    #: complete Chunk records that fail their CRC or do not decompress (bytes changed):
    #: (number among the file's Chunk records from 1, offset, what is wrong)
    damaged: list[tuple[int, int, str]] = field(default_factory=list)
    data_end: int = 0  # end of the last complete record of the data section
    ended: bool = False  # the scan reached DataEnd (or the Footer)
    complete: bool = False  # the file ends in a valid footer and magic

    @property
    def messages(self) -> int:
        return sum(len(c.index) for c in self.chunks)

    def channel_counts(self) -> dict[int, int]:
        counts = dict.fromkeys(self.channels, 0)
        for c in self.chunks:
            for cid, n in zip(*np.unique(c.index[:, 0], return_counts=True), strict=True):
                counts[int(cid)] = counts.get(int(cid), 0) + int(n)
        return counts

    def time_range(self) -> tuple[int, int]:
        times = [c.index[:, 1] for c in self.chunks if len(c.index)]
        return (
            (int(min(t.min() for t in times)), int(max(t.max() for t in times)))
            if times
            else (0, 0)
        )


@dataclass
class RepairReport:
    """What :func:`repair_bag` found and did."""

    bag: Path
    file: str
    was_complete: bool
    messages: int
    chunks: int
    dropped_bytes: int
    topics: dict[str, int]
    #: damaged chunks left out of the rewritten file: (number, offset, what is wrong)
    damaged: list[tuple[int, int, str]] = field(default_factory=list)

    def summary(self) -> str:
        if self.was_complete:
            head = [
                f'bag {self.bag}: {self.file} is complete (valid footer); left untouched, '
                'metadata.yaml rewritten',
                f'  {self.messages} messages in {self.chunks} chunks on {len(self.topics)} topics',
            ]
        else:
            head = [
                f'bag {self.bag}: {self.file} had no valid summary/footer; rewrote it and '
                'metadata.yaml',
                '  ' + _repair_line(self.messages, self.chunks, self.dropped_bytes, self.damaged),
            ]
        return '\n'.join(head + [f'  {t}: {n}' for t, n in sorted(self.topics.items())])


def _repair_line(
    messages: int, chunks: int, dropped: int, damaged: list[tuple[int, int, str]]
) -> str:
    left_out = ''.join(
        f'; left out damaged chunk {number} at byte {at} ({why})' for number, at, why in damaged
    )
    return (
        f'recovered {messages} messages in {chunks} chunks; discarded {dropped} bytes '
        f'after the last complete chunk{left_out}'
    )


def _parse_chunk(body: bytes, scan: McapScan, at: int) -> ScannedChunk:
    """Validate a Chunk record body and index its messages (registers its schemas/channels)."""
    c = Cursor(body)
    start, end, usize, crc = c.u('QQQI')
    comp = c.s()
    (clen,) = c.u('Q')
    if c.p + clen != len(body):
        raise ValueError('chunk records length mismatch')
    raw = chunk_records(comp, body[c.p :], usize, crc)
    schemas: dict[int, tuple[str, bytes]] = {}
    channels: dict[int, tuple[str, int, dict[str, str], bytes]] = {}
    rows: list[tuple[int, int, int]] = []
    found, stop = walk(np.frombuffer(raw, np.uint8), 0, len(raw), -1)
    if stop != len(raw):
        raise ValueError('record past the end of its chunk')
    for op, p, n in found:
        if op == Opcode.MESSAGE:
            cid, _seq, log_time = struct.unpack_from('<HIQ', raw, p)
            if n < 22 or (cid not in scan.channels and cid not in channels):
                raise ValueError('bad message record')
            rows.append((cid, log_time, p - 9))
        elif op in (Opcode.SCHEMA, Opcode.CHANNEL):
            parse_definition(op, raw[p - 9 : p + n], schemas, channels)
    for sid, schema in schemas.items():
        scan.schemas.setdefault(sid, schema)
    for cid, channel in channels.items():
        scan.channels.setdefault(cid, channel)
    return ScannedChunk(
        at, 9 + len(body), start, end, comp, clen, usize, np.array(rows, np.int64).reshape(-1, 3)
    )


def _has_footer(f: BinaryIO, size: int) -> bool:
    """The file ends in Footer + magic, and the summary CRC (if any) matches."""
    if size < 8 + 9 + _FOOTER_BYTES + 8:
        return False
    f.seek(size - 8 - _FOOTER_BYTES)
    tail = f.read(_FOOTER_BYTES + 8)
    if tail[-8:] != MAGIC or tail[:9] != struct.pack('<BQ', Opcode.FOOTER, 20):
        return False
    summary_start, _offsets, crc = struct.unpack_from('<QQI', tail, 9)
    if not crc:
        return True
    begin = summary_start or size - 8 - _FOOTER_BYTES
    if not 8 < begin <= size - 8 - _FOOTER_BYTES:
        return False
    f.seek(begin)
    return zlib.crc32(f.read(size - 8 - 4 - begin)) == crc


def bag_is_closed(bag_dir: Path) -> bool:
    """The recorder finished ``bag_dir``: its metadata.yaml says ``closed`` (written after
    the file) and its .mcap file ends in a valid footer. Cheap: the file's tail only."""
    try:
        meta = read_metadata_yaml(bag_dir)
        if (meta.get('custom_data') or {}).get('im_tuner.state') != 'closed':
            return False
        path = find_mcap(Path(bag_dir))
        with open(path, 'rb') as f:
            return _has_footer(f, os.fstat(f.fileno()).st_size)
    except (OSError, BagReadError, yaml.YAMLError, KeyError, TypeError, AttributeError):
        return False


def scan_mcap(path: Path) -> McapScan:
    """Read the data section of ``path`` up to DataEnd or the first incomplete/invalid record."""
    path = Path(path)
    try:
        f = open(path, 'rb')  # noqa: SIM115
    except OSError as exc:
        raise RepairError(f'{path}: cannot read it ({exc.strerror})') from None
    with f:
        size = os.fstat(f.fileno()).st_size
        if f.read(8) != MAGIC:
            raise RepairError(f'{path}: not an MCAP file (bad magic)')
        head = f.read(9)
        op, n = struct.unpack('<BQ', head) if len(head) == 9 else (0, 0)
        if op != Opcode.HEADER or 17 + n > size:
            raise RepairError(f'{path}: no complete MCAP header')
        scan = McapScan(path, size, head + f.read(n))
        scan.data_end = 17 + n
        number = 0  # Chunk records seen
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            for op, at, ln in walk(mm, 17 + n, size, Opcode.DATA_END)[0]:
                pos, rec = at - 9, bytes(mm[at - 9 : at + ln])
                try:
                    if op == Opcode.CHUNK:
                        number += 1
                        try:
                            scan.chunks.append(_parse_chunk(rec[9:], scan, pos))
                        except ChunkDamage as exc:  # a whole record: its bytes were changed
                            scan.damaged.append((number, pos, str(exc)))
                    elif op in (Opcode.SCHEMA, Opcode.CHANNEL):
                        parse_definition(op, rec, scan.schemas, scan.channels)
                    elif op == Opcode.METADATA:
                        c = Cursor(rec, 9)
                        scan.metadata.append((pos, len(rec), c.s()))
                        c.map()
                    elif op == Opcode.ATTACHMENT:
                        c = Cursor(rec, 9)
                        t_log, t_create = c.u('QQ')
                        name, media = c.s(), c.s()
                        (dlen,) = c.u('Q')
                        c.raw(dlen + 4)
                        scan.attachments.append((pos, len(rec), t_log, t_create, dlen, name, media))
                    elif op == Opcode.MESSAGE:
                        _add_loose(scan, rec, pos)
                except (struct.error, ValueError):
                    break
                if op in (Opcode.DATA_END, Opcode.FOOTER):
                    scan.ended = True
                    break
                scan.data_end = at + ln
        scan.complete = _has_footer(f, size)
    for ch in scan.chunks:  # index the runs of loose messages as the chunks they will become
        if ch.loose:
            offsets = np.cumsum(np.array([0] + [n for _a, n, _c, _t in ch.loose[:-1]], np.int64))
            ch.index = np.array(
                [(cid, t, o) for (_a, _n, cid, t), o in zip(ch.loose, offsets, strict=True)],
                np.int64,
            )
    return scan


def _add_loose(scan: McapScan, rec: bytes, at: int) -> None:
    """A Message record outside chunks: append it to a run that will become a new chunk."""
    cid, _seq, log_time, _pub = struct.unpack_from('<HIQQ', rec, 9)
    if len(rec) < 31 or cid not in scan.channels:
        raise ValueError('bad message record')
    last = scan.chunks[-1] if scan.chunks else None
    if last is None or last.loose is None or last.uncompressed_size >= LOOSE_CHUNK_BYTES:
        last = ScannedChunk(at, 0, log_time, log_time, '', 0, 0, np.zeros((0, 3), np.int64), [])
        scan.chunks.append(last)
    assert last.loose is not None
    last.loose.append((at, len(rec), cid, log_time))
    last.start, last.end = min(last.start, log_time), max(last.end, log_time)
    last.uncompressed_size += len(rec)
    last.compressed_size = last.uncompressed_size


def _write_repaired(scan: McapScan, dst: BinaryIO) -> None:
    """Write the repaired file (see the module doc) to ``dst``."""
    pos = 0

    def put(b: bytes) -> int:
        nonlocal pos
        dst.write(b)
        pos += len(b)
        return pos - len(b)

    put(MAGIC + scan.header)
    for _name, rec in scan.schemas.values():
        put(rec)
    for *_x, rec in scan.channels.values():
        put(rec)
    with open(scan.path, 'rb') as src:

        def read(at: int, n: int) -> bytes:
            src.seek(at)
            return src.read(n)

        def copy(at: int, n: int) -> int:
            return put(read(at, n))

        meta_index = [(copy(at, n), n, name) for at, n, name in scan.metadata]
        att_index = [(copy(a[0], a[1]), *a[1:]) for a in scan.attachments]
        infos = []
        for ch in scan.chunks:
            if ch.loose is None:
                rec = read(ch.offset, ch.length)
            else:
                recs = b''.join(read(o, n) for o, n, _c, _t in ch.loose)
                rec = chunk_head(ch.start, ch.end, recs, '', len(recs)) + recs
            sizes = (ch.compressed_size, ch.uncompressed_size)
            infos.append(
                indexed_chunk(put, (rec,), ch.index, ch.start, ch.end, ch.compression, sizes)
            )
    put(
        file_end(
            pos,
            schemas=[rec for _n, rec in scan.schemas.values()],
            channels=[c[3] for c in scan.channels.values()],
            metadata_index=meta_index,
            chunks=infos,
            counts=scan.channel_counts(),
            time_range=scan.time_range(),
            attachment_index=[encode(AttachmentIndex(*a)) for a in att_index],
        )
    )


def repair_bag(bag_dir: Path) -> RepairReport:
    """Repair the bag directory ``bag_dir`` (see the module doc); returns what was done."""
    bag_dir = Path(bag_dir)
    if not bag_dir.is_dir():
        raise RepairError(f'{bag_dir}: not a directory')
    try:
        path = find_mcap(bag_dir)
    except BagReadError as exc:
        raise RepairError(str(exc)) from None
    writer = writer_of(path)
    if writer is not None:
        raise RepairError(
            f'{bag_dir}: being recorded now by {writer}; left untouched (a recorder closes '
            'its bag when it stops: repair only a bag whose recorder was killed)'
        )
    scan = scan_mcap(path)
    if scan.complete and scan.damaged:
        number, at, why = scan.damaged[0]
        more = f' (and {len(scan.damaged) - 1} more chunks)' if len(scan.damaged) > 1 else ''
        raise RepairError(
            f'{path}: chunk {number} at byte {at} is damaged ({why}){more}: its messages '
            'cannot be trusted and no repair recovers them; left untouched'
        )
    if scan.complete and not scan.ended:
        raise RepairError(
            f'{path}: has a valid footer but its data section is damaged at '
            f'byte {scan.data_end}; left untouched'
        )
    dropped = 0 if scan.complete else scan.size - scan.data_end
    if not scan.complete:
        tmp = path.with_name(path.name + '.repairing')
        try:
            with open(tmp, 'wb') as f:
                _write_repaired(scan, f)
                f.flush()
                os.fsync(f.fileno())
            shutil.copymode(path, tmp)
            os.replace(tmp, path)
        except BaseException as exc:
            tmp.unlink(missing_ok=True)
            if isinstance(exc, OSError):
                raise RepairError(
                    f'{path}: cannot write the repaired file ({exc}); the original is unchanged'
                ) from exc
            raise
        dfd = os.open(bag_dir, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    counts = scan.channel_counts()
    topics: dict[str, TopicRecord] = {}
    for cid, (topic, sid, meta, _rec) in scan.channels.items():
        t = topics.setdefault(
            topic,
            TopicRecord(
                topic,
                scan.schemas.get(sid, ('', b''))[0],
                0,
                _qos(meta.get('offered_qos_profiles', '')),
                meta.get('topic_type_hash', ''),
            ),
        )
        t.message_count += counts.get(cid, 0)
    try:
        custom = dict(read_metadata_yaml(bag_dir).get('custom_data') or {})
    except (OSError, yaml.YAMLError, KeyError, TypeError, AttributeError):
        custom = {}
    custom['im_tuner.state'] = 'closed' if scan.complete else 'repaired'
    custom['im_tuner.repair'] = (
        'complete file (valid footer), left untouched; '
        f'{scan.messages} messages in {len(scan.chunks)} chunks'
        if scan.complete
        else _repair_line(scan.messages, len(scan.chunks), dropped, scan.damaged)
    )
    t0, t1 = scan.time_range()
    try:
        write_metadata_yaml(
            bag_dir,
            bag_metadata([(path.name, t0, t1, scan.messages)], list(topics.values()), custom),
        )
    except OSError as exc:
        raise RepairError(
            f'{bag_dir}: cannot write metadata.yaml ({exc}); '
            f'{path.name} is {"intact" if scan.complete else "repaired"}'
        ) from exc
    return RepairReport(
        bag_dir,
        path.name,
        scan.complete,
        scan.messages,
        len(scan.chunks),
        dropped,
        {t.name: t.message_count for t in topics.values()},
        scan.damaged,
    )


def _qos(text: str) -> list[dict]:
    try:
        profiles = yaml.safe_load(text) if text else []
    except yaml.YAMLError:
        return []
    return profiles if isinstance(profiles, list) else []
