"""im_tuner.record.reader's index path: a chunk's messages found through the
MessageIndex records after it, without the numba record walk, and the walk taken instead
whenever an index is missing or does not match its chunk.

Each case reads a bag written by McapWriter (test_record_reader's ``write_bag``) whose index
records are then removed or altered on disk; whatever the index, the reader must give
what the mcap library's reader and the written values say.
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.opcode import Opcode

from im_tuner.record import reader
from im_tuner.record.reader import read_bag

sys.path.insert(0, str(Path(__file__).parent))
from test_record_reader import mcap_library_counts, write_bag

ARRAYS = {'/controller/internals': None, '/labelled': None}


def top_records(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, start, end) of each top-level record of the data section."""
    out, p = [], 8
    while p + 9 <= len(data):
        op, n = struct.unpack_from('<BQ', data, p)
        out.append((op, p, p + 9 + n))
        p += 9 + n
        if op == Opcode.DATA_END:
            break
    return out


def counting_walk(monkeypatch) -> list[int]:
    """Counts the record walks of chunks (start 0) that read_bag makes."""
    calls: list[int] = []
    real = reader.walk_records

    def walk(buf, start, stop_op):
        if start == 0:
            calls.append(1)
        return real(buf, start, stop_op)

    monkeypatch.setattr(reader, 'walk_records', walk)
    return calls


def written(bag: Path) -> dict:
    """A bag (test_record_reader's) and what it holds: the values written, and the log times
    the mcap library reads from the file as written (before any edit here: the library
    follows the summary's offsets, which an edit moves)."""
    want = write_bag(bag)
    want['lib'] = mcap_library_counts(want['file'])
    return want


def check_against_written(bag: Path, want: dict) -> None:
    got = read_bag(bag, ARRAYS)
    lib = want['lib']
    assert {t: s.count for t, s in got.topics.items()} == {t: len(v) for t, v in lib.items()}
    for t, times in lib.items():
        assert (got.topics[t].first_ns, got.topics[t].last_ns) == (min(times), max(times))
    np.testing.assert_array_equal(got.arrays['/controller/internals'], np.array(want['rows']))
    np.testing.assert_array_equal(got.arrays['/labelled'], np.array(want['labelled']))
    assert [int(m['experiment_id']) for m in got.losses] == list(range(len(want['losses'])))
    assert got.complete and got.unread_bytes == 0


@pytest.mark.parametrize('compression', ['lz4', 'zstd', 'none'])
def test_indexed_chunks_need_no_record_walk(tmp_path, monkeypatch, compression):
    want = write_bag(tmp_path / 'b', compression=compression)
    want['lib'] = mcap_library_counts(want['file'])
    calls = counting_walk(monkeypatch)
    check_against_written(tmp_path / 'b', want)
    assert read_bag(tmp_path / 'b').chunks > 10 and calls == []


def _rewrite(path: Path, edit) -> int:
    """Rewrite the bag's file with ``edit(op, record bytes, chunk number) -> bytes``
    applied to each top-level record; returns the number of chunks."""
    data = path.read_bytes()
    recs = top_records(data)
    out, chunk = [data[:8]], -1
    for op, a, b in recs:
        chunk += op == Opcode.CHUNK
        out.append(edit(op, data[a:b], chunk))
    out.append(data[recs[-1][2] :])
    path.write_bytes(b''.join(out))
    return chunk + 1


def test_no_index_at_all_walks_every_chunk(tmp_path, monkeypatch):
    want = written(tmp_path / 'b')
    n = _rewrite(want['file'], lambda op, rec, _c: b'' if op == Opcode.MESSAGE_INDEX else rec)
    calls = counting_walk(monkeypatch)
    check_against_written(tmp_path / 'b', want)
    assert len(calls) == n


def _first_index_of_chunk(target: int):
    seen: set[int] = set()

    def pick(op: int, chunk: int) -> bool:
        if op == Opcode.MESSAGE_INDEX and chunk == target and chunk not in seen:
            seen.add(chunk)
            return True
        return False

    return pick


def walks_with_one_index_edited(path: Path, monkeypatch, chunk: int, edit) -> int:
    """Write a bag, replace the first message index of chunk ``chunk`` by ``edit(rec)``,
    and read it back (checked against what was written): the chunks read by a walk."""
    want = written(path)
    pick = _first_index_of_chunk(chunk)
    _rewrite(want['file'], lambda op, rec, c: edit(rec) if pick(op, c) else rec)
    calls = counting_walk(monkeypatch)
    check_against_written(path, want)
    return len(calls)


def test_a_wrong_log_time_in_an_index_walks_that_chunk(tmp_path, monkeypatch):
    def later_first_entry(rec: bytes) -> bytes:
        # first entry: (log_time, offset) after opcode, length, channel id, byte count
        (t,) = struct.unpack_from('<Q', rec, 15)
        return rec[:15] + struct.pack('<Q', t + 1) + rec[23:]

    assert walks_with_one_index_edited(tmp_path / 'b', monkeypatch, 3, later_first_entry) == 1


def test_a_missing_channel_index_walks_that_chunk(tmp_path, monkeypatch):
    """A chunk whose first channel's index is gone: its messages lie between the indexed
    ones, so the index does not tile the chunk."""
    assert walks_with_one_index_edited(tmp_path / 'b', monkeypatch, 5, lambda rec: b'') == 1


def test_an_offset_past_the_chunk_walks_that_chunk(tmp_path, monkeypatch):
    def past_the_chunk(rec: bytes) -> bytes:
        return rec[:23] + struct.pack('<Q', 2**63 + 5) + rec[31:]

    assert walks_with_one_index_edited(tmp_path / 'b', monkeypatch, 2, past_the_chunk) == 1
