"""The composed real-time loop publishes through an outbox (docs/real-drive.md,
"Real-time set-up"): its thread only hands messages over, a publisher thread publishes
them with the GIL released, the run's recorder takes them from a tap ring.

* every message handed over reaches a DDS reader, in order, byte for byte;
* a ring that overflows loses messages, never the loop: what was lost is counted, in the
  loop's figures (the summary's ``loop.outbox``), the bag's ``im_tuner.outbox`` metadata
  and the recorder's counts, and one line says so;
* a reliable reader frozen (SIGSTOP) next to a tuning run stalls nothing: the run is
  done, no experiment is off the paper timing, nothing failed to publish, and the bag is
  lossless.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray

from im_drive_sim.cdr import Float64ArrayWire
from im_drive_sim.outbox import Outbox, PublisherThread
from im_drive_sim.runtime import ROUTES, publish_lossless
from im_tuner.bench.forms import say_outbox_losses
from im_tuner.bench.realtime import RealtimeBench
from im_tuner.record.node import Recorder

sys.path.insert(0, str(Path(__file__).parent))
from test_faults import bag_counts, results, ros2

FROZEN_READER = Path(__file__).resolve().parents[1] / 'benchmarks' / 'frozen_reader.py'

# wall-clock timing is asserted: alone, after the tests that run on two workers
pytestmark = pytest.mark.serial


def test_the_publisher_thread_delivers_every_message_in_order(ros_context, wait_until):
    node = Node('outbox_pub', context=ros_context)
    reader = Node('outbox_reader', context=ros_context)
    qos = QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE
    )
    pub = node.create_publisher(Float64MultiArray, '/outbox_test', qos)
    sub = reader.create_subscription(
        Float64MultiArray,
        '/outbox_test',
        lambda _m: None,
        QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE),
        raw=True,
    )
    wait_until(lambda: pub.get_subscription_count() == 1, 10.0, message='the reader to match')
    box = Outbox()
    box.add(pub, 'std_msgs/msg/Float64MultiArray', 256, 512)
    ROUTES[id(pub)] = box
    thread = PublisherThread(box.channels[0], period=0.001)
    wire = Float64ArrayWire(3)
    got: list[bytes] = []

    def take() -> int:
        while (r := sub.handle.take_message(Float64MultiArray, True)) is not None:
            got.append(r[0])
        return len(got)

    try:
        for i in range(3000):
            wire.values[:] = (i, 2.0 * i, -i)
            assert publish_lossless(pub, wire, ros_context) == 0  # handed over, no retry
            if i % 200 == 199:  # a producer the publisher keeps up with (the ring holds 512)
                wait_until(lambda: box.pending() == 0, 10.0, 0.001, 'the ring to drain')
                take()
        wait_until(lambda: take() >= 3000, 20.0, message='all 3000 messages')
    finally:
        thread.stop()
        ROUTES.pop(id(pub), None)
    vals = np.array([np.frombuffer(b, '<f8', 3, 20) for b in got])
    np.testing.assert_array_equal(vals[:, 0], np.arange(3000))
    np.testing.assert_array_equal(vals[:, 1], 2.0 * np.arange(3000))
    c = box.counts()['/outbox_test']
    assert c == {
        'put': 3000,
        'published': 3000,
        'lost_dds': 0,
        'publish_failed': 0,
        'too_big': 0,
    }, c
    assert box.lost() == 0
    node.destroy_node()
    reader.destroy_node()


def test_an_outbox_overflow_is_counted_in_the_figures_the_bag_and_one_line(
    ros_context, tmp_path, wait_until, capsys
):
    """The recorder is not polled for 1500 periods while its tap ring holds 64: the loop
    runs on (its periods all fresh), and the loss is counted everywhere it is reported.
    The recorder's chunk timer is off here: it would drain the ring whenever the owner has
    not polled for 0.125 s, and how often it does depends on the host's pace."""
    rec: list[Recorder] = []

    def start_recorder(b: RealtimeBench) -> None:
        rec.append(
            Recorder(
                Node('recorder', context=ros_context, start_parameter_services=False),
                tmp_path / 'bag',
                taps=b.outbox.tap(),
                flush_timer=False,
            )
        )

    bench = RealtimeBench(context=ros_context, before_start=start_recorder, outbox_capacity=64)
    try:
        start = bench.periods
        # the serving thread does nothing meanwhile: the recorder's tap ring overflows
        wait_until(lambda: bench.periods >= start + 1500, 30.0, message='1500 periods')
        bench.spin_until(lambda: False, timeout=0.2)  # serve again: the rest is recorded
        bench.final_status()
        loop = bench.timing()
        r = rec[0]
        r.add_metadata('im_tuner.outbox', bench.outbox.counts())
        say_outbox_losses(bench.outbox)
        counts = r.close()
    finally:
        bench.destroy()
    st = loop['outbox']['/drive/state']
    assert st['lost_recorder'] >= 1000 and st['lost_dds'] == 0, st
    assert loop['outbox_lost'] >= st['lost_recorder']
    # every period fresh but the last (zero current after the stop)
    assert loop['drive']['held'] <= 1 and loop['answers_missed'] == 0, loop
    # the recorder's own counts: what it recorded plus what the ring lost is what was put
    c = counts['/drive/state']
    assert c['lost'] == st['lost_recorder'] and c['recorded'] + c['lost'] == c['published'], c
    assert bag_counts(tmp_path / 'bag')['/drive/state'] == c['recorded']
    with open(next((tmp_path / 'bag').glob('*.mcap')), 'rb') as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert (
        json.loads(meta['im_tuner.outbox']['/drive/state'])['lost_recorder'] == st['lost_recorder']
    )
    err = capsys.readouterr().err
    line = [x for x in err.splitlines() if 'could not deliver' in x]
    assert len(line) == 1 and '/drive/state' in line[0], err


