"""im_tuner.record.repair: bags cut short by a crash are repaired, checked by independent readers.

Bags are written with :class:`~im_tuner.record.writer.McapWriter` (and, for files shaped
differently, with the ``mcap`` library's own writer); what comes out is read back by the
``mcap`` library (indexed and streaming) and by ``rosbags`` (its own MCAP reader and CDR
deserialiser), so an index or summary that misdescribes the data shows up as missing or
wrong messages. Payloads are real CDR: ``Float64MultiArray`` built by hand in the layout the
drive simulator publishes, ``std_msgs/String`` from rclpy's serialiser.
"""

from __future__ import annotations

import hashlib
import io
import os
import struct
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.reader import make_reader
from mcap.records import (
    Chunk as McapChunk,
    Message as McapMessage,
    MessageIndex as McapMessageIndex,
)
from mcap.stream_reader import StreamReader, get_chunk_data_stream
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import Reader as RosbagsReader, ReaderError as RosbagsReaderError
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from std_msgs.msg import String

from im_tuner.record import repair as mcap_repair
from im_tuner.record.metadata import (
    TopicRecord,
    bag_metadata,
    prepare_bag_dir,
    qos_to_dict,
    qos_yaml,
    read_metadata_yaml,
    storage_file_name,
    write_metadata_yaml,
)
from im_tuner.record.schemas import schema_text
from im_tuner.record.writer import McapWriter

sys.path.insert(0, str(Path(__file__).parent))
from test_record_reader import f64_array_cdr

RepairError = mcap_repair.RepairError
repair_bag = mcap_repair.repair_bag
scan_mcap = mcap_repair.scan_mcap

T0 = 1_700_000_000_000_000_000
ARRAY = 'std_msgs/msg/Float64MultiArray'
STRING = 'std_msgs/msg/String'
QOS = [qos_to_dict('keep_all', 0, 'reliable', 'volatile')]
TYPE_HASH = 'RIHS01_' + 'ab' * 32


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def snapshot(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())}


