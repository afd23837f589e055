"""The command-delay probe on a power stage that runs on its own clock, preempted once:
a late probe period must not be caught up in a burst (every write of the burst would land
in one of the stage's periods, the last, zero, would win and the step be "not seen").
A fake clock makes the stall exact and the test deterministic."""

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
    """A stage paced by ``clock``, command delay 2: the last write of its period p is the
    current of period p + 1, which a read in period p + 1 returns (the probe's onset 2:
    the read of the period after the one that starts with the write). ``stall_on``: the
    writes (1-based) before which the process is preempted for ``stall`` s."""

    def __init__(self, clock: Clock, stall_on: set[int], stall: float) -> None:
        self.clock, self.stall_on, self.stall = clock, stall_on, stall
        self.writes: dict[int, float] = {}  # stage period -> its last write
        self.n = 0

    def _period(self) -> int:
        return math.floor(self.clock.t / TS)

    def _current(self, p: int) -> float:
        before = [q for q in self.writes if q < p]
        return self.writes[max(before)] if before else 0.0

    def write(self, isq_ref: float, load_torque: float) -> None:
        self.n += 1
        if self.n in self.stall_on:
            self.clock.t += self.stall
        self.writes[self._period()] = isq_ref

    def read(self) -> SimpleNamespace:
        return SimpleNamespace(isq=self._current(self._period()))


def _probe(monkeypatch: pytest.MonkeyPatch, stall_on: set[int], stall: float):
    clock = Clock()
    monkeypatch.setattr(hardware_probe.time, 'perf_counter', clock)
    stage = WallClockStage(clock, stall_on, stall)
    return hardware_probe.probe_delay(stage, TS, 10.0, 2), stage


def test_an_undisturbed_probe_sees_the_declared_delay_every_time(monkeypatch) -> None:
    probe, stage = _probe(monkeypatch, set(), 0.0)
    assert probe.onsets == (2, 2, 2, 2) and probe.ok
    per_repeat = hardware_probe.BASELINE + hardware_probe.ON + hardware_probe.SETTLE
    assert stage.n == hardware_probe.REPEATS * per_repeat + 1  # (+ the final zero)


@pytest.mark.parametrize('stall_periods', [2.5, 10, 40])
def test_a_stall_before_the_step_is_not_caught_up_in_a_burst(monkeypatch, stall_periods) -> None:
    """The process preempted just before the second repeat's step: the step's three writes
    (and the zeros after them) would all fall in one stage period if the probe caught up."""
    per_repeat = hardware_probe.BASELINE + hardware_probe.ON + hardware_probe.SETTLE
    first_step_write = per_repeat + hardware_probe.BASELINE + 1
    probe, stage = _probe(monkeypatch, {first_step_write}, stall_periods * TS)
    assert probe.onsets == (2, 2, 2, 2), probe.text()
    # the preempted repeat was run again: one repeat's writes more
    assert stage.n == (hardware_probe.REPEATS + 1) * per_repeat + 1


def test_a_stage_preempted_in_every_repeat_still_ends(monkeypatch) -> None:
    """At most REPEATS repeats are run again; the probe then judges what it measured."""
    per_repeat = hardware_probe.BASELINE + hardware_probe.ON + hardware_probe.SETTLE
    stalls = {k * per_repeat + 3 for k in range(3 * hardware_probe.REPEATS)}
    probe, stage = _probe(monkeypatch, stalls, 5 * TS)
    assert len(probe.onsets) == hardware_probe.REPEATS
    assert stage.n == 2 * hardware_probe.REPEATS * per_repeat + 1
    assert probe.ok and probe.fastest == 2
