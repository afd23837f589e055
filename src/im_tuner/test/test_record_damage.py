"""A bag whose bytes changed on disk: every reader of the project names the damaged chunk.

A bag is written with McapWriter (test_record_reader's ``write_bag``), closed or left as a
killed recorder leaves it, and one byte of one chunk's records is changed. The mcap
library's own reader, asked to validate CRCs, is the outside judge that the file is
damaged there; the project's reader (report, ``--bag-info``), replay and repair must say
which chunk, leave its messages out, and read every other chunk as before.
"""

from __future__ import annotations

import json
import struct
import sys
from pathlib import Path

import pytest
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader

from im_tuner.record.reader import read_bag
from im_tuner.record.repair import RepairError, repair_bag
from im_tuner.replay.plan import ReplayError, load_plan
from im_tuner.report.baginfo import bag_info, format_info

sys.path.insert(0, str(Path(__file__).parent))
from test_record_reader import write_bag

ARRAYS = {'/controller/internals': None}
DAMAGED = 3  # the chunk changed, counted from 1 in file order


def chunks(data: bytes) -> list[tuple[int, int]]:
    """(offset, end) of each Chunk record of the data section."""
    out, p = [], 8
    while p + 9 <= len(data):
        op, n = struct.unpack_from('<BQ', data, p)
        if op == 0 or p + 9 + n > len(data):
            break
        if op == Opcode.CHUNK:
            out.append((p, p + 9 + n))
        p += 9 + n
        if op == Opcode.DATA_END:
            break
    return out


def change_one_byte(path: Path, number: int) -> int:
    """Flip the bits of one byte in the middle of chunk ``number``'s records; its offset."""
    data = bytearray(path.read_bytes())
    at, end = chunks(bytes(data))[number - 1]
    pos = (at + end) // 2
    data[pos] ^= 0xFF
    path.write_bytes(bytes(data))
    return at


def library_says_damaged(path: Path) -> bool:
    """The mcap library's reader, validating CRCs, fails on the file."""
    try:
        with open(path, 'rb') as f:
            for _ in make_reader(f, validate_crcs=True).iter_messages(log_time_order=False):
                pass
    except (McapError, ValueError):
        return True
    return False


@pytest.mark.parametrize('compression', ['none', 'lz4', 'zstd'])
def test_one_changed_byte_is_named_by_chunk_and_the_rest_is_read(tmp_path, compression):
    whole = read_bag_of(tmp_path / 'whole', compression)
    bag = tmp_path / 'b'
    want = write_bag(bag, compression=compression)
    offset = change_one_byte(want['file'], DAMAGED)
    if compression == 'none':  # compressed: the library may fail on decompression instead
        assert library_says_damaged(want['file'])

    got = read_bag(bag, ARRAYS)
    assert [(d.number, d.offset) for d in got.damaged] == [(DAMAGED, offset)]
    assert got.complete and got.chunks == whole.chunks - 1
    # every other chunk read as before: the damaged one's messages, and no more, left out
    lost = whole.messages - got.messages
    assert 0 < lost < whole.messages / whole.chunks * 3
    k_all = set(whole.arrays['/controller/internals'][:, 0].tolist())
    k = set(got.arrays['/controller/internals'][:, 0].tolist())
    missing = sorted(k_all - k)
    assert k <= k_all and missing and missing[-1] - missing[0] == len(missing) - 1
    if compression == 'none':
        assert 'CRC' in got.damaged[0].reason

    info = bag_info(bag)
    assert [d['number'] for d in info['damaged_chunks']] == [DAMAGED]
    json.dumps(info)  # --json prints it
    text = format_info(info)
    assert f'DAMAGED:    chunk {DAMAGED} at byte {offset}' in text

    with pytest.raises(ReplayError, match=f'DAMAGED: chunk {DAMAGED} at byte {offset}'):
        load_plan(bag)


def read_bag_of(bag: Path, compression: str):
    write_bag(bag, compression=compression)
    return read_bag(bag, ARRAYS)


def test_repair_refuses_a_closed_bag_with_a_damaged_chunk_and_changes_nothing(tmp_path):
    bag = tmp_path / 'b'
    want = write_bag(bag, compression='none')
    offset = change_one_byte(want['file'], DAMAGED)
    before = {p.name: p.read_bytes() for p in bag.iterdir()}
    with pytest.raises(RepairError, match=rf'chunk {DAMAGED} at byte {offset} is damaged \(CRC'):
        repair_bag(bag)
    assert {p.name: p.read_bytes() for p in bag.iterdir()} == before


def test_repair_of_a_killed_bag_leaves_the_damaged_chunk_out_and_keeps_the_rest(tmp_path):
    whole = tmp_path / 'whole'
    write_bag(whole, compression='none', close=False)
    n_whole = repair_bag(whole).messages
    bag = tmp_path / 'b'
    want = write_bag(bag, compression='none', close=False)
    offset = change_one_byte(want['file'], DAMAGED)

    rep = repair_bag(bag)
    assert rep.damaged and rep.damaged[0][:2] == (DAMAGED, offset)
    assert f'left out damaged chunk {DAMAGED} at byte {offset} (CRC' in rep.summary()
    assert 0 < n_whole - rep.messages < n_whole / 10  # one chunk's messages, not the rest
    assert not library_says_damaged(want['file'])  # the rewritten file is whole
    got = read_bag(bag, ARRAYS)
    assert got.complete and not got.damaged and got.messages == rep.messages