class Recording:
    """A bag being written as the recorder writes it; remembers what went in, in order."""

    def __init__(
        self, out: Path, compression: str = 'zstd', chunk_size: int = 4096, background: bool = False
    ) -> None:
        self.out = prepare_bag_dir(out)
        self.file = self.out / storage_file_name(self.out)
        self.w = McapWriter(
            self.file, compression=compression, chunk_size=chunk_size, background=background
        )
        self.w.add_metadata('im_tuner.run', {'command': 'test'})
        write_metadata_yaml(
            self.out,
            bag_metadata(
                [(self.file.name, 0, 0, 0)],
                [],
                {'im_tuner.state': 'recording', 'im_tuner.run_id': 'test-42'},
            ),
        )
        meta = {'offered_qos_profiles': qos_yaml(QOS), 'topic_type_hash': TYPE_HASH}
        self.ch = {
            '/drive/state': self.w.add_channel(
                '/drive/state',
                self.w.add_schema(ARRAY, 'ros2msg', schema_text(ARRAY).encode()),
                'cdr',
                meta,
            ),
            '/chatter': self.w.add_channel(
                '/chatter',
                self.w.add_schema(STRING, 'ros2msg', schema_text(STRING).encode()),
                'cdr',
                meta,
            ),
        }
        #: (topic, log_time, value) in write order; value: float64 array or str.
        self.sent: list[tuple[str, int, object]] = []

    def write(self, n: int, flush_every: int = 0) -> None:
        """``n`` messages, 4 array messages per string; a forced chunk flush every
        ``flush_every`` messages (what ``max_chunk_age`` does in the recorder)."""
        for _ in range(n):
            i = len(self.sent)
            t = T0 + i * 200_000  # 5 kHz
            if i % 5 == 4:
                topic, value = '/chatter', f'message {i}'
                data = serialize_message(String(data=value))
            else:
                topic, value = '/drive/state', np.array([i, 0.5 * i, -1.0 / (i + 1)])
                data = f64_array_cdr(value)
            self.w.add_message(self.ch[topic], i, t, t - 1000, data)
            self.sent.append((topic, t, value))
            if flush_every and (i + 1) % flush_every == 0:
                self.w.flush_chunk()

    def flushed(self, chunks: int | None = None) -> list[tuple[str, int, object]]:
        """What is in the first ``chunks`` written chunks (all when None)."""
        infos = self.w.chunks[:chunks]
        # A Message Index record is 15 bytes plus 16 per entry.
        n = sum((c.message_index_length - 15 * len(c.message_index_offsets)) // 16 for c in infos)
        return self.sent[:n]


def topic_counts(sent: list[tuple[str, int, object]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for topic, _t, _v in sent:
        out[topic] = out.get(topic, 0) + 1
    return out


def check_value(topic: str, got: object, want: object) -> None:
    if topic == '/chatter':
        assert got == want
    else:
        np.testing.assert_array_equal(got, want)


def decode_cdr(topic: str, data: bytes) -> object:
    """Our own reading of the two payload layouts (used for the mcap library's output)."""
    if topic == '/chatter':
        n = struct.unpack_from('<I', data, 4)[0]
        return data[8 : 8 + n - 1].decode()
    assert data[:4] == b'\x00\x01\x00\x00' and data[4:12] == bytes(8)
    n = struct.unpack_from('<I', data, 12)[0]
    return np.frombuffer(data, '<f8', n, 20)


def stream_messages(path: Path) -> list[int]:
    """log_time of every message the mcap StreamReader yields before the file ends/fails."""
    out = []
    with open(path, 'rb') as f:
        try:
            for r in StreamReader(f).records:
                if isinstance(r, McapMessage):
                    out.append(r.log_time)
        except EndOfFile:  # a cut file (or one without a footer) ends here
            pass
    return out


def read_with_mcap(path: Path, sent: list[tuple[str, int, object]]) -> None:
    """The mcap library's indexed reader returns exactly ``sent``, CRCs and summary valid."""
    with open(path, 'rb') as f:
        reader = make_reader(f, validate_crcs=True)
        got = [
            (ch.topic, m.log_time, m.publish_time, m.sequence, decode_cdr(ch.topic, m.data))
            for _s, ch, m in reader.iter_messages()
        ]
        summary = reader.get_summary()
    assert [(t, lt) for t, lt, *_ in got] == [(t, lt) for t, lt, _ in sent]
    for (topic, t, want), (_tp, _lt, pt, seq, value) in zip(sent, got, strict=True):
        check_value(topic, value, want)
        assert pt == t - 1000 and seq == (t - T0) // 200_000
    stats = summary.statistics
    assert stats.message_count == len(sent)
    assert stats.message_start_time == sent[0][1] and stats.message_end_time == sent[-1][1]
    by_topic = {summary.channels[c].topic: n for c, n in stats.channel_message_counts.items()}
    assert {t: n for t, n in by_topic.items() if n} == topic_counts(sent)
    assert {s.name for s in summary.schemas.values()} == {ARRAY, STRING}
    assert scan_mcap(path).complete  # ends in a footer whose summary CRC matches
    check_message_indexes(path, summary)


def check_message_indexes(path: Path, summary) -> None:
    """Every chunk's Message Index records (read by the mcap library) list each of its
    messages once, sorted by (log_time, offset), each pointing at a Message of that channel
    and log_time; the summary's Chunk Indexes point at those records."""
    with open(path, 'rb') as f:
        records = list(StreamReader(f, emit_chunks=True, validate_crcs=True).records)
    chunk_data, msgs, seen, n_chunks = b'', {}, [], 0

    def check_chunk() -> None:
        assert sorted(seen) == sorted(msgs)

    for r in records:
        if isinstance(r, McapChunk):
            if n_chunks:
                check_chunk()
            n_chunks += 1
            stream, _n = get_chunk_data_stream(r, validate_crc=True)
            chunk_data, msgs, seen = stream.read(r.uncompressed_size), {}, []
            for m_off in _message_offsets(chunk_data):
                m = McapMessage.read(
                    ReadDataStream(io.BytesIO(chunk_data[m_off + 9 :])),
                    struct.unpack_from('<Q', chunk_data, m_off + 1)[0],
                )
                msgs[m_off] = (m.channel_id, m.log_time)
        elif isinstance(r, McapMessageIndex):
            assert r.records == sorted(r.records)
            for t, off in r.records:
                assert msgs[off] == (r.channel_id, t)
                seen.append(off)
    if n_chunks:
        check_chunk()
    assert n_chunks == len(summary.chunk_indexes)
    with open(path, 'rb') as f:
        for ci in summary.chunk_indexes:
            f.seek(ci.chunk_start_offset)
            assert f.read(1) == b'\x06'
            for cid, off in ci.message_index_offsets.items():
                f.seek(off)
                head = f.read(11)
                assert head[0] == 0x07 and struct.unpack_from('<H', head, 9)[0] == cid


def _message_offsets(data: bytes) -> list[int]:
    out, p = [], 0
    while p < len(data):
        op, n = struct.unpack_from('<BQ', data, p)
        if op == 0x05:
            out.append(p)
        p += 9 + n
    return out


def read_with_rosbags(bag: Path, sent: list[tuple[str, int, object]]) -> None:
    """rosbags reads the bag directory (metadata.yaml + MCAP) and deserialises every message."""
    store = get_typestore(Stores.EMPTY)
    got = []
    with RosbagsReader(bag) as reader:
        for conn in reader.connections:
            store.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
        assert reader.message_count == len(sent)
        assert {c.topic: c.msgcount for c in reader.connections} == topic_counts(sent)
        for conn, t, raw in reader.messages():
            msg = store.deserialize_cdr(raw, conn.msgtype)
            got.append((conn.topic, t, msg.data))
    assert [(t, lt) for t, lt, _ in got] == [(t, lt) for t, lt, _ in sent]
    for (topic, _t, want), (_tp, _lt, value) in zip(sent, got, strict=True):
        check_value(topic, value, want)


def check_metadata_yaml(bag: Path, sent: list[tuple[str, int, object]], state: str) -> dict:
    info = read_metadata_yaml(bag)
    assert info['message_count'] == len(sent)
    counts = {
        t['topic_metadata']['name']: t['message_count'] for t in info['topics_with_message_count']
    }
    assert {t: n for t, n in counts.items() if n} == topic_counts(sent)
    for t in info['topics_with_message_count']:
        assert t['topic_metadata']['offered_qos_profiles'] == QOS
        assert t['topic_metadata']['type_description_hash'] == TYPE_HASH
    assert info['starting_time']['nanoseconds_since_epoch'] == sent[0][1]
    assert info['duration']['nanoseconds'] == sent[-1][1] - sent[0][1]
    assert info['custom_data']['im_tuner.state'] == state
    assert info['custom_data']['im_tuner.run_id'] == 'test-42'  # kept from the provisional file
    return info


def crash(rec: Recording, cut_last_chunk: bool = True) -> list[tuple[str, int, object]]:
    """SIGKILL: the open chunk is lost, the last written chunk cut in half (if asked)."""
    rec.w.abandon()
    if not cut_last_chunk:
        return rec.flushed()
    last = rec.w.chunks[-1]
    os.truncate(rec.file, last.chunk_start_offset + last.chunk_length // 2)
    return rec.flushed(len(rec.w.chunks) - 1)


# --- 1. complete bags are readable by independent readers ---------------------------------


@pytest.mark.parametrize('compression', ['none', 'zstd', 'lz4'])
def test_complete_bag_reads_back(tmp_path: Path, compression: str) -> None:
    rec = Recording(tmp_path / 'bag', compression)
    rec.write(700, flush_every=97)
    rec.w.close()
    assert len(rec.w.chunks) > 5
    write_metadata_yaml(
        rec.out,
        bag_metadata(
            [(rec.file.name, rec.w.t_start, rec.w.t_end, rec.w.message_count)],
            [
                TopicRecord(
                    t,
                    ARRAY if t == '/drive/state' else STRING,
                    rec.w.channel_counts[c],
                    QOS,
                    TYPE_HASH,
                )
                for t, c in rec.ch.items()
            ],
            {'im_tuner.state': 'closed', 'im_tuner.run_id': 'test-42'},
        ),
    )
    read_with_mcap(rec.file, rec.sent)
    read_with_rosbags(rec.out, rec.sent)


# --- 2. a crash: readable up to the last complete chunk, repaired ------------------------


@pytest.mark.parametrize(
    'compression,background', [('none', False), ('zstd', False), ('lz4', False), ('lz4', True)]
)
def test_crash_then_repair(tmp_path: Path, compression: str, background: bool) -> None:
    rec = Recording(tmp_path / 'bag', compression, background=background)
    rec.write(900, flush_every=61)
    rec.write(3)  # in the open chunk: lost
    complete = crash(rec)
    assert len(rec.w.chunks) > 5 and 0 < len(complete) < len(rec.sent)

    # Before repair: the indexed readers refuse the file (no footer)...
    with open(rec.file, 'rb') as f, pytest.raises(McapError):
        make_reader(f).get_summary()
    with pytest.raises(RosbagsReaderError, match='end magic'):
        RosbagsReader(rec.file).open()
    # ...a streaming reader gets every message of the complete chunks, then hits the cut.
    streamed = []
    with open(rec.file, 'rb') as f, pytest.raises(EndOfFile):
        for r in StreamReader(f).records:
            if isinstance(r, McapMessage):
                streamed.append(r.log_time)
    assert streamed == [t for _tp, t, _v in complete]
    # ...and so does the mcap reader on a non-seekable stream, in file order (its default,
    # log_time_order=True, sorts everything first and so yields nothing before the error).
    nonseek = []
    with open(rec.file, 'rb') as f, pytest.raises(EndOfFile):
        reader = make_reader(io.BufferedReader(_NonSeekable(f)))
        for _s, _c, m in reader.iter_messages(log_time_order=False):
            nonseek.append(m.log_time)
    assert nonseek == streamed

    report = repair_bag(rec.out)
    assert not report.was_complete
    assert report.messages == len(complete)
    assert report.chunks == len(rec.w.chunks) - 1
    assert report.topics == topic_counts(complete)
    last = rec.w.chunks[-1]
    assert report.dropped_bytes == last.chunk_length // 2
    assert not list(rec.out.glob('*.repairing'))
    assert 'recovered' in report.summary() and '/chatter' in report.summary()
    read_with_mcap(rec.file, complete)
    read_with_rosbags(rec.out, complete)
    info = check_metadata_yaml(rec.out, complete, 'repaired')
    assert info['custom_data']['im_tuner.repair'] == (
        f'recovered {len(complete)} messages in {report.chunks} chunks; discarded '
        f'{report.dropped_bytes} bytes after the last complete chunk'
    )
    # The metadata record written at the start survives.
    with open(rec.file, 'rb') as f:
        assert [m.name for m in make_reader(f).iter_metadata()] == ['im_tuner.run']

    # Repairing again finds a complete file and leaves it alone.
    digest = sha(rec.file)
    again = repair_bag(rec.out)
    assert again.was_complete and again.messages == len(complete) and sha(rec.file) == digest


class _NonSeekable(io.RawIOBase):
    def __init__(self, f) -> None:
        self.f = f

    def readable(self) -> bool:
        return True

    def readinto(self, b) -> int:
        data = self.f.read(len(b))
        b[: len(data)] = data
        return len(data)


def test_crash_right_after_a_chunk(tmp_path: Path) -> None:
    """Killed between chunks (no partial record): every flushed message is recovered."""
    rec = Recording(tmp_path / 'bag')
    rec.write(300, flush_every=50)
    complete = crash(rec, cut_last_chunk=False)
    report = repair_bag(rec.out)
    assert report.messages == len(complete) == 300 and report.dropped_bytes == 0
    read_with_mcap(rec.file, complete)
    read_with_rosbags(rec.out, complete)


def test_crash_before_any_chunk(tmp_path: Path) -> None:
    """Only header, schemas, channels, metadata: an empty but valid bag."""
    rec = Recording(tmp_path / 'bag')
    rec.write(3)
    rec.w.abandon()
    report = repair_bag(rec.out)
    assert (report.messages, report.chunks, report.dropped_bytes) == (0, 0, 0)
    assert report.topics == {'/drive/state': 0, '/chatter': 0}
    with open(rec.file, 'rb') as f:
        reader = make_reader(f, validate_crcs=True)
        assert list(reader.iter_messages()) == []
        assert len(reader.get_summary().channels) == 2
    with RosbagsReader(rec.out) as reader:
        assert reader.message_count == 0 and list(reader.messages()) == []
    assert read_metadata_yaml(rec.out)['custom_data']['im_tuner.state'] == 'repaired'


# --- 3. a complete bag is left untouched ------------------------------------------------


def test_repair_complete_bag_leaves_mcap_untouched(tmp_path: Path) -> None:
    rec = Recording(tmp_path / 'bag', 'lz4')
    rec.write(400, flush_every=77)
    rec.w.close()
    digest = sha(rec.file)
    report = repair_bag(rec.out)
    assert report.was_complete and report.dropped_bytes == 0
    assert report.messages == 400 and report.chunks == len(rec.w.chunks)
    assert sha(rec.file) == digest
    assert 'left untouched' in report.summary()
    check_metadata_yaml(rec.out, rec.sent, 'closed')
    read_with_rosbags(rec.out, rec.sent)


# --- 4. garbage after the last chunk ---------------------------------------------------


@pytest.mark.parametrize('tail', ['random', 'zeros', 'partial-dataend'])
def test_garbage_tail_is_dropped(tmp_path: Path, tail: str) -> None:
    rec = Recording(tmp_path / 'bag')
    rec.write(500, flush_every=100)
    complete = crash(rec, cut_last_chunk=False)
    size = rec.file.stat().st_size
    junk = {
        'random': np.random.default_rng(7).bytes(3000),
        'zeros': bytes(4096),
        'partial-dataend': b'\x0f\x04\x00\x00\x00\x00\x00\x00\x00\x00',
    }[tail]
    with open(rec.file, 'ab') as f:
        f.write(junk)
    report = repair_bag(rec.out)
    assert report.dropped_bytes == len(junk)
    assert report.messages == len(complete) == 500
    assert rec.file.stat().st_size > size  # summary and footer added
    read_with_mcap(rec.file, complete)
    read_with_rosbags(rec.out, complete)


def test_a_corrupt_chunk_is_left_out_and_the_chunks_after_it_recovered(tmp_path: Path) -> None:
    """A whole chunk whose payload fails its CRC had its bytes changed: it is named and
    left out, and the scan goes on to recover every chunk after it."""
    rec = Recording(tmp_path / 'bag', 'none')
    rec.write(400, flush_every=100)
    crash(rec, cut_last_chunk=False)
    size = rec.file.stat().st_size
    third = rec.w.chunks[2]
    with open(rec.file, 'r+b') as f:
        f.seek(third.chunk_start_offset + third.chunk_length - 5)
        byte = f.read(1)
        f.seek(-1, os.SEEK_CUR)
        f.write(bytes([byte[0] ^ 0xFF]))
    report = repair_bag(rec.out)
    kept = rec.flushed(2) + rec.sent[len(rec.flushed(3)) : len(rec.flushed())]
    assert [d[:2] for d in report.damaged] == [(3, third.chunk_start_offset)]
    assert report.messages == len(kept) and report.chunks == len(rec.w.chunks) - 1
    # (only what followed the last chunk)
    assert report.dropped_bytes < size - third.chunk_start_offset
    assert 'left out damaged chunk 3' in report.summary()
    read_with_mcap(rec.file, kept)


# --- files from another writer: channels inside chunks, messages outside chunks ------------


@pytest.mark.parametrize('chunked', [True, False])
def test_repair_file_of_the_mcap_library(tmp_path: Path, chunked: bool) -> None:
    from mcap.writer import Writer

    out = prepare_bag_dir(tmp_path / 'bag')
    path = out / 'bag_0.mcap'
    sent = []
    with open(path, 'wb') as f:
        w = Writer(f, chunk_size=2048, use_chunking=chunked)
        w.start(profile='ros2', library='test')
        meta = {'offered_qos_profiles': qos_yaml(QOS), 'topic_type_hash': TYPE_HASH}
        sid = w.register_schema(ARRAY, 'ros2msg', schema_text(ARRAY).encode())
        cid = w.register_channel('/drive/state', 'cdr', sid, meta)
        for i in range(600):
            t = T0 + i * 200_000
            value = np.array([float(i)])
            w.add_message(cid, t, f64_array_cdr(value), t - 1000, sequence=i)
            sent.append(('/drive/state', t, value))
        f.flush()
        size = f.tell()  # crash: no finish()
    recovered = sent[: len(stream_messages(path))]
    assert len(recovered) == 600 if not chunked else 400 < len(recovered) < 600
    report = repair_bag(out)
    assert report.messages == len(recovered) and report.dropped_bytes == 0
    assert path.stat().st_size > size
    with open(path, 'rb') as f:
        reader = make_reader(f, validate_crcs=True)
        got = [(m.log_time, decode_cdr(c.topic, m.data)) for _s, c, m in reader.iter_messages()]
        assert reader.get_summary().statistics.message_count == len(recovered)
    assert [t for t, _ in got] == [t for _, t, _ in recovered]
    for (_tp, _t, want), (_lt, value) in zip(recovered, got, strict=True):
        np.testing.assert_array_equal(value, want)
    store = get_typestore(Stores.EMPTY)
    with RosbagsReader(out) as reader:
        for conn in reader.connections:
            store.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
        values = [store.deserialize_cdr(raw, c.msgtype).data[0] for c, _t, raw in reader.messages()]
    assert values == [v[0] for _tp, _t, v in recovered]
