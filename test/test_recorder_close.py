"""A stopped recorder child on a loaded machine: waiting for it costs time, never the run.

The tuner's child bench (``bench.forms.Children``) stops its recorder with SIGINT and
decides from the bag, not from the child's exit code alone, whether anything was lost.
A stand-in child (no rclpy: it writes its bag with the project's own writer when
SIGINT comes, as the recorder does at close) closes slowly, closes and then hangs, or
never closes; only the last is a lost bag.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from im_tuner.bench import forms, recorder_watch as watch
from im_tuner.record.repair import bag_is_closed

STAND_IN = r"""
import signal, sys, time
from pathlib import Path
from im_tuner.record.counts import closing_custom_data
from im_tuner.record.metadata import bag_metadata, storage_file_name, write_metadata_yaml
from im_tuner.record.writer import McapWriter

out, close_after, then = Path(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
path = out / storage_file_name(out)
w = McapWriter(path, compression='none')
write_metadata_yaml(out, bag_metadata([(path.name, 0, 0, 0)], [], {'im_tuner.state': 'recording'}))
stop = []
signal.signal(signal.SIGINT, lambda *a: stop.append(1))
print('ready', flush=True)
while not stop:
    time.sleep(0.01)
if close_after < 0:  # never closes: a recorder that lost its bag
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    time.sleep(600)
time.sleep(close_after)
w.close()
write_metadata_yaml(out, bag_metadata([(path.name, 0, 0, 0)], [], closing_custom_data({}, {}, '')))
if then == 'hang':  # closed, but the process does not end (rclpy shutdown on a loaded host)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    time.sleep(600)
"""


STARTED: list[subprocess.Popen] = []


@pytest.fixture(autouse=True)
def _end_stand_ins():
    """A stand-in a failed test left running is ended by its PID."""
    yield
    while STARTED:
        p = STARTED.pop()
        if p.poll() is None:
            p.kill()
            p.wait()


class Host:
    def __init__(self) -> None:
        self.said: list[str] = []

    def warn(self, text: str) -> None:
        self.said.append(text)


def children_with(tmp_path: Path, close_after: float, then: str) -> tuple[forms.Children, Host]:
    """A Children bench holding only a stand-in recorder child recording ``tmp_path/bag``."""
    bag = tmp_path / 'bag'
    bag.mkdir()
    p = subprocess.Popen(
        [sys.executable, '-c', STAND_IN, str(bag), str(close_after), then],
        stdout=subprocess.PIPE,
        text=True,
    )
    STARTED.append(p)
    assert p.stdout is not None and p.stdout.readline().strip() == 'ready'
    host = Host()
    bench = object.__new__(forms.Children)  # only what closing the recording touches
    bench.children, bench.ended, bench.bag, bench.host = {'recorder': p}, [], bag, host
    bench.watch, bench.spin_until = None, None
    return bench, host


def test_a_recorder_slower_than_the_old_grace_to_close_is_waited_for(tmp_path):
    bench, host = children_with(tmp_path, 7.0, 'exit')
    t0 = time.monotonic()
    assert bench.close_recording() == []
    assert 7.0 <= time.monotonic() - t0 < 30.0
    assert bench.ended[0].returncode == 0 and bag_is_closed(bench.bag)
    assert any('waiting for the recorder to close its bag: 5 s' in s for s in host.said), host.said


def test_a_recorder_that_closed_its_bag_and_then_hangs_loses_nothing(tmp_path):
    bench, host = children_with(tmp_path, 0.0, 'hang')
    t0 = time.monotonic()
    assert bench.close_recording() == []
    took = time.monotonic() - t0
    assert watch.RECORDER_EXIT_AFTER_CLOSE <= took < watch.RECORDER_EXIT_AFTER_CLOSE + 20.0
    assert bench.ended[0].returncode == -9 and bag_is_closed(bench.bag)
    assert host.said == ['note: the recorder closed bag whole, then ended (killed by signal 9)']


def test_a_recorder_that_never_closes_its_bag_fails_the_recording(tmp_path, monkeypatch):
    monkeypatch.setattr(watch, 'RECORDER_CLOSE_TIMEOUT', 3.0)
    bench, _host = children_with(tmp_path, -1.0, 'hang')
    (problem,) = bench.close_recording()
    assert problem.startswith('the recorder did not close its bag (killed by signal 9)')
    assert 'repaired' in problem and bench.ended[0].returncode == -9
