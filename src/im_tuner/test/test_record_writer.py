"""im_tuner.record.writer: background writes never fail on the writer's own bookkeeping.

The bug: ``_submit`` filtered finished futures out of its pending list
and then asked each remaining one ``done()`` again; a write that finished in between was
reported as ``background write failed: None``. These tests pin the mechanism (a future that
finishes between two looks) deterministically, then race thousands of tiny writes against
their completion and check the file with the ``mcap`` library (CRCs on).
"""

from __future__ import annotations

from concurrent.futures import Future
from pathlib import Path

import pytest
from mcap.reader import make_reader

from im_tuner.record.writer import McapWriteError, McapWriter


class _FinishesWhileLookedAt(Future):
    """A future seen running at the first ``done()`` and finished (no error) from then on."""

    def __init__(self) -> None:
        super().__init__()
        self.set_result(None)
        self.looks = 0

    def done(self) -> bool:
        self.looks += 1
        return self.looks > 1


def test_a_write_finishing_between_two_looks_is_not_an_error(tmp_path: Path) -> None:
    w = McapWriter(tmp_path / 'a.mcap', compression='none', background=True)
    racer = _FinishesWhileLookedAt()
    w.pending.append(racer)
    w.add_metadata('m', {'k': 'v'})  # used to raise: "background write failed: None"
    w.close()
    with open(tmp_path / 'a.mcap', 'rb') as f:
        assert [m.name for m in make_reader(f).iter_metadata()] == ['m']


def test_a_failed_background_write_is_reported(tmp_path: Path) -> None:
    w = McapWriter(tmp_path / 'b.mcap', compression='none', background=True)
    bad: Future = Future()
    bad.set_exception(OSError(28, 'No space left on device'))
    w.pending.append(bad)
    with pytest.raises(McapWriteError, match='No space left on device'):
        w.add_metadata('m', {'k': 'v'})
    w.abandon()


@pytest.mark.parametrize('compression', ['none', 'lz4'])
def test_many_tiny_background_writes_race_their_completion(
    tmp_path: Path, compression: str
) -> None:
    """5000 messages in 1-record chunks plus metadata, every one a background job that
    may finish at any instant of the next submit: no error, and every record is there."""
    path = tmp_path / f'c_{compression}.mcap'
    # chunk_size 1: every message closes its chunk, so every add is a background write
    w = McapWriter(path, compression=compression, chunk_size=1, background=True)
    sid = w.add_schema('std_msgs/msg/String', 'ros2msg', b'string data')
    cid = w.add_channel('/t', sid, 'cdr')
    n = 5000
    for i in range(n):
        w.add_message(cid, i, 1000 + i, 1000 + i, b'\x00\x01\x00\x00' + bytes(8))
        if i % 250 == 0:
            w.add_metadata(f'm{i}', {'i': str(i)})
    w.close()
    with open(path, 'rb') as f:
        r = make_reader(f, validate_crcs=True)
        seqs = [m.sequence for _s, _c, m in r.iter_messages()]
        summary = r.get_summary()
    assert seqs == list(range(n))
    assert summary is not None and summary.statistics.message_count == n
    assert len(summary.chunk_indexes) == n
