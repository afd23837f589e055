"""The wall-clock schedule (:class:`im_drive_sim.pacing.Pacer`): a drive that pauses
re-anchors after a late start; a drive that cannot pause (``wall_clock``) reports the
whole periods that went by, and its schedule stays on the wall clock.

The stall is made with a sleep of a known length (the thing under test is what the
schedule does after a late start); no assertion depends on the sleep being exact."""

from __future__ import annotations

import time

import pytest

from im_drive_sim.pacing import Pacer

TS = 1e-3  # [s] a long period: the test's own jitter stays far below it


def _never(_s: float) -> bool:
    return False


def _stalled(wall_clock: bool, stall_s: float) -> tuple[Pacer, dict[str, int]]:
    """A pacer after one period, a stall of ``stall_s`` and the next start; with its
    counters from before the stall (a loaded machine may have made period 1 late too)."""
    p = Pacer(TS, 0.0, wall_clock=wall_clock)
    p.wait(_never, lambda: None)  # period 1
    before = {'n': p.n, 'missed_total': p.missed_total, 'overruns': p.overruns}
    time.sleep(stall_s)  # the loop stalls
    p.wait(_never, lambda: None)
    return p, before


@pytest.mark.parametrize('stall_ms', [5.5, 20.3])
def test_a_drive_that_cannot_pause_counts_the_periods_that_went_by(stall_ms):
    p, b = _stalled(True, stall_ms * 1e-3)
    # the start came >= stall - 1 period late: that many whole periods went by
    assert p.missed >= int(stall_ms) - 1
    assert p.missed_total == b['missed_total'] + p.missed
    assert p.overruns == b['overruns'] + 1
    # period n starts at t0 + n Ts: the schedule kept the wall clock (no re-anchor) ...
    assert p.deadline == pytest.approx(p.t0 + p.n * TS, rel=0, abs=1e-9)  # 1 ns of rounding
    assert p.n == b['n'] + 1 + p.missed
    # ... and the start is less than a period after its (new) deadline
    assert 0.0 <= p.lateness_s < TS


def test_a_drive_that_pauses_reanchors_and_misses_nothing():
    p, b = _stalled(False, 5.5e-3)
    assert (p.missed, p.missed_total) == (0, 0)
    assert (p.overruns, p.n) == (b['overruns'] + 1, b['n'] + 1)
    assert p.lateness_s > 4 * TS  # the lateness is reported, and the schedule re-anchored
    assert p.deadline == pytest.approx(p.t0 + p.n * TS, rel=0, abs=1e-9)  # 1 ns of rounding


def test_the_lateness_histogram_puts_each_start_in_its_bin():
    """A stall of 5.5 ms: that start lands in the 1-10 ms bin (or beyond, on a loaded
    machine); every start is in exactly one bin."""
    from im_drive_sim.pacing import LATENESS_BINS, LATENESS_EDGES_US

    assert len(LATENESS_BINS) == len(LATENESS_EDGES_US) + 1
    p, b = _stalled(False, 5.5e-3)
    assert sum(p.lateness_hist) == p.n == b['n'] + 1
    assert p.lateness_hist[4] + p.lateness_hist[5] >= 1
