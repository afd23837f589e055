"""``--timing-tolerance auto`` during a run: after an experiment off the paper's timing the
tuner checks its host again (``TunerSession.recheck_host``), raises the tolerance when the
host got louder -- on the controller, in run.yaml, said in one line -- keeps it when it did
not, never lowers it, and records every check in the session's record. A resumed auto run
goes on with auto from its tolerance up.

The host's check is a stand-in here (``host.check_before_run`` with figures the test sets):
what a louder host does to the choice is :mod:`im_drive_sim.host`'s, tested there.
"""

from __future__ import annotations

from typing import Any

import pytest

from im_drive_sim import host
from im_tuner.rundir import RunDir
from im_tuner.runlog import RunConfig
from im_tuner.tuner_args import parse_options
from im_tuner.tuner_cli import PreparedSession, _new_run_config, make_tuning
from im_tuner.tuner_session import TunerSession

pytestmark = pytest.mark.unit


class Said:
    """The progress printer's lines."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def note(self, text: str) -> None:
        self.lines.append(text)

    warn = note


class Link:
    """The controller's side: what it was told."""

    call_timeout = 10.0

    def __init__(self) -> None:
        self.told: list[int] = []

    def set_timing_tolerance(self, periods: int, deadline: float) -> None:
        self.told.append(periods)


def _stand_in(
    monkeypatch: pytest.MonkeyPatch, p95: list[int], expect: Any = host.AUTO
) -> list[int]:
    """``host.check_before_run`` giving, check after check, 95 % of experiments within
    ``p95[i]`` held periods (auto: the larger of its least and twice that; a fixed
    tolerance: itself); returns the leasts it was asked with."""
    asked: list[int] = []

    def check(tolerance: Any, least: int, opts: Any = None, seconds: float = 2.0):
        assert tolerance == expect
        auto = tolerance == host.AUTO
        asked.append(least if auto else int(tolerance))
        t = p95[len(asked) - 1]
        chosen = max(least, host.AUTO_MARGIN * t) if auto else int(tolerance)
        record = {
            'late_pct': 0.5 * t,
            'max_lateness_us': 1000.0 * t,
            'held_per_experiment': {'p95': t},
            'tolerance': t,
            'auto': auto,
            'tolerance_chosen': chosen,
        }
        return chosen, record, f'timing tolerance auto: {chosen} held periods per experiment'

    monkeypatch.setattr(host, 'check_before_run', check)
    return asked


def _session(tmp_path, monkeypatch) -> TunerSession:
    monkeypatch.setattr(
        host, 'check_before_run', lambda *a, **k: (10, {'auto': True, 'tolerance': 3}, None)
    )
    argv = ['tuner', '--bench', 'realtime', '--timing-tolerance', 'auto', '--seed', '3']
    cli = parse_options(argv[1:])
    new = _new_run_config(cli, argv)
    assert new.run.timing_tolerance == 10 and new.run.host_check['auto'] is True
    out = tmp_path / 'run'
    s = TunerSession(cli, argv, PreparedSession(new.run, new.params, None, Said(), out=out))
    s.rundir = RunDir.create(out)
    s.tuning = make_tuning(s.rundir, new.run, new.params, None)
    s.rundir.write_run(new.run)
    return s


def test_a_louder_host_raises_the_tolerance_a_quieter_one_keeps_it(tmp_path, monkeypatch):
    s = _session(tmp_path, monkeypatch)
    assert s.tuning.timing_tolerance == 10
    asked = _stand_in(monkeypatch, [4, 9, 2])
    link = Link()
    # as loud as before the run: 2 x 4 = 8 < 10, kept, nothing told
    assert s.recheck_host(link) is None and link.told == []
    assert s.progress.lines[-1].startswith(
        'host checked again after an experiment off the timing: '
    )
    # louder: 2 x 9 = 18 -> the controller, run.yaml, one line
    assert s.recheck_host(link) == 18 and link.told == [18]
    assert RunConfig.from_text((s.rundir.path / 'run.yaml').read_text()).timing_tolerance == 18
    assert s.progress.lines[-1] == (
        'timing tolerance auto: 18 held periods per experiment; the host got louder: '
        'from the next experiment on'
    )
    s.tuning.timing_tolerance = 18  # (TuningRun takes what recheck_host returns)
    # quieter again: never lowered
    assert s.recheck_host(link) is None and link.told == [18]
    assert asked == [10, 10, 18]
    checks = s.session['host_rechecks']
    assert [(c['timing_tolerance_before'], c['timing_tolerance']) for c in checks] == [
        (10, 10),
        (10, 18),
        (18, 18),
    ]
    assert [c['held_per_experiment']['p95'] for c in checks] == [4, 9, 2]


def test_a_resumed_auto_run_goes_on_with_auto_from_its_tolerance(monkeypatch):
    from im_tuner.tuner_cli import _check_resumed_host

    cli = parse_options([])
    for check, p95, tolerance, asked_with in (
        ({'auto': True}, 30, 60, host.AUTO),  # louder than the run's 18: raised
        ({'auto': True}, 2, 18, host.AUTO),  # quieter: never below the run's 18
        ({'auto': False}, 30, 18, 18),  # a fixed tolerance stays fixed
    ):
        run = RunConfig.from_dict(
            {'algo': 'safe', 'budget': 5, 'timing_tolerance': 18, 'host_check': check}
        )
        run.put(bench_requested='realtime')
        asked = _stand_in(monkeypatch, [p95], asked_with)
        _check_resumed_host(cli, run)
        assert asked == [18] and run.timing_tolerance == tolerance, check
        assert run.host_check['auto'] is (asked_with == host.AUTO)
