"""The ratio-10 drives' start does not chatter at the current limit
(docs/drive-family.md, "Start gains"): one encoder count is a quarter of isq_max, measured
(research/family_start.py) against the start by the inertia rule alone; the paper's start
is the paper's exactly."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

from im_controller.config import Gains
from im_tuner.family import COUNT_STEP_MAX, count_step, drive_setup, start_scale

SCRIPT = Path(__file__).resolve().parents[1] / 'research' / 'family_start.py'
_spec = importlib.util.spec_from_file_location('family_start', SCRIPT)
assert _spec is not None and _spec.loader is not None
_start = importlib.util.module_from_spec(_spec)
sys.modules['family_start'] = _start  # (its dataclasses look their module up)
_spec.loader.exec_module(_start)  # (research/ is not a package: the script, loaded by path)
inertia_rule_experiment = _start.inertia_rule_experiment
measure_start = _start.measure_start
standstill_windows = _start.standstill_windows


def test_the_papers_start_and_windows_are_the_papers() -> None:
    s = drive_setup('paper_750w')
    assert start_scale(s.drive) == 1.0 and s.experiment.fallback_gains == Gains()
    assert inertia_rule_experiment(s) == s.experiment
    w = standstill_windows(s.experiment)
    assert [x for ab in w for x in ab] == pytest.approx([0.3, 0.7, 0.9, 1.125], abs=1e-12)
    # one count through the speed filter: 1.39 rad/s, 0.74 A with k_pw 0.53 (10.5 % of 7 A)
    assert count_step(s.drive, 1.0) == pytest.approx(1.3903, abs=1e-4)
    assert count_step(s.drive, 0.53) / 7.0 == pytest.approx(0.105, abs=1e-3)


def test_im7500w_j10_start_no_longer_chatters_at_the_limit() -> None:
    """Before: one count 27.8 A (80 % of 34.84 A), 9.7 A rms at standstill, 158 periods at
    the limit in 3 experiments. Now: 8.7 A (25 %), under 2.5 A rms, never at the limit, not
    aborted, and a lower loss by the weights of before (0.94 against 0.99)."""
    s = drive_setup('im7500w-j10')
    before = inertia_rule_experiment(s)
    b = measure_start(s, before, before, 3)
    now = measure_start(s, s.experiment, before, 3)
    assert b.count_fraction == pytest.approx(0.797, abs=1e-3) and b.count_step > 27.0
    assert b.rms > 8.0 and b.at_limit > 100
    assert now.count_fraction == pytest.approx(COUNT_STEP_MAX, rel=1e-12)
    assert now.rms < 2.5 and now.rms_max < 3.0 and now.at_limit == 0 and now.aborted == 0
    assert now.loss == pytest.approx(0.98, abs=0.01)  # its own weights: 1/3 each term
    assert now.loss_yardstick < b.loss - 0.03
    # the corner k_iw/k_pw and the rest of the start are the paper's
    assert now.k_iw / now.k_pw == pytest.approx(20.0 / 0.53)
    assert s.experiment.fallback_gains.as_tuple()[2:] == (30.0, 0.005, 0.007)


def test_the_table_command_refuses_bad_input_in_one_line() -> None:
    for argv in (['x'], ['0'], ['3', '4'], ['--realism', 'lab'], ['--realism']):
        p = subprocess.run(
            [sys.executable, str(SCRIPT), *argv],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert p.returncode == 2 and p.stdout == '', argv
        assert p.stderr.count('\n') == 1 and p.stderr.startswith('error: '), argv
