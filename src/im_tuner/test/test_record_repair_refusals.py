"""im_tuner.record.repair refuses what it must not rewrite and fails atomically: errors name
the path and change nothing; a damaged complete file is refused; a repair interrupted midway
leaves the original. The recordings and the independent readers: test_record_repair.py.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from im_tuner.record import repair as mcap_repair

sys.path.insert(0, str(Path(__file__).parent))
from test_record_repair import Recording, crash, read_with_mcap, read_with_rosbags, snapshot

RepairError = mcap_repair.RepairError
repair_bag = mcap_repair.repair_bag


# --- 5. errors ---------------------------------------------------------------------------


def test_errors_name_the_path_and_change_nothing(tmp_path: Path) -> None:
    not_dir = tmp_path / 'file.txt'
    not_dir.write_text('x')
    with pytest.raises(RepairError, match='not a directory') as e:
        repair_bag(not_dir)
    assert str(not_dir) in str(e.value)
    with pytest.raises(RepairError, match='not a directory'):
        repair_bag(tmp_path / 'missing')
    assert not (tmp_path / 'missing').exists()

    empty = tmp_path / 'empty'
    empty.mkdir()
    (empty / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
    before = snapshot(empty)
    with pytest.raises(RepairError, match=r'no \.mcap file') as e:
        repair_bag(empty)
    assert str(empty) in str(e.value) and snapshot(empty) == before

    for name, content, msg in [
        ('bad', b'not an mcap file at all' * 10, 'bad magic'),
        ('short', b'\x89MC', 'bad magic'),
        ('nohead', b'\x89MCAP0\r\n\x01\x30\x00', 'no complete MCAP header'),
        ('zero', b'', 'bad magic'),
    ]:
        d = tmp_path / name
        d.mkdir()
        (d / f'{name}_0.mcap').write_bytes(content)
        (d / 'metadata.yaml').write_text('provisional: true\n')
        before = snapshot(d)
        with pytest.raises(RepairError, match=msg) as e:
            repair_bag(d)
        assert str(d / f'{name}_0.mcap') in str(e.value)
        assert snapshot(d) == before


def test_several_mcap_files_are_refused(tmp_path: Path) -> None:
    d = tmp_path / 'multi'
    d.mkdir()
    for name in ('a.mcap', 'b.mcap'):
        (d / name).write_bytes(b'\x89MCAP0\r\n')
    with pytest.raises(RepairError, match=r'several \.mcap files \(a\.mcap, b\.mcap\)'):
        repair_bag(d)


def test_damaged_complete_file_is_refused(tmp_path: Path) -> None:
    """A valid footer but a chunk that fails its CRC: not ours to rewrite; nothing changes."""
    rec = Recording(tmp_path / 'bag', 'none')
    rec.write(300, flush_every=100)
    rec.w.close()
    second = rec.w.chunks[1]
    with open(rec.file, 'r+b') as f:
        f.seek(second.chunk_start_offset + second.chunk_length - 3)
        f.write(b'\xff\xfe\xfd')
    before = snapshot(rec.out)
    with pytest.raises(RepairError, match=r'chunk 2 at byte \d+ is damaged \(CRC') as e:
        repair_bag(rec.out)
    assert str(rec.file) in str(e.value) and snapshot(rec.out) == before


def test_killed_while_writing_the_summary(tmp_path: Path) -> None:
    """DataEnd is there but the summary is cut: rewritten, nothing of the data lost."""
    rec = Recording(tmp_path / 'bag', 'zstd')
    rec.write(500, flush_every=120)
    rec.w.close()
    last = rec.w.chunks[-1]
    # the DataEnd record is here
    data_end = last.chunk_start_offset + last.chunk_length + last.message_index_length
    size = rec.file.stat().st_size
    os.truncate(rec.file, size - 40)
    report = repair_bag(rec.out)
    assert not report.was_complete and report.messages == 500
    assert report.dropped_bytes == size - 40 - data_end
    read_with_mcap(rec.file, rec.sent)
    read_with_rosbags(rec.out, rec.sent)


# --- 6. failure atomicity -----------------------------------------------------------------


def test_failure_leaves_the_original(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rec = Recording(tmp_path / 'bag')
    rec.write(300, flush_every=40)
    crash(rec)
    before = snapshot(rec.out)

    def boom(*_a, **_k):
        raise OSError(28, 'No space left on device')

    monkeypatch.setattr(mcap_repair.os, 'replace', boom)
    with pytest.raises(RepairError, match='original is unchanged') as e:
        repair_bag(rec.out)
    assert str(rec.file) in str(e.value)
    assert snapshot(rec.out) == before  # no .repairing left, metadata.yaml untouched
    monkeypatch.undo()

    def interrupted(*_a, **_k):
        raise KeyboardInterrupt

    monkeypatch.setattr(mcap_repair, 'file_end', interrupted)  # mid-way: the summary
    with pytest.raises(KeyboardInterrupt):
        repair_bag(rec.out)
    assert snapshot(rec.out) == before
    monkeypatch.undo()

    assert repair_bag(rec.out).messages == len(rec.flushed(len(rec.w.chunks) - 1))
