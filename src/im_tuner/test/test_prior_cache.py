"""The first steps kept across processes (``IM_TUNER_PRIOR_CACHE``, im_tuner.prior): a
point computed once is read back bit for bit by another process, never across a change
of code or numeric baseline, and a missing, corrupt or unwritable directory costs time,
not a result."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading

import pytest

from im_drive_sim.drive_file import load_config
from im_tuner import prior
from im_tuner.prior import CACHE_ENV, Prior
from im_tuner.space import load_params

#: floats that a lossy text form would change in their last bit
AWKWARD = Prior(
    u=(0.1, 1 / 3, math.nextafter(0.5, 1.0)),
    model_ratio=2 / 3,
    worst_ratio=math.nextafter(0.9, 0.0),
    experiments=661,
    seconds=7.25,
)


@pytest.fixture
def fresh(monkeypatch, tmp_path):
    """An empty process cache and a cache directory; counts the computations."""
    monkeypatch.setattr(prior, '_CACHE', {})
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / 'cache'))
    calls = []

    def compute(value=AWKWARD):
        calls.append(1)
        return value

    return tmp_path / 'cache', calls, compute


def test_a_point_is_computed_once_and_read_back_bit_for_bit(fresh, monkeypatch):
    where, calls, compute = fresh
    assert prior._cached('k', compute) is AWKWARD
    assert len(calls) == 1 and len(list(where.glob('prior-*.json'))) == 1
    monkeypatch.setattr(prior, '_CACHE', {})  # another process: only the directory
    again = prior._cached('k', compute)
    assert again == AWKWARD and len(calls) == 1
    assert [x.hex() for x in again.u] == [x.hex() for x in AWKWARD.u]
    assert prior._cached('other key', compute) == AWKWARD and len(calls) == 2


def test_none_is_kept_too(fresh, monkeypatch):
    _, calls, compute = fresh
    assert prior._cached('k', lambda: compute(None)) is None
    monkeypatch.setattr(prior, '_CACHE', {})
    assert prior._cached('k', lambda: compute(None)) is None and len(calls) == 1


def test_another_code_or_baseline_does_not_read_the_file(fresh, monkeypatch):
    where, calls, compute = fresh
    prior._cached('k', compute)
    monkeypatch.setattr(prior, '_CACHE', {})
    monkeypatch.setattr(prior, '_code_digest', lambda: 'another build')
    prior._cached('k', compute)
    assert len(calls) == 2 and len(list(where.glob('prior-*.json'))) == 2


def test_a_corrupt_file_is_computed_again_and_replaced(fresh, monkeypatch):
    where, calls, compute = fresh
    prior._cached('k', compute)
    (f,) = where.glob('prior-*.json')
    for bad in ('{"u": [0.1', '[1, 2]', '{"u": [0.1], "x": 1}'):
        f.write_text(bad)
        monkeypatch.setattr(prior, '_CACHE', {})
        assert prior._cached('k', compute) == AWKWARD
        assert json.loads(f.read_text())['model_ratio'] == AWKWARD.model_ratio
    assert len(calls) == 4


def test_an_unwritable_directory_still_gives_the_point(fresh, monkeypatch, tmp_path):
    _, calls, compute = fresh
    (tmp_path / 'file').write_text('not a directory')
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / 'file' / 'cache'))
    assert prior._cached('k', compute) == AWKWARD and len(calls) == 1


def test_without_the_variable_nothing_is_written(fresh, monkeypatch):
    where, calls, compute = fresh
    monkeypatch.delenv(CACHE_ENV)
    prior._cached('k', compute)
    assert not where.exists() and len(calls) == 1


def test_two_that_miss_at_once_compute_once(fresh, monkeypatch, wait_until):
    """A study's workers start together: the second to miss a key waits on the first's
    lock and reads its point instead of computing it again.  (Threads with their own
    lock descriptions behave as processes do; the first's computation waits until the
    second is at the lock, so without it the second would compute too.)"""
    where, calls, compute = fresh
    real_flock, at_lock = prior.fcntl.flock, threading.Event()
    entered = []

    def flock(fd, op):
        entered.append(op)
        if len(entered) == 2:
            at_lock.set()
        return real_flock(fd, op)

    monkeypatch.setattr(prior.fcntl, 'flock', flock)

    def slow():
        assert at_lock.wait(10), 'the second never reached the lock'
        return compute()

    got = []
    other = threading.Thread(target=lambda: got.append(prior._cached('k', compute)))
    first = threading.Thread(target=lambda: got.append(prior._cached('k', slow)))
    first.start()
    wait_until(lambda: entered, 10, message='the first caller at the lock')
    other.start()
    first.join(20)
    other.join(20)
    assert got == [AWKWARD, AWKWARD] and len(calls) == 1
    assert len(list(where.glob('prior-*.json'))) == 1


def test_the_paper_drives_first_step_from_another_process_is_the_same(tmp_path, monkeypatch):
    """The real thing: a child process computes the paper drive's first step into the
    directory; this process reads it without computing and gets its point exactly."""
    monkeypatch.setattr(prior, '_CACHE', {})
    monkeypatch.setenv(CACHE_ENV, str(tmp_path))
    code = (
        'import im_drive_sim, json\n'
        'from im_tuner.prior import model_prior\n'
        'from im_tuner.space import load_params\n'
        'from im_drive_sim.drive_file import load_config\n'
        'p = model_prior(load_config(None), load_params(None).space)\n'
        'print(json.dumps([x.hex() for x in p.u]))\n'
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True)
    assert len(list(tmp_path.glob('prior-*.json'))) == 1
    monkeypatch.setattr(prior, '_compute', lambda *a, **k: pytest.fail('computed again'))
    p = prior.model_prior(load_config(None), load_params(None).space)
    assert p is not None and [x.hex() for x in p.u] == json.loads(out.stdout)
    assert p.experiments == 661


def test_the_study_names_the_same_variable():
    from im_tuner.study import cli

    assert cli.PRIOR_CACHE_ENV == CACHE_ENV