def test_a_frozen_reliable_reader_stalls_nothing_and_the_bag_stays_lossless(procs, tmp_path):
    reader = procs.start([sys.executable, str(FROZEN_READER)], stdout=subprocess.PIPE)
    run = tmp_path / 'run'
    tuner = procs.start(
        [
            *ros2('im_tuner', 'tuner', '--bench', 'realtime', '--budget', '4', '--seed', '4'),
            *('--remeasure', '0', '--quiet', '--out', str(run)),
        ]
    )
    # (5 experiments, ~8 s: the reader is ready 1-2 s into them on a loaded machine)
    # freeze the reader once it took 100 states (matched with every publisher)
    assert reader.stdout is not None
    assert reader.stdout.readline().strip() == 'ready'
    reader.send_signal(signal.SIGSTOP)
    frozen_at = time.monotonic()
    try:
        _out, err = tuner.communicate(timeout=240)
    finally:
        reader.send_signal(signal.SIGCONT)
    assert tuner.returncode == 0, err[-3000:]
    assert time.monotonic() - frozen_at > 5.0  # the run went on while it was frozen
    recs = results(run)
    assert recs and all(r['status'] == 'ok' for r in recs), [(r['kind'], r['status']) for r in recs]
    loop = json.loads((run / 'summary.json').read_text())['sessions'][0]['drive']['loop']
    assert loop['drive']['held'] <= 1 and loop['answers_missed'] == 0, loop
    for topic, c in loop['outbox'].items():
        # the recorder's tap lost nothing; what DDS did not take is counted, not lost
        # silently (a topic the frozen reader holds back may lose its DDS copy)
        assert c['lost_recorder'] == 0, (topic, c)
        assert c['published'] + c['lost_dds'] + c['publish_failed'] <= c['put'], (topic, c)
    # the topics the tuner itself needs reached it: one thread per topic
    assert loop['outbox']['/controller/loss']['published'] == len(recs), loop['outbox']
    (bag,) = run.glob('bag_*')
    counts = bag_counts(bag)
    for topic in ('/drive/state', '/drive/command', '/controller/internals'):
        assert counts[topic] == loop['outbox'][topic]['put'], (topic, counts)
    assert counts['/controller/loss'] == len(recs)
    assert counts['/tuner/result'] == len(recs)  # the tuner's, beside the loop's
