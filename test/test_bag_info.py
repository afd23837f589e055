"""``ros2 run im_tuner report --bag-info BAG_DIR``: a bag's statistics,
checked topic by topic against what two readers that are not our code report.

* rosbags' ``AnyReader`` (every type from the bag, checked against its hash on open):
  messages per topic, their bytes, first and last log time; its bag start and end;
* the ``mcap`` library: ``get_summary()`` (statistics, chunk indexes) and
  ``iter_messages()`` (CRC-checked): the same per topic, the chunk count, compression
  and every chunk's log-time span;
* the recorder's recorded / published / lost equal the bag's metadata (``metadata.yaml``
  custom_data ``im_tuner.counts``, and its MCAP record).

On a closed lock-step tuner bag, and on a bag whose recorder was SIGKILLed and then
repaired (its counts are not in it: the recorder writes them at close). A path that is
not a bag: one line, exit 2, nothing created.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray, String

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
RELIABLE_ALL = QoSProfile(
    history=HistoryPolicy.KEEP_ALL, depth=0, reliability=ReliabilityPolicy.RELIABLE
)


# -- what the readers say -----------------------------------------------------------------
def rosbags_stats(bag: Path) -> dict[str, Any]:
    """Per topic (count, bytes, first, last log time [ns]) and the bag's start and end,
    by rosbags' AnyReader (its ``end_time`` is exclusive: the last log time + 1)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    per: dict[str, list[int]] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, t, raw in reader.messages():
            p = per.setdefault(conn.topic, [0, 0, t, t])
            p[0] += 1
            p[1] += len(raw)
            p[2], p[3] = min(p[2], t), max(p[3], t)
        return {
            'topics': {k: tuple(v) for k, v in per.items()},
            'types': types,
            'start': reader.start_time,
            'end': reader.end_time - 1,
            'messages': reader.message_count,
        }


def mcap_stats(bag: Path) -> dict[str, Any]:
    """The same by the mcap library (CRC-checked read), plus what its summary says of the
    chunks (count, compressions, every chunk's log-time span [s], in file order) and the
    Metadata records."""
    from mcap.reader import make_reader

    (path,) = bag.glob('*.mcap')
    per: dict[str, list[int]] = {}
    with open(path, 'rb') as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None
        for _schema, channel, m in reader.iter_messages(log_time_order=False):
            p = per.setdefault(channel.topic, [0, 0, m.log_time, m.log_time])
            p[0] += 1
            p[1] += len(m.data)
            p[2], p[3] = min(p[2], m.log_time), max(p[3], m.log_time)
        metadata = {r.name: r.metadata for r in reader.iter_metadata()}
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    st = summary.statistics
    assert st is not None
    return {
        'topics': {k: tuple(v) for k, v in per.items()},
        'types': {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()},
        'start': st.message_start_time,
        'end': st.message_end_time,
        'messages': st.message_count,
        'channel_counts': {
            summary.channels[cid].topic: n for cid, n in st.channel_message_counts.items()
        },
        'chunks': len(chunks),
        'compression': sorted({c.compression or 'none' for c in chunks}),
        'spans': [(c.message_end_time - c.message_start_time) * 1e-9 for c in chunks],
        'metadata': metadata,
    }


def bag_info(bag: Path) -> dict[str, Any]:
    """``report --bag-info BAG --json``, run as a user runs it."""
    r = subprocess.run(
        [ROS2, 'run', 'im_tuner', 'report', '--bag-info', str(bag), '--json'],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout)


def assert_equals_the_readers(info: dict[str, Any], bag: Path) -> None:
    """Every figure of ``info`` that a reader reports too, equal to both readers'."""
    rb, mc = rosbags_stats(bag), mcap_stats(bag)
    assert rb['topics'] == mc['topics']  # the readers agree with each other first
    rows = {t['topic']: t for t in info['topics']}
    with_messages = {k for k, t in rows.items() if t['count']}
    assert with_messages == set(mc['topics']), (with_messages, set(mc['topics']))
    for topic, (count, nbytes, first, last) in mc['topics'].items():
        t = rows[topic]
        assert (t['count'], t['bytes'], t['first_ns'], t['last_ns']) == (
            count,
            nbytes,
            first,
            last,
        ), topic
        assert t['type'] == mc['types'][topic] == rb['types'][topic], topic
        span_s = (last - first) * 1e-9
        if count >= 10 or (count > 1 and span_s >= 1.0):
            assert t['rate_hz'] == pytest.approx((count - 1) / span_s, rel=1e-12)
        else:  # too short to have a rate (a 2-message topic 1 ms apart is not 1 kHz)
            assert t['rate_hz'] is None, topic
        assert mc['channel_counts'].get(topic) == count, topic
    assert (
        info['messages']
        == mc['messages']
        == rb['messages']
        == sum(c for c, *_ in mc['topics'].values())
    )
    assert info['bytes'] == sum(b for _c, b, *_ in mc['topics'].values())
    assert info['start_ns'] == mc['start'] == rb['start']
    assert info['end_ns'] == mc['end'] == rb['end']
    assert info['duration_s'] == pytest.approx((mc['end'] - mc['start']) * 1e-9, abs=1e-9)
    assert info['chunks'] == mc['chunks']
    assert info['compression'] == mc['compression']
    assert info['max_chunk_span_s'] == pytest.approx(max(mc['spans']), abs=1e-9)
    assert info['first_chunk_span_s'] == pytest.approx(mc['spans'][0], abs=1e-9)
    (f,) = bag.glob('*.mcap')
    assert info['files'] == [{'name': f.name, 'bytes': f.stat().st_size}]


