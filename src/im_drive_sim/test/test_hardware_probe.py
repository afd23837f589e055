"""The command-delay probe on a power stage that runs on its own clock: preempted once, a
late probe period must not be caught up in a burst (every write of the burst would land
in one of the stage's periods, the last, zero, would win and the step be "not seen");
with its calls close to the stage's period boundaries (the phase the probe cannot see),
or with reads that run late across one, the probe must still judge the delay the stage
has. A fake clock makes the stalls exact and the tests deterministic."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from im_drive_sim import hardware_probe

pytestmark = pytest.mark.unit

TS = 2e-4  #: the probe's and the stage's period [s]
TICK = 1e-6  #: what one clock reading costs [s]


class Clock:
    """perf_counter for the probe: 1 us per reading, plus the stalls the stage makes."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        self.t += TICK
        return self.t


class WallClockStage:
    """A stage paced by ``clock``, command delay ``delay`` (2 by default): the last write of
    its period p is the current of period p + delay - 1, which a read in that period
    returns (onset 2: the read of the period after the one that starts with the write).
    ``stall_on``: the writes (1-based) before which the process is preempted for
    ``stall`` s. ``offset``: where the stage's period boundaries lie [s, mod TS];
    ``read_stall(n)``: how long the n-th read (1-based) takes before it samples [s]."""

    def __init__(
        self,
        clock: Clock,
        stall_on: set[int],
        stall: float,
        *,
        delay: int = 2,
        offset: float = 0.0,
        read_stall=lambda n: 0.0,
    ) -> None:
        self.clock, self.stall_on, self.stall = clock, stall_on, stall
        self.delay, self.offset, self.read_stall = delay, offset, read_stall
        self.writes: dict[int, float] = {}  # stage period -> its last write
        self.n = self.reads = 0

    def _period(self) -> int:
        return math.floor((self.clock.t - self.offset) / TS)

    def _current(self, p: int) -> float:
        before = [q for q in self.writes if q <= p - self.delay + 1]
        return self.writes[max(before)] if before else 0.0

    def write(self, isq_ref: float, load_torque: float) -> None:
        self.n += 1
        if self.n in self.stall_on:
            self.clock.t += self.stall
        self.writes[self._period()] = isq_ref

    def read(self) -> SimpleNamespace:
        self.reads += 1
        self.clock.t += self.read_stall(self.reads)
        return SimpleNamespace(isq=self._current(self._period()))


def _probe(
    monkeypatch: pytest.MonkeyPatch, stall_on: set[int], stall: float, declared: int = 2, **stage
):
    clock = Clock()
    monkeypatch.setattr(hardware_probe.time, 'perf_counter', clock)
    hw = WallClockStage(clock, stall_on, stall, **stage)
    return hardware_probe.probe_delay(hw, TS, 10.0, declared), hw


def test_an_undisturbed_probe_sees_the_declared_delay_every_time(monkeypatch) -> None:
    probe, stage = _probe(monkeypatch, set(), 0.0)
    assert probe.onsets == (2,) * hardware_probe.REPEATS and probe.ok
    assert probe.text() == (
        'a current step takes effect in k+2 (median of k+2, k+2, k+2, k+2, k+2; '
        'declared command delay 2)'
    )
    per_repeat = hardware_probe.BASELINE + hardware_probe.ON + hardware_probe.SETTLE
    assert stage.n == hardware_probe.REPEATS * per_repeat + 1  # (+ the final zero)


@pytest.mark.parametrize('stall_periods', [2.5, 10, 40])
def test_a_stall_before_the_step_is_not_caught_up_in_a_burst(monkeypatch, stall_periods) -> None:
    """The process preempted just before the second repeat's step: the step's three writes
    (and the zeros after them) would all fall in one stage period if the probe caught up."""
    per_repeat = hardware_probe.BASELINE + hardware_probe.ON + hardware_probe.SETTLE
    first_step_write = per_repeat + hardware_probe.BASELINE + 1
    probe, stage = _probe(monkeypatch, {first_step_write}, stall_periods * TS)
    assert probe.onsets == (2,) * hardware_probe.REPEATS, probe.text()
    # the preempted repeat was run again: one repeat's writes more
    assert stage.n == (hardware_probe.REPEATS + 1) * per_repeat + 1


def test_a_stage_preempted_in_every_repeat_still_ends(monkeypatch) -> None:
    """At most REPEATS repeats are run again; the probe then judges what it measured."""
    per_repeat = hardware_probe.BASELINE + hardware_probe.ON + hardware_probe.SETTLE
    stalls = {k * per_repeat + 3 for k in range(3 * hardware_probe.REPEATS)}
    probe, stage = _probe(monkeypatch, stalls, 5 * TS)
    assert len(probe.onsets) == hardware_probe.REPEATS
    assert stage.n == 2 * hardware_probe.REPEATS * per_repeat + 1
    assert probe.ok and probe.onset == 2


# the stage's boundaries 0.05 of a period after the first repeat's writes (the probe's
# first repeat starts a fifth of a period after the probe's clock was read)
NEAR_THE_BOUNDARY = TS / hardware_probe.REPEATS + 0.05 * TS


def test_reads_across_the_stages_boundary_do_not_pass_a_stage_slower_than_declared(
    monkeypatch,
) -> None:
    """Delay 3, declared 2. Every read takes 0.1 of a period; in a repeat whose writes
    fall within that of the stage's next boundary, the read samples the next period and
    the step shows a period early (onset 2). With one phase for all repeats that is every
    repeat, and the fastest onset passed the stage; with the phases spread over the
    period it is at most one repeat, and the median refuses the stage."""
    probe, _ = _probe(
        monkeypatch, set(), 0.0, delay=3, offset=NEAR_THE_BOUNDARY, read_stall=lambda n: 0.1 * TS
    )
    assert sorted(probe.onsets) == [2, 3, 3, 3, 3], probe.text()
    assert probe.onset == 3 and not probe.ok
    assert 'takes effect in k+3 (median of ' in probe.text()


def test_one_late_read_after_the_step_reruns_its_repeat(monkeypatch) -> None:
    """A delay-2 stage; the first read after the first step's write runs 0.3 of a period
    late (not late enough to move the schedule): the time of the reads around the step
    varied by more than JITTER, so that repeat is run again, not counted (it would have
    seen the step at k+1 wherever the read crossed the boundary)."""
    first_step_read = hardware_probe.BASELINE + 1
    probe, stage = _probe(
        monkeypatch,
        set(),
        0.0,
        offset=NEAR_THE_BOUNDARY,
        read_stall=lambda n: 0.3 * TS if n == first_step_read else 0.0,
    )
    assert probe.onsets == (2,) * hardware_probe.REPEATS and probe.ok, probe.text()
    per_repeat = hardware_probe.BASELINE + hardware_probe.ON + hardware_probe.SETTLE
    assert stage.n == (hardware_probe.REPEATS + 1) * per_repeat + 1
