"""Read a tuning run's bag fast, also one whose recorder was killed: counts and signals.

One memory-mapped, read-only pass up to DataEnd or the first incomplete record. Each chunk
is decompressed once and checked against its CRC (a damaged one is named in
``BagData.damaged`` and its messages left out); its messages are found through the
Message Index records after it, with numpy, or -- without a complete index that tiles the
chunk -- by a record walk (docs/report.md, "Speed"). Per topic: counts, first and last log
time, bytes; of the ``Float64MultiArray`` topics asked for, the rows whose first value (the
step index ``k``) lies in the given windows; the loss messages decoded. No rclpy and no ROS
message packages: the two CDR layouts needed are parsed here."""

from __future__ import annotations

import contextlib
import json
import mmap
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from mcap.opcode import Opcode

from im_controller.contract import LOSS_TOPIC

from .mcap_format import MAGIC
from .metadata import read_metadata_yaml
from .records import Cursor, chunk_records, parse_definition, walk

_MSG_HEAD = 22  # channel id u16, sequence u32, log time u64, publish time u64
_F64_HEAD = b'\x00\x01\x00\x00'  # CDR little-endian encapsulation
_F64_DATA = 20  # first double of a Float64MultiArray with an empty layout
#: a topic's rate is given from this many messages, or over this much log time [s]
RATE_MIN_MESSAGES, RATE_MIN_SPAN_S = 10, 1.0


class BagReadError(Exception):
    """The bag cannot be read at all (no .mcap file, not MCAP)."""


@dataclass
class TopicStats:
    """One topic as found in the file."""

    name: str
    type: str
    count: int = 0
    first_ns: int = 0  #: log time of the first message [ns since the epoch]
    last_ns: int = 0
    bytes: int = 0  #: serialised message data (CDR), without MCAP record headers [B]

    @property
    def rate_hz(self) -> float | None:
        """Messages per second of log time between the first and the last message; None
        for a topic too short to have a rate: fewer than RATE_MIN_MESSAGES messages within
        less than RATE_MIN_SPAN_S (two messages 1 ms apart are not a 1 kHz topic)."""
        span_s = (self.last_ns - self.first_ns) * 1e-9
        if self.count < 2 or span_s <= 0.0:
            return None
        if self.count < RATE_MIN_MESSAGES and span_s < RATE_MIN_SPAN_S:
            return None
        return (self.count - 1) / ((self.last_ns - self.first_ns) * 1e-9)


@dataclass(frozen=True)
class ChunkStats:
    """One chunk as its header says (MCAP Chunk record)."""

    start_ns: int  #: message_start_time: the smallest log time in it [ns]
    end_ns: int  #: message_end_time: the largest [ns]
    compression: str  #: '' (none), 'lz4' or 'zstd'

    @property
    def span_s(self) -> float:
        """Log time the chunk spans [s] (what ``--max-chunk-age`` bounds)."""
        return (self.end_ns - self.start_ns) * 1e-9


@dataclass(frozen=True)
class DamagedChunk:
    """A complete Chunk record whose records cannot be trusted: its CRC (the MCAP
    ``uncompressed_crc``, CRC-32 of the decompressed records) does not match, or it does
    not decompress. Its messages are left out of every count."""

    number: int  #: its place among the file's chunks, from 1
    offset: int  #: byte offset of the Chunk record in the .mcap file
    start_ns: int  #: message_start_time its header states [ns]
    end_ns: int  #: message_end_time its header states [ns]
    reason: str  #: what is wrong, e.g. 'CRC 0x1234abcd stored, 0x0badf00d computed'

    def describe(self) -> str:
        """One phrase naming the chunk: 'chunk 3 at byte 123456 (log time ...): reason'."""
        span = f'{(self.end_ns - self.start_ns) * 1e-9:.3f} s of log time from {self.start_ns} ns'
        return f'chunk {self.number} at byte {self.offset} ({span}): {self.reason}'