# -- a closed lock-step tuner bag -----------------------------------------------------------
@pytest.fixture(scope='module')
def lockstep_run(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp('bag_info') / 'run'
    r = subprocess.run(
        [
            *(ROS2, 'run', 'im_tuner', 'tuner', '--budget', '2', '--remeasure', '0'),
            *('--seed', '3', '--quiet', '--discovery-timeout', '0.2', '--out', str(run)),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    return run


def test_bag_info_of_a_lockstep_bag_equals_the_readers(lockstep_run):
    (bag,) = lockstep_run.glob('bag_*')
    info = bag_info(bag)
    assert_equals_the_readers(info, bag)
    assert info['state'] == 'closed' and info['complete'] and info['recorder_counts']
    # the recorder's counts: those of metadata.yaml and of the bag's own MCAP record
    custom = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information'][
        'custom_data'
    ]
    counts = json.loads(custom['im_tuner.counts'])
    record = {k: json.loads(v) for k, v in mcap_stats(bag)['metadata']['im_tuner.counts'].items()}
    assert counts == record
    rows = {t['topic']: t for t in info['topics']}
    assert set(rows) == set(counts)
    for topic, c in counts.items():
        row = rows[topic]
        assert (row['recorded'], row['published'], row['lost']) == (
            c['recorded'],
            c['published'],
            c['lost'],
        ), topic
        assert row['published_before_recording'] == c['published_before_recording'], topic
        assert row['recorded'] == row['count'], topic  # nothing lost on the way
    assert info['lost_total'] == 0 == int(custom['im_tuner.lost_total'])
    assert rows['/drive/state']['count'] > 10_000  # two experiments and the start's, 5 kHz


def test_a_file_cut_short_beside_its_metadata_says_so(lockstep_run, tmp_path):
    """A closed bag's MCAP file cut to half (a copy that broke off), its metadata.yaml beside
    it: the state says both, and the messages the recorder counted but the file lacks are
    named, not hidden behind "lost 0"; a metadata.yaml that is not YAML is called so."""
    import shutil

    from im_tuner.report.baginfo import format_info

    (bag,) = lockstep_run.glob('bag_*')
    cut = tmp_path / 'cut'
    shutil.copytree(bag, cut)
    (f,) = cut.glob('*.mcap')
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    info = bag_info(cut)
    assert info['state'] == 'closed' and not info['complete']
    rows = {t['topic']: t for t in info['topics']}
    short = sum(t['recorded'] - t['count'] for t in rows.values())
    assert (
        info['not_in_file'] == short > 0
        and rows['/drive/state']['count'] < (rows['/drive/state']['recorded'])
    )
    text = format_info(info)
    assert 'metadata.yaml says closed, but the MCAP file is NOT CLOSED' in text
    assert f'{short} the recorder counted are NOT in the file' in text
    (cut / 'metadata.yaml').write_text('{{{ not yaml')
    assert bag_info(cut)['state'] == 'metadata.yaml unreadable'


def test_the_table_a_user_pastes(lockstep_run):
    """The default output: the totals, then one aligned row per topic with the same
    figures as --json."""
    (bag,) = lockstep_run.glob('bag_*')
    info = bag_info(bag)
    r = subprocess.run(
        [ROS2, 'run', 'im_tuner', 'report', '--bag-info', str(bag)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0 and r.stderr == '', r.stderr
    lines = r.stdout.splitlines()
    assert lines[0] == f'Bag:        {bag}'
    assert f'Duration:   {info["duration_s"]:.3f} s' in lines
    assert lines[2] == 'State:      closed'
    head = next(i for i, x in enumerate(lines) if x.startswith('topic '))
    assert lines[head].split() == [
        'topic', 'type', 'count', 'rate', '[Hz]', 'size', '[B]', 'recorded', 'published', 'lost'
    ]  # fmt: skip
    table = {x.split()[0]: x.split() for x in lines[head + 1 : head + 1 + len(info['topics'])]}
    for t in info['topics']:
        row = table[t['topic']]
        rate = '-' if t['rate_hz'] is None else f'{t["rate_hz"]:.1f}'
        assert row == [
            t['topic'], t['type'], str(t['count']), rate, str(t['bytes']),
            str(t['recorded']), str(t['published']), str(t['lost']),
        ]  # fmt: skip
    # the columns line up: every row's count ends where the header's does
    end = lines[head].index('count') + len('count')
    for x in lines[head + 1 : head + 1 + len(info['topics'])]:
        assert x[end - 1] != ' ' and x[end] == ' ', x


# -- a SIGKILLed recorder, repaired ----------------------------------------------------------
def test_bag_info_of_a_repaired_bag_equals_the_readers(ros_context, procs, tmp_path, wait_until):
    node = Node('bag_info_pub', context=ros_context)
    pub = node.create_publisher(Float64MultiArray, 'killed', RELIABLE_ALL)
    note = node.create_publisher(String, 'note', RELIABLE_ALL)
    bag = tmp_path / 'bag'
    rec = procs.start(
        [
            *(ROS2, 'run', 'im_tuner', 'recorder', '--out', str(bag)),
            *('--chunk-size', '8192', '--max-chunk-age', '0.05', '--compression', 'zstd'),
        ]
    )
    wait_until(
        lambda: pub.get_subscription_count() >= 1 and note.get_subscription_count() >= 1,
        30.0,
        message='the recorder matched',
    )
    msg = Float64MultiArray(data=[0.0] * 4)
    for i in range(2000):
        msg.data[0] = float(i)
        pub.publish(msg)
        if i % 500 == 0:
            note.publish(String(data=f'note {i}'))
    for p in (pub, note):
        assert p.wait_for_all_acked(timeout=Duration(seconds=30))
    mcap_file = bag / 'bag_0.mcap'
    sizes: list[int] = []

    def settled() -> bool:  # every chunk closed by size or age is on disk
        sizes.append(mcap_file.stat().st_size)
        return len(sizes) > 5 and len(set(sizes[-5:])) == 1 and sizes[-1] > 8192

    wait_until(settled, 20.0, interval=0.05, message='chunks on disk')
    rec.send_signal(signal.SIGKILL)
    rec.wait(timeout=10)
    fix = subprocess.run(
        [ROS2, 'run', 'im_tuner', 'recorder', '--repair', str(bag)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert fix.returncode == 0, fix.stderr
    node.destroy_node()

    info = bag_info(bag)
    assert_equals_the_readers(info, bag)
    assert info['state'] == 'repaired' and info['complete']
    assert info['compression'] == ['zstd']
    rows = {t['topic']: t for t in info['topics']}
    assert rows['/killed']['count'] == 2000 and rows['/note']['count'] == 4
    assert rows['/killed']['bytes'] == 2000 * len(_cdr(msg))
    # a killed recorder wrote no counts: none shown, none made up
    assert not info['recorder_counts'] and info['lost_total'] is None
    assert all(t['recorded'] is None and t['lost'] is None for t in info['topics'])
    custom = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information'][
        'custom_data'
    ]
    assert 'im_tuner.counts' not in custom
    assert 'im_tuner.counts' not in mcap_stats(bag)['metadata']


def _cdr(msg: Any) -> bytes:
    from rclpy.serialization import serialize_message

    return serialize_message(msg)


# -- bad input --------------------------------------------------------------------------------
def _tree(d: Path) -> list[tuple[str, int]]:
    return sorted((str(p.relative_to(d)), p.stat().st_size) for p in d.rglob('*'))


@pytest.mark.parametrize(
    'args, says',
    [
        (['--bag-info', '{tmp}/missing'], 'no such directory'),
        (['--bag-info', '{tmp}/a_file'], 'not a directory'),
        (['--bag-info', '{tmp}/empty'], 'no .mcap file'),
        (['--bag-info', '{tmp}/not_mcap'], 'not an MCAP file'),
        (['--bag-info', '{tmp}/split'], 'a split bag'),
        (['--bag-info', '{tmp}/empty', '{tmp}/empty'], 'no run, --bags or --out'),
        (['--bag-info', '{tmp}/empty', '--out', '{tmp}/out'], 'no run, --bags or --out'),
        (['--json', '{tmp}/empty'], '--json goes with --bag-info'),
        ([], 'the following arguments are required: RUN_DIR (or --bag-info BAG_DIR)'),
    ],
)
def test_bad_input_is_one_line_exit_2_and_nothing_created(tmp_path, args, says):
    (tmp_path / 'a_file').write_text('x')
    (tmp_path / 'empty').mkdir()
    (tmp_path / 'not_mcap').mkdir()
    (tmp_path / 'not_mcap' / 'bag_0.mcap').write_bytes(b'not an mcap file at all')
    (tmp_path / 'split').mkdir()
    for name in ('bag_0.mcap', 'bag_1.mcap'):
        (tmp_path / 'split' / name).write_bytes(b'')
    before = _tree(tmp_path)
    argv = [a.replace('{tmp}', str(tmp_path)) for a in args]
    r = subprocess.run(
        [ROS2, 'run', 'im_tuner', 'report', *argv], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert r.stdout == ''
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: report: ') and says in lines[0], lines
    assert _tree(tmp_path) == before
