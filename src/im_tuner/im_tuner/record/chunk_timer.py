"""A thread that closes the recorder's open chunk by wall time when nobody polls it, so that
nothing taken waits in memory where a SIGKILL loses it (docs/recorder.md, "Crash
safety"). It never touches the graph; the recorder owns the lock that makes ``tick()`` and
its own polls take turns. No rclpy here."""

from __future__ import annotations

import threading
from collections.abc import Callable


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
