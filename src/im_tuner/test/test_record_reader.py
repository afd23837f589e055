"""im_tuner.record.reader: the report's bag reader, checked against independent readers.

Bags are written with :class:`~im_tuner.record.writer.McapWriter` (small chunks, both
compressions); what :func:`read_bag` finds is compared with the ``mcap`` library's reader
(counts, log times, payloads) and with rclpy's CDR deserialiser (loss messages, arrays
with a non-empty layout). A file cut short (a killed recorder) is read up to its last
complete chunk and says so.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Channel as McapChannel, Message as McapMessage
from mcap.stream_reader import StreamReader
from rclpy.serialization import serialize_message
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String

from im_tuner.record.metadata import (
    bag_metadata,
    prepare_bag_dir,
    storage_file_name,
    write_metadata_yaml,
)
from im_tuner.record.reader import (
    BagReadError,
    parse_diagnostic_array,
    parse_float64_multiarray,
    read_bag,
)
from im_tuner.record.schemas import schema_text
from im_tuner.record.writer import McapWriter

T0 = 1_700_000_000_000_000_000
ARRAY = 'std_msgs/msg/Float64MultiArray'
DIAG = 'diagnostic_msgs/msg/DiagnosticArray'
STRING = 'std_msgs/msg/String'
WIDTH = 6


def f64_array_cdr(values: np.ndarray) -> bytes:
    """The drive's fast layout (a Float64MultiArray with an empty layout): header, no
    dims, data_offset 0, n, pad, data."""
    return (
        b'\x00\x01\x00\x00'
        + struct.pack('<III', 0, 0, len(values))
        + bytes(4)
        + np.asarray(values, '<f8').tobytes()
    )


def loss_msg(i: int) -> DiagnosticArray:
    st = DiagnosticStatus(
        level=DiagnosticStatus.WARN if i % 3 == 0 else DiagnosticStatus.OK,
        name=f'controller: experiment {i}',
        message='done' if i % 3 else 'max_speed',
        hardware_id='controller',
    )
    st.values = [
        KeyValue(key='experiment_id', value=str(i)),
        KeyValue(key='loss', value=repr(0.1 * i + 1 / 3)),
        KeyValue(key='t_start_ns', value=str(i * 1_125_000_000)),
        KeyValue(key='note', value='é' * (i % 4)),
    ]  # odd lengths: alignment
    msg = DiagnosticArray(status=[st])
    msg.header.stamp.sec, msg.header.stamp.nanosec = i, 7 * i
    msg.header.frame_id = 'x' * (i % 5)
    return msg


def write_bag(
    out: Path, n: int = 3000, compression: str = 'lz4', chunk_size: int = 8192, close: bool = True
) -> dict:
    """A bag like a tuning run's: internals rows [k, ...] at 5 kHz, a loss message every
    500 steps, a string every 7, arrays with a labelled layout every 11."""
    out = prepare_bag_dir(out)
    path = out / storage_file_name(out)
    w = McapWriter(path, compression=compression, chunk_size=chunk_size)
    write_metadata_yaml(
        out, bag_metadata([(path.name, 0, 0, 0)], [], {'im_tuner.state': 'recording'})
    )
    ch = {
        t: w.add_channel(t, w.add_schema(ty, 'ros2msg', schema_text(ty).encode()), 'cdr')
        for t, ty in (
            ('/controller/internals', ARRAY),
            ('/controller/loss', DIAG),
            ('/chatter', STRING),
            ('/labelled', ARRAY),
        )
    }
    want = {'rows': [], 'losses': [], 'labelled': [], 'times': {t: [] for t in ch}}
    seq = 0
    for k in range(n):
        t = T0 + k * 35_000
        row = np.array([k, *(np.sin(k * 0.01 * np.arange(1, WIDTH)))])
        w.add_message(ch['/controller/internals'], seq, t, t, f64_array_cdr(row))
        want['rows'].append(row)
        want['times']['/controller/internals'].append(t)
        seq += 1
        if k % 500 == 499:
            m = loss_msg(k // 500)
            w.add_message(ch['/controller/loss'], seq, t + 1, t, serialize_message(m))
            want['losses'].append(m)
            want['times']['/controller/loss'].append(t + 1)
        if k % 7 == 0:
            w.add_message(ch['/chatter'], seq, t + 2, t, serialize_message(String(data=f'{k}')))
            want['times']['/chatter'].append(t + 2)
        if k % 11 == 0:
            m = Float64MultiArray(data=[float(k), 2.0 * k, -1.0])
            m.layout.dim = [MultiArrayDimension(label='xyz', size=3, stride=3)]
            w.add_message(ch['/labelled'], seq, t + 3, t, serialize_message(m))
            want['labelled'].append([float(k), 2.0 * k, -1.0])
            want['times']['/labelled'].append(t + 3)
    if close:
        w.close()
    else:
        w.flush_chunk()
        w.abandon()
    want['file'] = path
    return want


def mcap_library_counts(path: Path) -> dict[str, list[int]]:
    """Log times per topic as the mcap library's streaming reader sees them."""
    out: dict[str, list[int]] = {}
    with open(path, 'rb') as f:
        for _s, ch, msg in make_reader(f).iter_messages(log_time_order=False):
            out.setdefault(ch.topic, []).append(msg.log_time)
    return out


