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
