"""The real-time loop's outbox rings, pre-serialised messages and fixed-memory timings
(im_drive_sim.outbox, cdr, pacing): what the composed loop hands over instead of
publishing, and how what it could not hand over is counted. No DDS graph here
(test/test_realtime_outbox.py publishes them)."""

from __future__ import annotations

import numpy as np
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from im_drive_sim.cdr import ClockWire, Float64ArrayWire, JointStateWire
from im_drive_sim.outbox import R_HEAD, R_LOST, R_TAIL, R_TOO_BIG, Ring
from im_drive_sim.pacing import DurationHistograms


def test_a_ring_keeps_order_and_counts_what_did_not_fit():
    r = Ring(slot=16, capacity=4)
    for i in range(6):  # two more than it holds: the newest two are dropped, counted
        r.put(np.full(3 + i, i, np.uint8), stamp=1000 + i)
    assert (int(r.ctrl[R_HEAD]), int(r.ctrl[R_LOST]), r.pending) == (4, 2, 4)
    assert [int(n) for n in r.lens] == [3, 4, 5, 6]
    assert [int(s) for s in r.stamps] == [1000, 1001, 1002, 1003]
    assert all((r.buf[i, : 3 + i] == i).all() for i in range(4))
    # the consumer frees two slots: the next two puts land in them, in order
    r.ctrl[R_TAIL] = 2
    assert r.put(np.full(2, 9, np.uint8), 7) and r.put(np.full(2, 8, np.uint8), 8)
    assert (int(r.ctrl[R_HEAD]), r.pending) == (6, 4)
    assert list(r.buf[0, :2]) == [9, 9] and list(r.buf[1, :2]) == [8, 8]
    # a message larger than a slot is lost (and said to be too big), never truncated
    r.ctrl[R_TAIL] = 6
    assert not r.put(np.zeros(17, np.uint8), 9)
    assert (int(r.ctrl[R_LOST]), int(r.ctrl[R_TOO_BIG]), int(r.ctrl[R_HEAD])) == (3, 1, 6)


def test_a_read_only_buffer_goes_in_like_a_wire():
    r = Ring(slot=32, capacity=2)
    raw = serialize_message(Clock())
    assert r.put(np.frombuffer(raw, np.uint8), 5)
    assert bytes(r.buf[0, : r.lens[0]]) == raw


def test_pre_serialised_joint_state_and_clock_equal_rclpy_messages():
    j = JointStateWire('motor')
    j.sec[0], j.nanosec[0] = 12, 345_000_000
    j.position[0], j.velocity[0], j.effort[0] = 1.25, -3.5, 0.75
    m = deserialize_message(bytes(j.raw), JointState)
    assert (m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id) == (12, 345_000_000, '')
    assert (list(m.name), list(m.position), list(m.velocity), list(m.effort)) == (
        ['motor'],
        [1.25],
        [-3.5],
        [0.75],
    )
    c = ClockWire()
    c.sec[0], c.nanosec[0] = 7, 800_000
    got = deserialize_message(c.payload(), Clock)
    assert (got.clock.sec, got.clock.nanosec) == (7, 800_000)
    assert len(c.raw) == len(serialize_message(Clock()))
    f = Float64ArrayWire(3)
    f.values[:] = (1.0, 2.0, 3.0)
    assert bytes(f.raw) == f.payload()  # the outbox takes the raw view, no copy


def test_duration_histograms_percentiles_within_a_microsecond_in_fixed_memory():
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.gamma(3.0, 8.0, 50_000), [15_000.0, 250_000.0]])
    y = rng.uniform(0.0, 100.0, len(x))
    y[:3] = (-5.0, float('nan'), 30_000.0)  # counted in the first and the last bin
    h = DurationHistograms(('x', 'y'), limit_us=20_000)
    assert h.summary('x') is None and np.isnan(h.percentile('y', 50))
    size = h.counts.nbytes
    for a, b in zip(x, y, strict=True):
        h.add((float(a), float(b)))
    assert h.counts.nbytes == size and h.n == len(x)
    assert h.counts[0].sum() == h.counts[1].sum() == len(x)
    assert h.counts[1, 0] == 2 + np.sum((y >= 0.0) & (y < 1.0)) and h.counts[1, -1] == 1
    for q in (50, 90, 99):
        assert abs(h.percentile('x', q) - np.percentile(x, q)) <= 1.0, q
        assert abs(h.percentile('y', q) - np.nanpercentile(y, q)) <= 1.5, q
    s = h.summary('x')
    assert s is not None and s['max'] == 250_000.0
    assert h.summary('y')['max'] == 30_000.0