@dataclass
class BagData:
    """What :func:`read_bag` found."""

    path: Path  #: the bag directory
    file: Path  #: its .mcap file
    complete: bool = False  #: data section read to DataEnd
    state: str = 'unknown'  #: metadata.yaml im_tuner.state
    unread_bytes: int = 0  #: after the last complete record
    chunks: int = 0
    #: every complete chunk read, in file order
    chunk_stats: list[ChunkStats] = field(default_factory=list)
    #: complete chunks left out because their CRC or compression is wrong (bytes changed)
    damaged: list[DamagedChunk] = field(default_factory=list)
    #: the MCAP Metadata records found (name -> string map; the first of a name wins)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    topics: dict[str, TopicStats] = field(default_factory=dict)
    #: the recorder's own count per topic (recorded, published, lost, ...) when it closed
    recorder_counts: dict[str, dict[str, int]] | None = None
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    #: decoded loss messages: the key/value pairs plus 'log_time_ns', 'level', 'name'
    losses: list[dict[str, str]] = field(default_factory=list)
    #: the messages of the ``raw`` topics asked for: (log time [ns], CDR bytes), in file order
    raw: dict[str, list[tuple[int, bytes]]] = field(default_factory=dict)

    @property
    def messages(self) -> int:
        return sum(t.count for t in self.topics.values())

    @property
    def t_range_ns(self) -> tuple[int, int]:
        ts = [t for t in self.topics.values() if t.count]
        if not ts:
            return (0, 0)
        return min(t.first_ns for t in ts), max(t.last_ns for t in ts)


