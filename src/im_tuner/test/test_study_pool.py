"""The study's pool, interrupted: ``runs._end_pool`` returns only when the executor's
manager thread has ended and closed its wakeup pipe, so the interpreter's exit hook
(``concurrent.futures.process._python_exit``, which takes no lock) cannot write to a pipe
the manager is closing (the OSError traceback CI saw after ``study: interrupted``)."""

import multiprocessing
import signal
import time
from concurrent.futures import ProcessPoolExecutor, process as cf_process

import pytest

from im_tuner.study.runs import _end_pool


def _sleep(s: float) -> float:
    time.sleep(s)
    return s


@pytest.mark.skipif(
    hasattr(ProcessPoolExecutor, 'terminate_workers'), reason='Python >= 3.14 ends it itself'
)
def test_end_pool_leaves_no_manager_thread_and_closes_its_wakeup(monkeypatch):
    # a loaded machine: the manager thread closes its wakeup pipe 0.5 s after it sees the
    # broken pool (the race's window, made wide enough to hit every time)
    close = cf_process._ThreadWakeup.close

    def slow_close(self):
        time.sleep(0.5)
        close(self)

    monkeypatch.setattr(cf_process._ThreadWakeup, 'close', slow_close)
    pool = ProcessPoolExecutor(max_workers=2, mp_context=multiprocessing.get_context('forkserver'))
    futures = [pool.submit(_sleep, 60.0) for _ in range(4)]
    deadline = time.monotonic() + 60.0
    while not any(f.running() for f in futures):  # a worker holds a run
        assert time.monotonic() < deadline, 'no worker started a run within 60 s'
        time.sleep(0.01)
    manager = pool._executor_manager_thread
    procs = list(pool._processes.values())
    assert manager is not None and manager.is_alive()
    wakeups = [w for t, w in cf_process._threads_wakeups.items() if t is manager]
    assert len(wakeups) == 1

    t0 = time.monotonic()
    _end_pool(pool)
    took = time.monotonic() - t0

    assert not manager.is_alive()
    assert wakeups[0]._closed
    assert not any(p.is_alive() for p in procs)
    assert took < 10.0  # not the 60 s runs
    wakeups[0].wakeup()  # what the exit hook does: a no-op now, not EBADF


def test_end_pool_kills_a_worker_the_executor_has_not_registered():
    """A signal landing while the executor waits for a new worker's PID leaves that
    worker out of its table; it went on starting after the study ended and printed a
    traceback (test/test_study_bad_input.py, under load). Here a forkserver child the
    pool does not know stands for it."""
    ctx = multiprocessing.get_context('forkserver')
    pool = ProcessPoolExecutor(max_workers=1, mp_context=ctx)
    fut = pool.submit(_sleep, 60.0)
    stray = ctx.Process(target=_sleep, args=(60.0,))
    stray.start()
    deadline = time.monotonic() + 60.0
    while not fut.running():
        assert time.monotonic() < deadline, 'no worker started a run within 60 s'
        time.sleep(0.01)
    assert stray.pid not in pool._processes and stray.is_alive()

    _end_pool(pool)

    stray.join(5.0)
    assert stray.exitcode == -signal.SIGKILL
