"""Py-BOBYQA as the study's outside reference row: a maintained trust-region method
(Cartis et al., "Improving the flexibility and robustness of model-based derivative-free
optimization solvers", ACM TOMS 2019), not a tuner algorithm.

``pybobyqa.solve`` calls its objective itself, while the study's run (the tuner's
``TuningRun``) asks for one candidate at a time. :class:`BobyqaRun` joins the two: the
solver runs in a thread whose objective hands each point to :meth:`BobyqaRun.ask` and
waits for its loss from :meth:`BobyqaRun.tell_measurement`; one side runs at a time. The
run is measured as every other row (the reference, the budget counting every evaluation,
an aborted one told as its penalised loss, the re-measurement, the statistics).

Configuration: the box normalised to [0, 1]^dim, the hand-tuned start, trust-region
radius ``rhobeg``, ``maxfun`` = the budget, ``objfun_has_noise=True`` (soft restarts
instead of stopping when the radius shrinks); a solver that returns early starts again
from its best point with the remaining budget. Its restart directions come from numpy's
global generator, seeded from the run's optimiser stream: deterministic while a process
runs one run at a time (the local pool; a Dask worker with ``--nthreads 1``).
"""

from __future__ import annotations

import contextlib
import queue
import threading
import warnings

import numpy as np

#: How long ask() waits for the solver's next point [s] (its own work takes milliseconds).
ASK_TIMEOUT_S = 120.0


class _Closed(Exception):
    """Raised in the solver's objective when the run is closed before its budget."""


class BobyqaRun:
    """Py-BOBYQA one evaluation at a time (the ``ask``/``tell_measurement`` of the tuner's
    optimisers, as much of it as ``TuningRun`` uses).

    dim: parameters; seed: the run's optimiser seed (int or ``SeedSequence``); x0: the
    normalised start in [0, 1]^dim; budget: evaluations; rhobeg: initial trust-region
    radius in normalised units.
    """

    def __init__(
        self,
        dim: int,
        seed: int | np.random.SeedSequence,
        x0: np.ndarray | tuple[float, ...],
        budget: int,
        rhobeg: float = 0.08,
    ) -> None:
        if not (0.0 < rhobeg <= 0.5):
            raise ValueError(f'rhobeg must be in (0, 0.5] of the normalised box, got {rhobeg}')
        self.dim, self.budget, self.rhobeg = int(dim), int(budget), float(rhobeg)
        self.x0 = np.clip(np.asarray(x0, dtype=float), 0.0, 1.0)
        if self.x0.shape != (self.dim,):
            raise ValueError(f'x0 must have {self.dim} values, got {self.x0.shape}')
        ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        self.np_seed = int(ss.generate_state(1)[0])
        self.evaluations = 0
        self._pending: np.ndarray | None = None
        self._points: queue.Queue[np.ndarray | None] = queue.Queue(maxsize=1)
        self._losses: queue.Queue[float | None] = queue.Queue(maxsize=1)
        self._best: tuple[float, np.ndarray] | None = None
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None

    @property
    def iterations(self) -> int:
        """Evaluations (the solver's iterations are not observable one by one)."""
        return self.evaluations

    # -- the tuner's side -------------------------------------------------------------------
    def ask(self) -> np.ndarray:
        """The next point to measure (the same one until it is told)."""
        if self._pending is None:
            if self.evaluations >= self.budget:
                raise RuntimeError(f'bobyqa: budget of {self.budget} evaluations spent')
            if self._thread is None:
                self._thread = threading.Thread(target=self._solve, name='bobyqa', daemon=True)
                self._thread.start()
            try:
                x = self._points.get(timeout=ASK_TIMEOUT_S)
            except queue.Empty:
                raise RuntimeError('bobyqa: the solver gave no point in time') from None
            if x is None:
                raise RuntimeError(f'bobyqa: the solver ended ({self._error!r:.200})')
            self._pending = x
        return self._pending.copy()

    def tell_measurement(self, u: np.ndarray, loss: float, aborted: bool = False) -> None:
        """The measured loss of the point just asked (an aborted experiment's penalised
        loss, as for every optimiser)."""
        if self._pending is None or not np.array_equal(np.asarray(u, dtype=float), self._pending):
            raise ValueError('bobyqa: told a point that was not the one asked')
        loss = float(loss)
        if not np.isfinite(loss):
            raise ValueError(f'bobyqa: loss must be finite, got {loss}')
        if self._best is None or loss < self._best[0]:
            self._best = (loss, self._pending)
        self._pending = None
        self.evaluations += 1
        self._losses.put(loss)

    def close(self) -> None:
        """End the solver thread (at the end of a run, or when it stops early)."""
        t = self._thread
        if t is None or not t.is_alive():
            return
        while t.is_alive():
            with contextlib.suppress(queue.Full):  # a blocked objective raises _Closed
                self._losses.put_nowait(None)
            with contextlib.suppress(queue.Empty):  # the solver may wait to put a point
                self._points.get_nowait()
            t.join(0.05)

    # -- the solver's side (its thread) -----------------------------------------------------
    def _objective(self, x: np.ndarray) -> float:
        self._points.put(np.clip(np.asarray(x, dtype=float), 0.0, 1.0))
        loss = self._losses.get()
        if loss is None:
            raise _Closed
        return loss

    def _solve(self) -> None:
        import pybobyqa
        from scipy.linalg import LinAlgWarning

        lo, hi = np.zeros(self.dim), np.ones(self.dim)
        x = self.x0
        try:
            np.random.seed(self.np_seed % 2**32)
            while self.evaluations < self.budget:
                before = self.evaluations
                with warnings.catch_warnings():
                    # a restart near the end of the budget has maxfun <= npt (2 dim + 1):
                    # fewer evaluations than its model needs, by design here; not news
                    warnings.filterwarnings(
                        'ignore', message='maxfun <= npt', category=RuntimeWarning
                    )
                    # noisy steps clipped to the box can make its interpolation points
                    # degenerate (scipy: a singular LU factor); the solver goes on, and a
                    # worker's warning would break the study's progress line
                    warnings.filterwarnings('ignore', category=LinAlgWarning)
                    pybobyqa.solve(
                        self._objective,
                        x,
                        bounds=(lo, hi),
                        rhobeg=self.rhobeg,
                        maxfun=self.budget - self.evaluations,
                        objfun_has_noise=True,
                        do_logging=False,
                    )
                if self.evaluations == before or self._best is None:
                    self._error = RuntimeError('the solver returned without evaluating')
                    break
                x = self._best[1]  # an early return: again from the best point
        except _Closed:
            return
        except Exception as exc:  # reported by the next ask()
            self._error = exc
        self._points.put(None)
