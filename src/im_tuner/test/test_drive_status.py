"""The drive's counters in the run summary (im_tuner.bench.drive_status), without ROS."""

from __future__ import annotations

from im_tuner.bench.drive_status import drive_delta, drive_report
from im_tuner.progress import drive_text


def test_a_status_becomes_numbers_and_unknown_counters_are_left_out():
    rep = drive_report(
        {'mode': 'realtime', 'model': 'full', 'steps': '12', 'held': 'x', 'sim_time_s': '2.0'},
        level=1,
        message='late',
    )
    assert rep == {
        'mode': 'realtime',
        'model': 'full',
        'steps': 12,
        'sim_time_s': 2.0,
        'level': 1,
        'message': 'late',
    }
    assert drive_report({})['mode'] == 'unknown'


def test_an_external_drives_counters_are_the_sessions_share():
    def rep(**kv):
        return drive_report({'mode': 'realtime', **{k: str(v) for k, v in kv.items()}})

    start = rep(steps=100_000, held=40, overruns=7, max_lateness_us=900.0, watchdog_trips=1)
    end = rep(steps=130_000, held=55, overruns=7, max_lateness_us=900.0, watchdog_trips=1)
    d = drive_delta(start, end)
    assert (d['steps'], d['held'], d['overruns'], d['watchdog_trips']) == (30_000, 15, 0, 0)
    assert 'max_lateness_us' not in d and d['max_lateness_us_at_most'] == 900.0
    text = drive_text(d, 'this session')
    assert '30000 periods' in text and 'lateness <= 900 us' in text
    assert "this session's share" in text
    worse = drive_delta(start, rep(steps=130_000, max_lateness_us=2500.0))
    assert worse['max_lateness_us'] == 2500.0 and 'held' not in worse  # unknown at the end
    again = drive_delta(start, rep(steps=5_000, held=0))  # the drive restarted meanwhile
    assert again['steps'] == 5_000 and again['restarted'] and not again['per_session']
    assert 'restarted' in drive_text(again, None)
    assert drive_delta(None, end)['per_session'] is False  # no status at the start
    assert drive_delta(start, None) is None