@pytest.mark.parametrize('compression', ['lz4', 'zstd', 'none'])
def test_counts_times_rows_and_losses_match_independent_readers(tmp_path, compression):
    want = write_bag(tmp_path / 'b', compression=compression)
    got = read_bag(tmp_path / 'b', {'/controller/internals': None, '/labelled': None})
    assert got.complete and got.unread_bytes == 0 and got.chunks > 20
    lib = mcap_library_counts(want['file'])
    assert {t: s.count for t, s in got.topics.items()} == {t: len(v) for t, v in lib.items()}
    for t, times in want['times'].items():
        s = got.topics[t]
        assert (s.count, s.first_ns, s.last_ns) == (len(times), times[0], times[-1])
        span_s = (times[-1] - times[0]) * 1e-9
        if len(times) >= 10 or span_s >= 1.0:
            assert s.rate_hz == pytest.approx((len(times) - 1) / span_s)
        else:  # a few messages close together: no rate (not a 60 Hz "topic" of 6 losses)
            assert s.rate_hz is None
    assert got.topics['/controller/internals'].type == ARRAY
    assert got.topics['/controller/loss'].type == DIAG
    np.testing.assert_array_equal(got.arrays['/controller/internals'], np.array(want['rows']))
    # the general CDR path (a labelled layout) gives the same numbers as rclpy wrote
    np.testing.assert_array_equal(got.arrays['/labelled'], np.array(want['labelled']))
    assert len(got.losses) == len(want['losses'])
    for g, m in zip(got.losses, want['losses'], strict=True):
        st = m.status[0]
        assert {k: g[k] for k in ('level', 'name', 'message', 'hardware_id')} == {
            'level': str(int.from_bytes(st.level, 'little')),
            'name': st.name,
            'message': st.message,
            'hardware_id': st.hardware_id,
        }
        assert {kv.key: kv.value for kv in st.values} == {
            k: v
            for k, v in g.items()
            if k not in ('level', 'name', 'message', 'hardware_id', 'stamp_ns', 'log_time_ns')
        }
        assert int(g['stamp_ns']) == m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
    assert [int(g['log_time_ns']) for g in got.losses] == want['times']['/controller/loss']


def test_windows_keep_only_the_rows_asked_for(tmp_path):
    want = write_bag(tmp_path / 'b')
    windows = [(10, 20), (2990, 5000), (500, 501)]
    got = read_bag(tmp_path / 'b', {'/controller/internals': windows})
    k = got.arrays['/controller/internals'][:, 0]
    assert k.tolist() == [*range(10, 20), 500, *range(2990, 3000)]
    rows = np.array(want['rows'])
    np.testing.assert_array_equal(got.arrays['/controller/internals'], rows[k.astype(int)])
    # a topic not asked for is counted, not kept; an empty window list keeps nothing
    assert '/labelled' not in got.arrays and got.topics['/labelled'].count == 273
    assert (
        read_bag(tmp_path / 'b', {'/controller/internals': []})
        .arrays['/controller/internals']
        .shape[0]
        == 0
    )


def test_a_bag_cut_short_is_read_to_its_last_complete_chunk(tmp_path):
    want = write_bag(tmp_path / 'b', close=False)
    path = want['file']
    full = read_bag(tmp_path / 'b', {'/controller/internals': None})
    assert not full.complete  # no DataEnd: the recorder never closed it
    assert full.messages == sum(len(v) for v in want['times'].values())
    # cut in the middle of a chunk: what is before it is read, the rest is reported
    size = path.stat().st_size
    data = path.read_bytes()
    path.write_bytes(data[: size * 3 // 5])
    got = read_bag(tmp_path / 'b', {'/controller/internals': None})
    assert not got.complete and 0 < got.unread_bytes < size * 3 // 5
    assert got.state == 'recording' and got.recorder_counts is None
    rows = got.arrays['/controller/internals']
    n = len(rows)
    assert 0 < n < len(want['rows'])
    np.testing.assert_array_equal(rows, np.array(want['rows'][:n]))
    assert got.topics['/controller/internals'].count == n
    lib = mcap_library_counts_until_error(path)
    assert {t: s.count for t, s in got.topics.items() if s.count} == {
        t: len(v) for t, v in lib.items()
    }


def mcap_library_counts_until_error(path: Path) -> dict[str, list[int]]:
    """Log times per topic from the mcap library's StreamReader, up to where the file ends."""
    chans: dict[int, str] = {}
    out: dict[str, list[int]] = {}
    with open(path, 'rb') as f:
        try:
            for r in StreamReader(f).records:
                if isinstance(r, McapChannel):
                    chans[r.id] = r.topic
                elif isinstance(r, McapMessage):
                    out.setdefault(chans[r.channel_id], []).append(r.log_time)
        except EndOfFile:  # the cut
            pass
    return out


def test_not_a_bag(tmp_path):
    (tmp_path / 'empty').mkdir()
    with pytest.raises(BagReadError, match=r'no \.mcap file'):
        read_bag(tmp_path / 'empty')
    (tmp_path / 'bad').mkdir()
    (tmp_path / 'bad' / 'x.mcap').write_bytes(b'not an mcap file at all')
    with pytest.raises(BagReadError, match='not an MCAP file'):
        read_bag(tmp_path / 'bad')


def test_cdr_parsers_on_rclpy_bytes():
    m = Float64MultiArray(data=[1.5, -2.0, np.pi])
    m.layout.dim = [MultiArrayDimension(label='a', size=3, stride=3)]
    m.layout.data_offset = 0
    np.testing.assert_array_equal(
        parse_float64_multiarray(serialize_message(m)), [1.5, -2.0, np.pi]
    )
    assert parse_float64_multiarray(serialize_message(Float64MultiArray())).size == 0
    two = DiagnosticArray(status=[loss_msg(1).status[0], loss_msg(2).status[0]])
    got = parse_diagnostic_array(serialize_message(two))
    assert [g['experiment_id'] for g in got] == ['1', '2']
    with pytest.raises(ValueError):
        parse_diagnostic_array(b'\x01\x00\x00\x00' + bytes(8))  # big-endian: refused
