"""The wall-clock tests' judgement of a run against its host (conftest.HostFloor.run_judged),
on runs and host measurements the test makes up: a run later than the floor while its own
work was short is made once more after the host is measured again; it skips only when
some measurement in the test found the host louder, and a late run on a host every
measurement found quiet is returned for the caller to fail."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

QUIET = {
    'seconds': 8.0,
    'late_pct': 0.01,
    'held_pct': 0.02,
    'max_lateness_us': 300.0,
    'held_per_experiment': {'p50': 0.0, 'p95': 2.0, 'max': 3.0},
    'tolerance': 2,
}
LOUD = {
    **QUIET,
    'late_pct': 2.5,
    'held_pct': 6.0,
    'max_lateness_us': 12000.0,
    'held_per_experiment': {'p50': 300.0, 'p95': 800.0, 'max': 900.0},
    'tolerance': 800,
}


def _run(tmp_path: Path, name: str, rc: int, overruns: int, work: float, check=None):
    """A finished run: its process (exit ``rc``) and a run directory whose summary.json
    says ``overruns`` of 10000 periods and a period work p50 of ``work`` us."""
    run = tmp_path / name
    run.mkdir()
    loop = {'period_work_us': {'p50': work}, 'realtime': {'host_check': check}}
    drive = {'steps': 10000, 'overruns': overruns, 'held': overruns, 'max_lateness_us': 9e3}
    summary = {'sessions': [{'drive': {**drive, 'loop': loop}}]}
    (run / 'summary.json').write_text(json.dumps(summary))
    return subprocess.CompletedProcess(['tuner'], rc, '', ''), run


class Runs:
    """A start function that plays the given runs in turn and notes the tolerances."""

    def __init__(self, tmp_path: Path, *plays: tuple) -> None:
        self.tmp_path, self.plays, self.tolerances = tmp_path, list(plays), []

    def __call__(self, tolerance: int):
        self.tolerances.append(tolerance)
        return _run(self.tmp_path, f'run{len(self.tolerances)}', *self.plays.pop(0))


@pytest.fixture
def floor(host_floor_type, monkeypatch):
    """The quiet floor; ``floor.rechecks`` lists what a re-check of the host returns."""
    f = host_floor_type(QUIET)
    f.rechecks = []  # type: ignore[attr-defined]
    module = sys.modules[host_floor_type.__module__]
    monkeypatch.setattr(module, 'measure_host', lambda seconds: f.rechecks.pop(0))
    return f


def test_a_run_that_completes_is_run_once_at_the_floors_tolerance(floor, tmp_path):
    runs = Runs(tmp_path, (0, 500, 6.0))
    p, run, tol = floor.run_judged(runs)
    assert (p.returncode, run.name, tol, runs.tolerances) == (0, 'run1', 10, [10])


def test_a_failed_run_no_later_than_the_floor_is_the_codes_at_once(floor, tmp_path):
    # 0.02 % late: within 2 x 0.01 % + 0.05 %
    runs = Runs(tmp_path, (1, 2, 6.0))
    p, run, _ = floor.run_judged(runs)
    assert (p.returncode, run.name, runs.tolerances) == (1, 'run1', [10])


def test_a_late_run_whose_own_work_is_slow_is_the_codes_at_once(floor, tmp_path):
    runs = Runs(tmp_path, (1, 3000, 150.0))
    p, run, _ = floor.run_judged(runs)
    assert (p.returncode, run.name, runs.tolerances) == (1, 'run1', [10])


def test_a_late_run_is_made_again_at_the_tolerance_of_the_host_measured_again(floor, tmp_path):
    floor.rechecks.append({**QUIET, 'tolerance': 20})  # louder: 3 x 20 = 60
    runs = Runs(tmp_path, (1, 500, 6.0), (0, 500, 6.0))
    p, run, tol = floor.run_judged(runs)
    assert (p.returncode, run.name, tol, runs.tolerances) == (0, 'run2', 60, [10, 60])


def test_two_late_runs_on_a_host_measured_louder_skip_with_the_figures(floor, tmp_path):
    floor.rechecks.append({**QUIET, 'late_pct': 0.5})
    runs = Runs(tmp_path, (1, 500, 6.0), (1, 600, 6.0))
    with pytest.raises(pytest.skip.Exception) as skipped:
        floor.run_judged(runs)
    why = str(skipped.value)
    assert 'louder than its floor' in why and 'late 5.00 % of 10000 periods' in why, why
    assert 'late 6.00 %' in why and 'late 0.500 %' in why, why


def test_a_run_whose_own_check_found_the_host_loud_skips_the_second_time(floor, tmp_path):
    floor.rechecks.append(QUIET)
    runs = Runs(tmp_path, (1, 500, 6.0, LOUD), (1, 600, 6.0))
    with pytest.raises(pytest.skip.Exception):
        floor.run_judged(runs)


def test_two_late_runs_on_a_host_every_measurement_found_quiet_are_the_codes(floor, tmp_path):
    floor.rechecks.append(QUIET)
    runs = Runs(tmp_path, (1, 500, 6.0, QUIET), (1, 600, 6.0, QUIET))
    p, run, tol = floor.run_judged(runs)
    assert (p.returncode, run.name, tol, runs.tolerances) == (1, 'run2', 10, [10, 10])


def test_a_host_measured_hopeless_after_a_late_run_skips(floor, tmp_path):
    floor.rechecks.append(LOUD)  # 3 x 900 > 1000
    runs = Runs(tmp_path, (1, 500, 6.0))
    with pytest.raises(pytest.skip.Exception) as skipped:
        floor.run_judged(runs)
    assert 'cannot run a 5 kHz wall-clock loop' in str(skipped.value)
    assert runs.tolerances == [10]


HOPELESS = {**LOUD, 'held_per_experiment': {'p50': 900.0, 'p95': 1600.0, 'max': 1700.0}}
HOPELESS['tolerance'] = 1600


def test_a_hopeless_floor_is_measured_again_and_a_quiet_one_kept(floor, host_floor_type):
    f = host_floor_type(HOPELESS)
    f.taken = float('-inf')  # measured long ago
    floor.rechecks.append(QUIET)
    f.require()  # no skip: the host is quiet now
    assert f['late_pct'] == QUIET['late_pct'] and f.tolerance == 10
    assert floor.rechecks == []


def test_a_floor_hopeless_twice_skips_with_both_measurements(floor, host_floor_type):
    f = host_floor_type(HOPELESS)
    f.taken = float('-inf')
    floor.rechecks.append({**HOPELESS, 'late_pct': 4.0})
    with pytest.raises(pytest.skip.Exception, match=r'late 2\.500 %.*again: .*late 4\.000 %'):
        f.require()
    # measured just now: the next test skips on it without measuring again
    with pytest.raises(pytest.skip.Exception, match=r'late 4\.000 %'):
        f.require()
