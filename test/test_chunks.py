"""Chunks of at most ``--max-chunk-age`` (0.5 s) of log time, the first included, and
the real-time loop's outbox counts equal to the bag's.

Measured before: on the real-time bench 17 of 55 chunks spanned up to 0.585 s, and chunk
0 once 17.6 s (state 0 and the first log line waited in memory until traffic came: the
recorder took the loop's tap rings without the span bound, and closed a chunk only when
its owner polled it). The outbox's ``/drive/status put`` was one short of the bag: the
summary's figures were taken before the drive's last status was published.

* a tap backlog of 3 s of log time taken in one poll: chunks of at most the bound;
* a recorder nobody polls writes its first message to the file within the bound (the
  chunk timer), so a SIGKILL cannot lose it;
* real bags of a lock-step and a real-time tuner run: every chunk's span from the mcap
  library's chunk indexes <= 0.5 s, the first included; on the real-time run the
  outbox's ``put`` (the summary's ``loop.outbox`` and the bag's ``im_tuner.outbox``)
  equals the bag's count on every topic, by the mcap library and rosbags.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray, String

from im_drive_sim.outbox import Outbox
from im_tuner.record.node import Recorder

sys.path.insert(0, str(Path(__file__).parent))
from test_bag_info import bag_info, mcap_stats, rosbags_stats

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
RELIABLE_ALL = QoSProfile(
    history=HistoryPolicy.KEEP_ALL, depth=0, reliability=ReliabilityPolicy.RELIABLE
)
#: the documented bound (docs/recorder.md, "Crash safety") [s]
MAX_CHUNK_AGE = 0.5


def test_a_tap_backlog_is_cut_into_chunks_of_at_most_max_chunk_age(ros_context, tmp_path):
    """3 s of a loop's messages (1 kHz log times) waiting in the recorder's tap ring, taken
    in one poll: chunks of at most 0.25 s each, every message once, in order."""
    node = Node('tap_pub', context=ros_context)
    pub = node.create_publisher(Float64MultiArray, '/tapped', RELIABLE_ALL)
    box = Outbox()
    ch = box.add(pub, 'std_msgs/msg/Float64MultiArray', 256, 4000)
    rec = Recorder(
        Node('recorder', context=ros_context, start_parameter_services=False),
        tmp_path / 'bag',
        compression='none',
        max_chunk_age=0.25,
        flush_timer=False,  # one poll takes the whole backlog
        taps=box.tap(),
    )
    t0 = time.time_ns()
    n = 3000
    cdr = bytearray(b'\x00\x01\x00\x00' + bytes(8) + np.uint32(1).tobytes() + bytes(4) + bytes(8))
    assert ch.tap is not None
    for i in range(n):  # what the compiled loop does: put_slot with its stamp, put counted
        cdr[-8:] = np.float64(i).tobytes()
        assert ch.tap.put(np.frombuffer(bytes(cdr), np.uint8), t0 + i * 1_000_000)
        ch.put_count += 1
    try:
        assert rec.poll() == n
        counts = rec.close()
    finally:
        node.destroy_node()
    assert counts['/tapped'] == {
        'recorded': n,
        'published': n,
        'lost': 0,
        'publishers': 1,
        'published_before_recording': 0,
        'unmatched_publishers': 0,
    }
    mc = mcap_stats(tmp_path / 'bag')
    assert mc['topics']['/tapped'][0] == n
    assert mc['topics']['/tapped'][2:] == (t0, t0 + (n - 1) * 1_000_000)
    # 3 s in spans of 0.25 s: 12 chunks at least (0.249 s each when cut at 1 ms steps)
    assert mc['chunks'] >= 12 and max(mc['spans']) <= 0.25, mc['spans']
    values = [m.data[0] for m in rosbags_messages(tmp_path / 'bag', '/tapped')]
    np.testing.assert_array_equal(values, np.arange(n))


def rosbags_messages(bag: Path, topic: str) -> list:
    """The messages of ``topic``, deserialised by rosbags' AnyReader, in log-time order."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([bag], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [reader.deserialize(raw, c.msgtype) for c, _t, raw in reader.messages(conns)]


