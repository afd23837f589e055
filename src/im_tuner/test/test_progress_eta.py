"""The one ETA of every progress line (tuner, study, replay), on a clock the test holds."""

from __future__ import annotations

import pytest

from im_tuner import progress


@pytest.fixture
def clock(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(progress.time, 'monotonic', lambda: now[0])
    return now


def test_no_eta_before_it_has_a_rate(clock):
    eta = progress.Eta()
    assert eta(0, 10) == 'ETA -:--'  # the first call: its start, not a rate
    clock[0] += 0.5
    assert eta(1, 10) == 'ETA -:--'  # under a second of progress: not trusted yet
    clock[0] += 0.5
    assert eta(1, 10) == 'ETA 0:09'  # 1 s for 1 item, 9 left


def test_the_start_up_before_the_first_call_is_not_in_the_rate(clock):
    """A replay whose controller took 40 s to start did 3 of 200000 states when it first
    reported: its rate is taken from there on, not from the process's start."""
    eta = progress.Eta()
    clock[0] += 40.0
    eta(3, 200_000)
    clock[0] += 2.0
    assert eta(20_003, 200_000) == 'ETA 0:18'  # 10000 states/s, 180000 left


def test_minutes_and_the_end(clock):
    eta = progress.Eta()
    eta(0, 100)
    clock[0] += 75.0
    assert eta(1, 100) == 'ETA 123:45'  # 75 s per item, 99 left
    clock[0] += 1.0
    assert eta(100, 100) == 'ETA 0:00'


def test_a_long_step_says_where_it_is_every_10_s_and_at_the_end(clock):
    import io

    out = io.StringIO()
    p = progress.Progress('necga', 10, quiet=False, stream=out)
    step = p.steps('restoring the simulated plant')
    for k in range(1, 41):  # 40 experiments of 1 s each
        clock[0] += 1.0
        step(k, 40)
    lines = out.getvalue().splitlines()
    assert lines == [
        'restoring the simulated plant: 10/40, ETA 0:30',
        'restoring the simulated plant: 20/40, ETA 0:20',
        'restoring the simulated plant: 30/40, ETA 0:10',
        'restoring the simulated plant: 40/40, ETA 0:00',
    ]


def test_off_a_terminal_a_line_each_part_of_the_total_and_at_the_end(clock):
    """The one progress line of the tuner, the study and replay: off a terminal a line
    each time another 1/parts of the total is done (the study's and replay's 10 %), and
    the last; nothing but warnings with quiet."""
    import io

    out = io.StringIO()
    line = progress.Line(quiet=False, parts=10, stream=out)
    for i in range(1, 26):
        line.update(i, 25, f'{i}/25')
    assert out.getvalue().splitlines() == [f'{i}/25' for i in (3, 5, 8, 10, 13, 15, 18, 20, 23, 25)]
    quiet = io.StringIO()
    line = progress.Line(quiet=True, parts=10, stream=quiet)
    line.update(25, 25, 'done')
    line.note('a note')
    line.warn('a warning')
    assert quiet.getvalue() == 'a warning\n'
