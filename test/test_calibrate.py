"""The ``bench`` profile's calibration command (research/calibrate_bench.py): its refusals,
the fit it states and a tiny real run (docs/calibration.md is its full output)."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest

from im_drive_sim.params import BENCH_ESTIMATES, BENCH_NOISE_KEYS, bench_profile

SCRIPT = Path(__file__).resolve().parents[1] / 'research' / 'calibrate_bench.py'
_spec = importlib.util.spec_from_file_location('calibrate_bench', SCRIPT)
assert _spec is not None and _spec.loader is not None
C = importlib.util.module_from_spec(_spec)
sys.modules['calibrate_bench'] = C  # (its dataclasses look their module up)
_spec.loader.exec_module(C)  # (research/ is not a package: the script, loaded by path)


def _row(scale: float | None, final: tuple[float, float], sat: tuple[float, float]) -> C.Row:
    return C.Row(
        scale,
        0.02,
        1.0,
        5.0,
        1.0,
        dict(zip(C.CENTRE, final, strict=True)),
        dict(zip(C.CENTRE, sat, strict=True)),
        dict.fromkeys(C.CENTRE, 0.5),
    )


def test_distance_and_the_chosen_scale_in_the_markdown() -> None:
    ideal = _row(None, (0.60, 0.50), (100.0, 100.0))
    near = _row(2.0, (0.81, 0.75), (90.0, 92.0))  # SPSA exact, neCGA 0.05 high: D = 1
    far = _row(1.0, (0.70, 0.60), (100.0, 100.0))
    assert near.distance == pytest.approx(1.0)
    assert far.distance == pytest.approx((0.11 / 0.05) ** 2 + 1 + (0.1 / 0.05) ** 2 + 0.64)
    text = C.markdown([ideal, far, near], 0.01, 30, 200, 30, 'python research/calibrate_bench.py')
    assert '**Chosen: s = 2**' in text and '| bench s=2 (chosen) |' in text
    assert 'current noise 0.02 A' in text and 'Without the bound' not in text
    assert 'Table I 0.75 (paper 0.70, ideal 0.50)' in text
    # a better s beyond the sources' bound is shown, not chosen
    far8 = _row(8.0, (0.81, 0.70), (90.0, 92.0))
    text = C.markdown([ideal, near, far8], 0.01, 30, 200, 30, 'cmd', max_scale=4.0)
    assert '| bench s=2 (chosen) |' in text and '| bench s=8 (beyond the sources) |' in text
    assert 'Without the bound the fit goes on to s = 8 (D = 0.0)' in text


def test_bench_profile_scales_only_the_noise_like_keys() -> None:
    twice = bench_profile(2.0)
    for k, v in BENCH_ESTIMATES.items():
        assert twice[k] == (2.0 * v if k in BENCH_NOISE_KEYS else v), k
    assert 'disturbance.load_step_delay_max' in BENCH_NOISE_KEYS


@pytest.mark.parametrize(
    ('argv', 'message'),
    [
        (['--scales', '0,1'], "scales must be numbers in (0, 16], got '0,1'"),
        (['--scales', 'a'], "not a list of numbers: 'a'"),
        (['--runs', '0'], "must be an integer >= 1, got '0'"),
        (['--out', '/nonexistent/dir/c.md'], '--out: no directory /nonexistent/dir'),
        (['--seed', '-1'], '--seed must be >= 0, got -1'),
    ],
)
def test_bad_options_one_line_exit_2(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with pytest.raises(SystemExit) as ex:
        C.main(argv)
    assert ex.value.code == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and message in err and err.startswith('calibrate: ')


def test_a_tiny_calibration_runs_and_writes_its_page(tmp_path: Path) -> None:
    out = tmp_path / 'calibration.md'
    argv = ['--scales', '1', '--runs', '1', '--budget', '3', '--spread', '3', '--jobs', '1']
    assert C.main([*argv, '--out', str(out)]) == 0
    text = out.read_text()
    assert text.startswith('# Calibration of the `bench` realism profile')
    assert '| ideal |' in text and '| bench s=1 (chosen) |' in text
    rows = [ln for ln in text.splitlines() if ln.startswith('| ideal |')]
    cv = float(rows[0].split('|')[2])
    assert 0.0 <= cv < 1.0 and not math.isnan(cv)  # ideal: a spread far below 1 %


def test_calibrate_says_how_long_it_will_take():
    """``make calibrate-bench`` said nothing for 5-10 minutes: the estimate comes first."""
    RATE_PER_WORKER, estimate = C.RATE_PER_WORKER, C.estimate
    line = estimate((1.0, 2.0, 4.0, 8.0), 30, 200, 30, 2)
    # 5 profiles x 2 cells x 30 runs x 200 evaluations on 2 workers, plus the side runs
    assert line.startswith('calibrate: 60686 experiments (5 profiles x 2 cells x 30 runs')
    assert RATE_PER_WORKER == 50.0 and line.endswith('about 10 min on 2 worker(s)')
    assert estimate((4.0,), 2, 10, 5, 1).endswith('about 1 min on 1 worker(s)')