def _messages_on_disk(path: Path) -> int:
    """Message records in the complete chunks of a file still being written (the mcap
    library's streaming reader, stopped at the unfinished end)."""
    from mcap.exceptions import McapError
    from mcap.records import Message
    from mcap.stream_reader import StreamReader

    n = 0
    with open(path, 'rb') as f:
        try:
            for r in StreamReader(f, skip_magic=False).records:
                n += isinstance(r, Message)
        except (McapError, EOFError, ValueError, AssertionError):
            pass  # the end of a file whose chunk is not written yet
    return n


def test_a_recorder_nobody_polls_writes_its_first_message_within_max_chunk_age(
    ros_context, tmp_path, wait_until
):
    """The owner does not poll (a bench loading its kernels, a tuner busy elsewhere): the
    chunk timer takes the first message and hands its chunk to the OS within about
    max_chunk_age; it used to wait in memory until the next poll."""
    node = Node('first_pub', context=ros_context)
    pub = node.create_publisher(String, '/first', RELIABLE_ALL)
    rec = Recorder(
        Node('recorder', context=ros_context, start_parameter_services=False),
        tmp_path / 'bag',
        compression='none',
        max_chunk_age=0.2,
    )
    try:
        assert rec.wait_matched(10.0) and '/first' in rec.topics
        path = tmp_path / 'bag' / rec.file_name
        before = _messages_on_disk(path)
        pub.publish(String(data='state 0'))
        # no poll from here on: only the timer can take it and write its chunk
        wait_until(lambda: _messages_on_disk(path) > before, 10.0, 0.02, 'the message on disk')
        assert rec.messages >= 1
        counts = rec.close()
    finally:
        node.destroy_node()
    assert counts['/first']['recorded'] == 1 and counts['/first']['lost'] == 0
    mc = mcap_stats(tmp_path / 'bag')
    assert mc['topics']['/first'][0] == 1 and max(mc['spans']) <= 0.2


# -- real bags ---------------------------------------------------------------------------------
def _tune(out: Path, *bench: str) -> Path:
    r = subprocess.run(
        [
            *(ROS2, 'run', 'im_tuner', 'tuner', *bench, '--budget', '2', '--remeasure', '0'),
            *('--seed', '4', '--quiet', '--out', str(out)),
        ],
        capture_output=True,
        text=True,
        timeout=400,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    (bag,) = out.glob('bag_*')
    return bag


def _assert_chunks_within_the_bound(bag: Path) -> dict:
    mc = mcap_stats(bag)
    spans = mc['spans']  # in file order: the first chunk is spans[0]
    assert mc['chunks'] >= 3, spans
    assert spans[0] <= MAX_CHUNK_AGE and max(spans) <= MAX_CHUNK_AGE, spans
    info = bag_info(bag)  # report --bag-info says the same
    assert info['max_chunk_span_s'] == pytest.approx(max(spans), abs=1e-9)
    assert info['first_chunk_span_s'] == pytest.approx(spans[0], abs=1e-9)
    return mc


def test_a_lockstep_bag_has_chunks_of_at_most_half_a_second(tmp_path):
    _assert_chunks_within_the_bound(_tune(tmp_path / 'run'))


@pytest.mark.serial  # a real-time loop on the wall clock: alone, not beside another test
def test_a_realtime_bag_has_chunks_of_at_most_half_a_second_and_the_outbox_counts_equal_the_bag(
    tmp_path,
):
    run = tmp_path / 'run'
    bag = _tune(run, '--bench', 'realtime')
    mc = _assert_chunks_within_the_bound(bag)
    rb = rosbags_stats(bag)
    outbox_bag = {t: json.loads(row) for t, row in mc['metadata']['im_tuner.outbox'].items()}
    summary = json.loads((run / 'summary.json').read_text())
    outbox_summary = summary['sessions'][0]['drive']['loop']['outbox']
    assert set(outbox_bag) == set(outbox_summary) >= {'/drive/state', '/drive/status'}
    for topic, row in outbox_bag.items():
        count = mc['topics'][topic][0]
        assert row['put'] == outbox_summary[topic]['put'] == count == rb['topics'][topic][0], (
            topic,
            row,
            outbox_summary[topic],
            count,
        )
        assert row['lost_recorder'] == 0 and row['lost_dds'] == 0, (topic, row)
    assert mc['topics']['/drive/status'][0] >= 2  # the periodic ones and the last
