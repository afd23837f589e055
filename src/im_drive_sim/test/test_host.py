"""The host's floor and its verdict (``im_drive_sim.host``; docs/real-drive.md, "Check
the host first"): the verdict's logic on held periods the test places (a clock the test
controls), and one short measurement of the loop's real wait, whose figures add up."""

from __future__ import annotations

import math

import numpy as np
import pytest

from im_drive_sim import host

W = host.EXPERIMENT_PERIODS


def test_a_quiet_host_meets_every_tolerance():
    v = host.judge(np.zeros(50_000, np.int64), tolerance=0)
    assert v['share_meeting'] == 1.0 and v['tolerance'] == 0 and v['meets'] is True
    assert v['loss_change_pct'] == 0.0 and v['held_per_experiment']['from'] == 'windows'


def test_one_stall_is_judged_over_every_experiment_long_window():
    held = np.zeros(50_000, np.int64)
    held[10_000] = 20  # a 4 ms stall: 20 periods held at once
    v = host.judge(held, tolerance=10)
    windows = 50_000 - W + 1
    assert v['share_meeting'] == pytest.approx(1 - W / windows)  # 12.7 % of windows hold it
    assert v['meets'] is False and v['tolerance'] == 20  # (p95 falls among them)
    assert v['loss_change_pct'] == 8.77  # a 20-period burst: the table's worst row
    assert v['held_per_experiment'] == {'p50': 0.0, 'p95': 20.0, 'max': 20.0, 'from': 'windows'}


def test_scattered_single_periods_set_the_tolerance_at_the_95th_percentile():
    held = np.zeros(100_000, np.int64)
    held[::2500] = 1  # one held period every 0.5 s: 2-3 per experiment
    v = host.judge(held, tolerance=2)
    per = np.convolve(held, np.ones(W, np.int64), 'valid')
    assert v['tolerance'] == int(np.quantile(per, 0.95, method='higher')) == 3
    assert v['share_meeting'] == pytest.approx(np.mean(per <= 2))
    assert v['loss_change_pct'] == 1.40


def test_a_measurement_shorter_than_an_experiment_is_judged_on_its_rate():
    held = np.zeros(2_000, np.int64)
    held[[5, 700]] = 1
    v = host.judge(held, tolerance=10)
    assert v['held_per_experiment']['from'] == 'rate'
    assert v['tolerance'] == round(2 * W / 2_000) == 6 and v['meets'] is True


def test_the_loss_change_is_the_held_period_table_of_the_docs():
    assert [host.loss_change_pct(n) for n in (0, 1, 2, 3, 10, 11, 50)] == [
        0.0, 0.83, 1.40, 1.40, 1.95, 8.77, 8.77,
    ]  # fmt: skip
    assert math.isinf(host.loss_change_pct(51))  # beyond what was measured


def test_bursts_merge_adjacent_skips_and_count_by_length():
    held = np.zeros(200, np.int64)
    held[3], held[4] = 1, 2  # one burst of 3
    held[10], held[11], held[12] = 1, 1, 5  # one of 7
    held[50] = 60  # one of 60
    held[190] = 1
    bursts, longest = host._bursts(held)
    assert bursts == {'1': 1, '2-4': 1, '5-9': 1, '10-49': 0, '>=50': 1} and longest == 60


def test_a_short_measurement_of_the_real_wait_adds_up():
    f = host.measure(0.5)
    assert f.periods >= 2500 and 0.45 < f.seconds < 5.0
    assert sum(f.histogram.values()) + f.held == f.periods  # every period: started or held
    assert f.overruns <= f.held and f.late_pct == pytest.approx(100 * f.overruns / f.periods)
    assert f.held_per_experiment['from'] == 'rate' and f.spin_us == host.SPIN_US
    d = f.as_dict()
    assert {'late_pct', 'tolerance', 'meets', 'histogram', 'bursts'} <= d.keys()


def _floor(held_total: int, tolerance: int, meets: bool) -> host.HostFloor:
    """A measurement the test makes up (the check's logic on figures it controls)."""
    return host.HostFloor(
        seconds=2.0, spin_us=40.0, periods=10_000, overruns=3, held=held_total,
        late_pct=0.03, held_pct=held_total / 100, late_per_s=1.5, max_lateness_us=2600.0,
        histogram={}, bursts={}, longest_burst=12,
        held_per_experiment={'p50': 5.0, 'p95': float(tolerance), 'max': 47.0, 'from': 'windows'},
        tolerance_checked=10, share_meeting=0.8 if not meets else 1.0, tolerance=tolerance,
        loss_change_pct=host.loss_change_pct(tolerance), meets=meets,
        realtime={'policy': 'SCHED_FIFO', 'pm_qos': {'held': True}},
    )  # fmt: skip


def test_a_host_that_cannot_meet_the_tolerance_is_told_so_in_one_line(monkeypatch):
    monkeypatch.setattr(host, 'probe', lambda *a, **k: _floor(61, 41, meets=False))
    tol, record, line = host.check_before_run(10, 10)
    assert tol == 10 and record['auto'] is False and record['meets'] is False
    assert line == (
        'this host cannot meet --timing-tolerance 10: 80 % of experiments would (2.0 s host '
        'check: late 0.030 % of periods, worst 2.6 ms); 95 % meet 41 (a loss may change by '
        'up to 8.77 %, 95th percentile): give --timing-tolerance auto, or quieten the host '
        '(docs/real-drive.md, "Check the host first")'
    )
    assert 'realtime' not in record and record['pm_qos_held'] is True


def test_auto_takes_what_the_host_meets_never_below_the_default(monkeypatch):
    monkeypatch.setattr(host, 'probe', lambda *a, **k: _floor(61, 41, meets=False))
    tol, record, line = host.check_before_run('auto', 10)
    assert tol == 2 * 41 == record['tolerance_chosen'] and record['auto'] is True
    assert line.startswith('timing tolerance auto: 82 held periods per experiment (2.0 s host')
    assert '95 % of its experiments meet 41, a whole run holds up to 2x that' in line, line
    assert 'more than the 50 held periods whose effect on a loss was measured' in line, line
    monkeypatch.setattr(host, 'probe', lambda *a, **k: _floor(1, 2, meets=True))
    tol, record, line = host.check_before_run('auto', 10)
    assert tol == 10 and record['tolerance'] == 2  # a quiet host keeps the default
    assert 'a loss may change by up to 1.95 %' in line, line
    tol, _record, line = host.check_before_run(10, 10)
    assert tol == 10 and line is None  # a host that meets it: nothing to say


def test_the_tolerance_option_takes_a_count_or_auto():
    import argparse

    assert host.tolerance_arg('auto') == 'auto' and host.tolerance_arg(' AUTO ') == 'auto'
    assert host.tolerance_arg('0') == 0 and host.tolerance_arg('1000000') == 1_000_000
    for bad, says in (
        ('-1', 'must be in [0, 1000000] periods, got -1'),
        ('x', "not an integer or 'auto'"),
    ):
        with pytest.raises(argparse.ArgumentTypeError, match=says.replace('[', r'\[')):
            host.tolerance_arg(bad)
