"""A stop signal (SIGINT, SIGTERM) passed to a real-time loop without waiting for Python,
whose handler runs in the main thread only at its next bytecode: the interpreter's C-level
handler writes the signal's number at once to the *wakeup fd*
(:func:`signal.set_wakeup_fd`); a watcher thread waits on that pipe in compiled code
(``poll(2)`` and ``read(2)`` from numba, no GIL) and sets the loop's stop word, which the
loop reads every period. Python's own handler still runs (the run's orderly end follows
it). The watcher also asks ``should_stop()`` every :data:`POLL_MS`; where the wakeup fd
cannot be taken (not the main thread) that is all it does.

Written by hand: the wakeup fd is the interpreter's own mechanism; no library waits on
it without the GIL.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Callable

import numba
import numpy as np
from numba import types

#: [ms] how often the watcher asks ``should_stop()``
POLL_MS = 5

_poll = types.ExternalFunction('poll', types.int32(types.uint64, types.uint64, types.int32))
_read = types.ExternalFunction('read', types.int64(types.int32, types.uint64, types.uint64))
POLLIN = 1
STOP_SIGNALS = np.array([int(signal.SIGINT), int(signal.SIGTERM)], np.uint8)


@numba.njit(cache=True, nogil=True)
def wait_for_stop(
    fd: int, pfd: np.ndarray, buf: np.ndarray, stops: np.ndarray, word: np.ndarray, index: int,
    quit_word: np.ndarray,
) -> int:  # fmt: skip
    """Wait on ``fd`` (the wakeup pipe), never returning to Python meanwhile (the GIL
    may be held elsewhere for long): a SIGINT or SIGTERM among the bytes read (``stops``)
    sets ``word[index] = 1`` and returns 1; ``quit_word[0]`` != 0, looked at whenever a
    byte came (:meth:`StopWatcher.close` writes one), returns 0. ``pfd``: two int32 words
    of scratch (a ``struct pollfd``); ``buf``: uint8 scratch."""
    while quit_word[0] == 0:
        pfd[0] = fd
        pfd[1] = POLLIN  # events in the low half (little-endian), revents cleared
        if _poll(np.uint64(pfd.ctypes.data), np.uint64(1), np.int32(-1)) <= 0:
            continue  # (EINTR)
        n = _read(np.int32(fd), np.uint64(buf.ctypes.data), np.uint64(buf.size))
        for i in range(max(n, 0)):
            for s in stops:
                if buf[i] == s:
                    word[index] = 1
                    return 1
    return 0


class StopWatcher:
    """Sets ``word[index] = 1`` on SIGINT/SIGTERM (a thread waiting on the wakeup fd in
    compiled code: no GIL) or once ``should_stop()`` is true (a thread that asks every
    POLL_MS). :meth:`close` ends both and gives the interpreter its previous wakeup fd
    back."""

    def __init__(self, word: np.ndarray, index: int, should_stop: Callable[[], bool]) -> None:
        self.word, self.index, self.should_stop = word, index, should_stop
        self._quit = np.zeros(1, np.int64)
        self._old_fd: int | None = None
        self._fds: tuple[int, int] | None = None
        if threading.current_thread() is threading.main_thread():
            r, w = os.pipe()
            os.set_blocking(r, False)
            os.set_blocking(w, False)  # (the interpreter's handler must never block)
            try:
                self._old_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
                self._fds = (r, w)
            except ValueError:
                os.close(r)
                os.close(w)
        #: True: a signal reaches the loop without Python (else: should_stop only)
        self.direct = self._fds is not None
        self._threads = [threading.Thread(target=self._ask, name='rt-stop-ask', daemon=True)]
        if self._fds is not None:
            # compiled (or loaded from numba's cache) now, not beside the loop
            self._run_signal_wait(np.ones(1, np.int64), np.zeros(1, self.word.dtype))
            self._threads.append(
                threading.Thread(target=self._signal, name='rt-stop-signal', daemon=True)
            )
        for t in self._threads:
            t.start()

    def _run_signal_wait(self, quit_word: np.ndarray, word: np.ndarray) -> int:
        assert self._fds is not None
        pfd, buf = np.zeros(2, np.int32), np.zeros(64, np.uint8)
        return wait_for_stop(self._fds[0], pfd, buf, STOP_SIGNALS, word, self.index, quit_word)

    def _signal(self) -> None:
        self._run_signal_wait(self._quit, self.word)

    def _ask(self) -> None:
        while self._quit[0] == 0 and self.word[self.index] == 0:
            if self.should_stop():
                self.word[self.index] = 1
                return
            time.sleep(POLL_MS / 1000)

    def close(self) -> None:
        """End the watcher; the interpreter's previous wakeup fd back (from the main
        thread; elsewhere the pipe stays: the interpreter's handler keeps writing to it)."""
        self._quit[0] = 1
        if self._fds is not None:
            # wakes the signal thread's poll (a full pipe: its poll returns anyway)
            with contextlib.suppress(BlockingIOError):
                os.write(self._fds[1], b'\0')
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(1.0)
        if self._fds is None or any(t.is_alive() for t in self._threads):
            return
        try:
            signal.set_wakeup_fd(-1 if self._old_fd is None else self._old_fd)
        except ValueError:
            return
        for fd in self._fds:
            os.close(fd)
        self._fds = None
