"""A thread that closes the recorder's open chunk by wall time when nobody polls it.

Why: the recorder takes messages and closes chunks only when its owner polls it. While
the owner is busy elsewhere (numba loading kernels at start-up, a tuner waiting for its
first experiment) what was already taken would sit in memory, where a SIGKILL loses it.
This thread wakes every ``period`` s and, when the owner has not polled for that long,
calls ``tick()`` (the recorder takes what is waiting and closes a chunk whose first
message is ``max_chunk_age`` old). It never touches the graph.

No rclpy here; the recorder owns the lock that makes ``tick()`` and its own polls take
turns.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

__all__ = ['ChunkTimer']


class ChunkTimer:
    """Calls ``tick()`` every ``period`` [s] on a daemon thread until :meth:`stop`.

    An exception from ``tick()`` ends the thread; it is kept in :attr:`error` for the
    owner to raise (the thread itself has no one to report to)."""

    def __init__(self, tick: Callable[[], None], period: float, name: str = 'chunk timer') -> None:
        if not period > 0:
            raise ValueError(f'period must be > 0 s, got {period!r}')
        self.period = float(period)
        self.error: BaseException | None = None
        self._tick = tick
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            try:
                self._tick()
            except BaseException as exc:  # kept for the owner: a thread cannot raise
                self.error = exc
                return

    def stop(self, timeout: float = 5.0) -> None:
        """End the thread (after a tick under way, if any); idempotent."""
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)