# ----------------------------------------------------------------------- record walk
def walk_records(
    buf: np.ndarray, start: int, stop_op: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Every record of ``buf`` from byte ``start`` (up to and including one of opcode
    ``stop_op``; -1: none), walked one by one: opcodes, body offsets and lengths, and for
    Message records channel ids and log times [ns] (-1 and 0 for the others); and where the
    walk stopped. What a chunk whose index does not tile it is read by."""
    found, end = walk(buf, start, buf.size, stop_op)
    rec = np.array(found, np.int64).reshape(-1, 3)
    ops, offs, lens = rec[:, 0].astype(np.uint8), rec[:, 1], rec[:, 2]
    msg = np.flatnonzero((ops == Opcode.MESSAGE) & (lens >= _MSG_HEAD))
    cids, times = np.full(len(rec), -1, np.int64), np.zeros(len(rec), np.int64)
    cids[msg] = buf[offs[msg]].astype(np.int64) | (buf[offs[msg] + 1].astype(np.int64) << 8)
    times[msg] = _u64_at(buf, offs[msg] + 6).astype(np.int64)
    return ops, offs, lens, cids, times, end


def _u64_at(buf: np.ndarray, at: np.ndarray) -> np.ndarray:
    """The little-endian u64 at each byte offset ``at`` of ``buf``."""
    return np.ascontiguousarray(buf[at[:, None] + np.arange(8)]).view('<u8')[:, 0]


def _indexed_messages(
    buf: np.ndarray, index: list[tuple[int, np.ndarray]], schemas: dict, channels: dict
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The Message records of a decompressed chunk ``buf`` found through its message
    indexes (channel id, entries ``[[log_time, offset], ...]``): body offsets, body
    lengths, channel ids and log times, in file order; the Schema and Channel records
    between them go into ``schemas``/``channels``. None when the index does not account
    for every record of the chunk exactly (then the chunk is walked instead)."""
    size = buf.size
    n = sum(len(e) for _c, e in index)
    cid = np.empty(n, np.int64)
    ent = np.empty((n, 2), np.uint64)
    i = 0
    for c, e in index:
        cid[i : i + len(e)] = c
        ent[i : i + len(e)] = e
        i += len(e)
    if n and int(ent[:, 1].max()) > size - 9 - _MSG_HEAD:
        return None
    order = np.argsort(ent[:, 1], kind='stable')
    cid, rec, t_idx = cid[order], ent[order, 1].astype(np.int64), ent[order, 0]
    if n:
        lens = _u64_at(buf, rec + 1)
        if (
            np.any(buf[rec] != Opcode.MESSAGE)
            or np.any(lens < _MSG_HEAD)
            or np.any(lens > (size - 9 - rec).astype(np.uint64))
        ):
            return None
        lens = lens.astype(np.int64)
        ends = rec + 9 + lens
        body_cid = buf[rec + 9].astype(np.int64) | (buf[rec + 10].astype(np.int64) << 8)
        if (
            np.any(ends[:-1] > rec[1:])  # overlapping or repeated entries
            or np.any(body_cid != cid)
            or np.any(_u64_at(buf, rec + 15) != t_idx)
        ):
            return None
        # what lies between the messages must be whole records, none of them a message
        cut = np.flatnonzero(ends[:-1] < rec[1:])
        gaps = [
            (0, int(rec[0])),
            *zip(ends[cut].tolist(), rec[cut + 1].tolist(), strict=True),
            (int(ends[-1]), size),
        ]
    else:
        lens = ends = rec
        gaps = [(0, size)]
    for a, b in gaps:
        if a == b:
            continue
        found, stop = walk(buf, a, b, -1)
        if stop != b or any(op == Opcode.MESSAGE for op, _o, _n in found):
            return None
        for op, o, ln in found:
            if op in (Opcode.SCHEMA, Opcode.CHANNEL):
                parse_definition(op, bytes(buf[o - 9 : o + ln]), schemas, channels)
    return rec + 9, lens, cid, t_idx.astype(np.int64)


# ------------------------------------------------------------------------ CDR parsing
class _Cdr:
    """Little-endian CDR reader (alignment relative to the byte after the 4-byte header)."""

    def __init__(self, b: bytes) -> None:
        if len(b) < 4 or b[0:2] != b'\x00\x01':
            raise ValueError('not little-endian CDR')
        self.b, self.p = b, 4

    def _align(self, n: int) -> None:
        self.p += (-(self.p - 4)) % n

    def u32(self, fmt: str = '<I') -> int:
        """The next 4-byte integer (``fmt`` '<i': signed)."""
        self._align(4)
        (v,) = struct.unpack_from(fmt, self.b, self.p)
        self.p += 4
        return v

    def u8(self) -> int:
        v = self.b[self.p]
        self.p += 1
        return v

    def string(self) -> str:
        n = self.u32()
        if n == 0 or self.p + n > len(self.b):
            raise ValueError('bad CDR string')
        s = self.b[self.p : self.p + n - 1].decode('utf-8')
        self.p += n
        return s

    def f64s(self) -> np.ndarray:
        n = self.u32()
        self._align(8)
        if self.p + 8 * n > len(self.b):
            raise ValueError('CDR sequence past the end')
        v = np.frombuffer(self.b, '<f8', n, self.p)
        self.p += 8 * n
        return v


def parse_float64_multiarray(data: bytes) -> np.ndarray:
    """``std_msgs/Float64MultiArray`` CDR -> its data (any layout)."""
    c = _Cdr(data)
    for _ in range(c.u32()):  # layout.dim: label, size, stride
        c.string()
        c.u32()
        c.u32()
    c.u32()  # layout.data_offset
    return c.f64s()


def parse_diagnostic_array(data: bytes) -> list[dict[str, str]]:
    """``diagnostic_msgs/DiagnosticArray`` CDR -> one dict per status: its key/value pairs
    plus 'level', 'name', 'message', 'hardware_id' and 'stamp_ns' (of the array header)."""
    c = _Cdr(data)
    sec, nsec = c.u32('<i'), c.u32()
    c.string()  # frame_id
    out = []
    for _ in range(c.u32()):
        st = {'level': str(c.u8())}
        st['name'], st['message'], st['hardware_id'] = c.string(), c.string(), c.string()
        for _ in range(c.u32()):
            k = c.string()
            st[k] = c.string()
        st['stamp_ns'] = str(sec * 1_000_000_000 + nsec)
        out.append(st)
    return out


def _f64_rows(
    buf: np.ndarray,
    offs: np.ndarray,
    lens: np.ndarray,
    windows: list[tuple[int, int]] | None = None,
) -> np.ndarray:
    """The data of the Float64MultiArray message bodies at ``offs`` whose first value lies
    in ``windows`` (None: all) as rows; all of one length.  Fast path for the project's
    layout (empty dims: the first value is read first, and only the rows kept are
    copied), a general parse otherwise."""
    if not len(offs):
        return np.zeros((0, 0))
    d0 = offs + _MSG_HEAD
    width = (int(lens[0]) - _MSG_HEAD - _F64_DATA) // 8
    fast = width >= 0 and bool(np.all(lens == lens[0]))
    if fast:
        head = buf[d0[:, None] + np.arange(16)]
        fast = bool(
            np.all(head[:, :12] == np.frombuffer(_F64_HEAD + bytes(8), np.uint8))
            and np.all(head[:, 12:16].view('<u4')[:, 0] == width)
        )
    if fast:
        if width and windows is not None:
            k = np.ascontiguousarray(buf[(d0 + _F64_DATA)[:, None] + np.arange(8)]).view('<f8')
            d0 = d0[_in_windows(k[:, 0], windows)]
        raw = buf[(d0 + _F64_DATA)[:, None] + np.arange(8 * width)]
        return np.ascontiguousarray(raw).view('<f8').reshape(len(d0), width)
    rows = [
        parse_float64_multiarray(bytes(buf[a : a + n - _MSG_HEAD]))
        for a, n in zip(d0, lens, strict=True)
    ]
    if len({len(r) for r in rows}) != 1:
        raise ValueError('messages of different lengths')
    out = np.array(rows)
    return out[_in_windows(out[:, 0], windows)] if out.size else out


def _in_windows(k: np.ndarray, windows: list[tuple[int, int]] | None) -> np.ndarray:
    if windows is None:
        return np.ones(len(k), bool)
    keep = np.zeros(len(k), bool)
    for a, b in windows:
        keep |= (k >= a) & (k < b)
    return keep


# ----------------------------------------------------------------------------- reader
def find_mcap(bag_dir: Path) -> Path:
    """The bag's one MCAP file; :class:`BagReadError` naming ``bag_dir`` when it is not a
    bag directory: missing, a file, no .mcap file, or several (a split bag is not read as
    its first file)."""
    bag_dir = Path(bag_dir)
    if not bag_dir.is_dir():
        exists = bag_dir.exists()
        raise BagReadError(f'{bag_dir}: ' + ('not a directory' if exists else 'no such directory'))
    found = sorted(p for p in bag_dir.glob('*.mcap') if p.is_file())
    if not found:
        raise BagReadError(f'{bag_dir}: not a bag (no .mcap file)')
    if len(found) > 1:
        raise BagReadError(
            f'{bag_dir}: several .mcap files ({", ".join(p.name for p in found)}): a split '
            'bag (the recorder writes one)'
        )
    return found[0]


def read_bag(
    bag_dir: Path | str,
    arrays: dict[str, list[tuple[int, int]] | None] | None = None,
    loss_topic: str = '/' + LOSS_TOPIC,
    raw: tuple[str, ...] = (),
) -> BagData:
    """Read ``bag_dir`` (see the module docstring).

    ``arrays``: topic -> windows ``[(k0, k1), ...]`` of the first value to keep (None: all
    rows) for ``Float64MultiArray`` topics.  Messages of ``loss_topic`` are decoded, those
    of the ``raw`` topics kept as they are.
    """
    bag_dir = Path(bag_dir)
    path = find_mcap(bag_dir)
    out = BagData(bag_dir, path)
    try:
        custom = read_metadata_yaml(bag_dir).get('custom_data') or {}
        out.state = custom.get('im_tuner.state', 'unknown')
        if 'im_tuner.counts' in custom:
            out.recorder_counts = json.loads(custom['im_tuner.counts'])
    except FileNotFoundError:
        out.state = 'no metadata.yaml'
    except (OSError, ValueError, KeyError, TypeError, AttributeError, yaml.YAMLError):
        out.state = 'metadata.yaml unreadable'
    arrays = arrays or {}
    schemas: dict[int, tuple[str, bytes]] = {}
    channels: dict[int, tuple[str, int, dict, bytes]] = {}
    per_chan: dict[int, list] = {}  # cid -> [count, first, last, bytes]
    rows: dict[str, list[np.ndarray]] = {t: [] for t in arrays}
    kept: dict[str, list[tuple[int, bytes]]] = {t: [] for t in (loss_topic, *raw)}
    with open(path, 'rb') as f:
        size = f.seek(0, 2)
        f.seek(0)
        if size < 8 or f.read(8) != MAGIC:
            raise BagReadError(f'{path}: not an MCAP file')
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            top, end = walk(mm, 8, size, Opcode.DATA_END)
            out.complete = bool(top) and top[-1][0] in (Opcode.DATA_END, Opcode.FOOTER)
            out.unread_bytes = 0 if out.complete else size - end
            # definitions first: a Channel record may follow a chunk holding its messages
            for op, a, n in top:
                if op in (Opcode.SCHEMA, Opcode.CHANNEL):
                    parse_definition(op, bytes(mm[a - 9 : a + n]), schemas, channels)
                elif op == Opcode.METADATA:  # (the first of a name wins; a bad one is left out)
                    with contextlib.suppress(ValueError, struct.error):
                        cur = Cursor(bytes(mm[a : a + n]))
                        name = cur.s()
                        out.metadata.setdefault(name, cur.map())
            # each chunk with the message indexes that follow it (before the next chunk)
            chunks: list[tuple[int, int, list[tuple[int, np.ndarray]]]] = []
            for op, a, n in top:
                if op == Opcode.CHUNK:
                    chunks.append((a, n, []))
                elif op == Opcode.MESSAGE_INDEX and chunks and n >= 6:
                    cid, nb = struct.unpack_from('<HI', mm, a)
                    if nb % 16 == 0 and 6 + nb <= n:
                        # a copy: no array may still point into the mmap when it closes
                        e = np.frombuffer(mm, '<u8', nb // 8, a + 6).reshape(-1, 2).copy()
                        chunks[-1][2].append((cid, e))
            for number, (a, n, index) in enumerate(chunks, 1):
                start, end, usize, crc, clen = struct.unpack_from('<QQQII', mm, a)
                try:
                    comp = mm[a + 32 : a + 32 + clen].decode()
                    p = a + 32 + clen  # the length of its records, then the records
                    (rlen,) = struct.unpack_from('<Q', mm, p)
                    if p + 8 + rlen > a + n:
                        raise ValueError('its records run past the record')
                    records = chunk_records(comp, mm[p + 8 : p + 8 + rlen], usize, crc)
                except ValueError as exc:
                    # a complete record (the walk above checked its length): bytes changed
                    out.damaged.append(DamagedChunk(number, a - 9, start, end, str(exc)))
                    continue
                out.chunks += 1
                out.chunk_stats.append(ChunkStats(start, end, comp))
                _take_chunk(
                    np.frombuffer(records, np.uint8), index, schemas, channels, per_chan, arrays,
                    rows, kept,
                )  # fmt: skip
    if out.recorder_counts is None and 'im_tuner.counts' in out.metadata:
        # no metadata.yaml (or one without them): the record the recorder wrote at close
        try:
            rec_counts = out.metadata['im_tuner.counts']
            out.recorder_counts = {k: json.loads(v) for k, v in rec_counts.items()}
        except ValueError:
            pass
    for cid, (topic, sid, _meta, _rec) in channels.items():
        c = per_chan.get(cid, [0, 0, 0, 0])
        ty = schemas.get(sid, ('?', b''))[0]
        prev = out.topics.get(topic)
        if prev is None:
            out.topics[topic] = TopicStats(topic, ty, c[0], c[1], c[2], c[3])
        elif c[0]:  # the same topic on a second channel (a second type): merge the counts
            prev.first_ns = min(prev.first_ns, c[1]) if prev.count else c[1]
            prev.last_ns = max(prev.last_ns, c[2])
            prev.count += c[0]
            prev.bytes += c[3]
    for t, parts in rows.items():
        parts = [p for p in parts if p.size]
        out.arrays[t] = np.concatenate(parts) if parts else np.zeros((0, 0))
    out.raw = {t: kept[t] for t in raw}
    for log_time, data in kept[loss_topic]:
        for st in parse_diagnostic_array(data):
            out.losses.append(st | {'log_time_ns': str(log_time)})
    return out


def _take_chunk(
    buf: np.ndarray,
    index: list[tuple[int, np.ndarray]],
    schemas: dict,
    channels: dict,
    per_chan: dict,
    arrays: dict,
    rows: dict,
    kept: dict[str, list[tuple[int, bytes]]],
) -> None:
    found = _indexed_messages(buf, index, schemas, channels) if index else None
    if found is not None:
        offs, lens, cids, times = found
    else:  # no index, or one that does not match the chunk: walk every record
        ops, offs, lens, cids, times, _end = walk_records(buf, 0, -1)
        for i in np.flatnonzero(ops != Opcode.MESSAGE):
            op = int(ops[i])
            if op in (Opcode.SCHEMA, Opcode.CHANNEL):
                a, n = int(offs[i]), int(lens[i])
                parse_definition(op, bytes(buf[a - 9 : a + n]), schemas, channels)
        is_msg = ops == Opcode.MESSAGE
        cids, times, offs, lens = cids[is_msg], times[is_msg], offs[is_msg], lens[is_msg]
    if not len(cids):
        return
    ids, counts = np.unique(cids, return_counts=True)
    for cid, n in zip(ids.tolist(), counts.tolist(), strict=True):
        sel = cids == cid
        t = times[sel]
        c = per_chan.setdefault(cid, [0, 0, 0, 0])
        c[1] = int(t.min()) if not c[0] else min(c[1], int(t.min()))
        c[2] = max(c[2], int(t.max()))
        c[0] += n
        c[3] += int(lens[sel].sum()) - _MSG_HEAD * n  # the message data, without its head
        topic = channels.get(cid, ('',))[0]
        if topic in arrays:
            rows[topic].append(_f64_rows(buf, offs[sel], lens[sel], arrays[topic]))
        elif topic in kept:
            for a, n_, lt in zip(offs[sel].tolist(), lens[sel].tolist(), t.tolist(), strict=True):
                kept[topic].append((lt, bytes(buf[a + _MSG_HEAD : a + n_])))
