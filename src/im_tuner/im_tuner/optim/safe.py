"""A local, abort-aware (1+1) evolution strategy with a local linear model ('safe').

Hand-written: no maintained library offers a one-at-a-time local search from known-safe
gains that treats an aborted experiment as a constraint rather than a loss.  The rule and
the model's first point: docs/optimisers.md, "Beyond the paper" and "The first step from
the identified drive"; the measurements behind the constants, research/NOTES.md, "safe".
The fit is numpy's (LAPACK ``gelsd``): a resumed run continues bit for bit on the same
machine and numpy build.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from .base import (
    FLOAT,
    FLOATS,
    FLOATS_OR_NONE,
    INT,
    ROWS,
    STR,
    Codec,
    Field,
    Optimizer,
    OptimizerError,
)
from .checks import check_start

#: ``first`` for a point given after the start's measurements (:meth:`SAFE.set_first`)
IDENTIFY = 'identify'


def check_first(first: Any, dim: int) -> list[float]:
    """The model's first point: dim finite numbers in [0, 1] (as python floats)."""
    try:
        u = check_start(first, dim)
    except OptimizerError:
        raise OptimizerError(
            f"safe: first must be {dim} finite numbers in [0, 1] (the model's point, "
            f'normalised), got {first!r}'
        ) from None
    assert u is not None
    return [float(x) for x in u]


def _point(opt: SAFE, v: Any) -> np.ndarray:
    """The saved incumbent: a point of [0, 1]^dim."""
    x = np.array(v, dtype=np.float64)
    if x.shape != (opt.dim,) or not np.all((x >= 0) & (x <= 1)):
        raise OptimizerError('safe state: x is not a point of [0, 1]^dim')
    return x


_POINT = Codec(_point, lambda _o, x: x.tolist())
_STEP = Codec(
    lambda _o, v: None if v is None else np.array(v, dtype=np.float64),
    lambda _o, s: None if s is None else s.tolist(),
)


class SAFE(Optimizer):
    """Local abort-aware (1+1)-ES from the start point (docs/optimisers.md)."""

    algo: ClassVar[str] = 'safe'
    ABORT_AWARE: ClassVar[bool] = True
    #: floor of the step size: below half a percent of a range the search stalls on noise
    SIGMA_MIN: ClassVar[float] = 0.005
    #: model radius in units of sigma sqrt(dim); noise of a model step in units of sigma;
    #: value of an aborted point in the model in units of the incumbent's loss
    MODEL_RADIUS: ClassVar[float] = 3.0
    MODEL_NOISE: ClassVar[float] = 0.3
    ABORT_VALUE: ClassVar[float] = 3.0
    #: step size after the identified model's point succeeds (first='identify'): that
    #: optimum lies near the plant's stability edge and the step was the model's
    IDENTIFIED_SIGMA: ClassVar[float] = 0.02
    #: points half-way back to the incumbent after a model's point fails (its loss, as
    #: told, not below f; not aborted): its direction is right more often than its length
    FIRST_BACKOFFS: ClassVar[int] = 2
    #: candidates the screen may turn away in a row before the incumbent is measured
    #: instead (each one shrinks the step as an abort does)
    SCREEN_TRIES: ClassVar[int] = 8
    STATE_VERSION: ClassVar[int] = 3
    STATE: ClassVar[tuple[Field, ...]] = (
        Field('x', _POINT),
        Field('f', FLOAT),
        Field('f_n', INT),
        Field('sigma', FLOAT),
        Field('step', _STEP),
        Field('evaluations', INT),
        Field('successes', INT),
        Field('aborts', INT),
        Field('pending', FLOATS_OR_NONE, '_pending'),
        Field('kind', STR, '_kind'),
        Field('points', ROWS, '_pts'),
        Field('values', FLOATS, '_vals'),
    )
    BAD_STATE: ClassVar[str] = 'not a safe state ({error!r:.80})'
    first_left: bool  #: the model's point not proposed yet

    def __init__(
        self,
        dim: int,
        seed: int | np.random.SeedSequence,
        start: np.ndarray | None = None,
        first: Any = None,
        **options: Any,
    ) -> None:
        # ``first``: the model's point (im_tuner.prior), measured right after the start;
        # not an option of the table (a point, computed from the drive, not typed in);
        # 'identify': a point given later (set_first), from the start's measurements
        self._identify = isinstance(first, str) and first == IDENTIFY
        self._first = None if first is None or self._identify else check_first(first, dim)
        super().__init__(dim, seed, start, **options)

    def _settings(self) -> dict[str, Any]:
        if self._identify:
            return {**self._opts, 'first': IDENTIFY}
        if self._first is None:  # (without a model: the configuration of the golden tests)
            return self._opts
        return {**self._opts, 'first': list(self._first)}

    @property
    def wants_screen(self) -> bool:
        """``first='identify'``: the screen of the drive identified for the first step,
        once the start is measured and the first point given (or none found)."""
        return self._identify and self.screen is None and self.f_n > 0 and not self.wants_first

    @property
    def wants_first(self) -> bool:
        """``first='identify'`` and the point not given yet, with the start measured:
        the tuner should call :meth:`set_first` before the next ``ask``."""
        return self._identify and self.first_left and self._first is None and self.f_n > 0

    def set_first(self, first: Any) -> None:
        """The identified model's point (``first='identify'``), or None: no first step."""
        if not self._identify or self._first is not None or not self.first_left:
            raise OptimizerError('safe: set_first is for first=identify, once, before it is asked')
        if self._pending is not None:
            raise OptimizerError('safe: set_first while a point is asked and not told')
        if first is None:
            self.first_left = False
        else:
            self._first = check_first(first, self.dim)

    def _check_options(self, options: dict[str, Any]) -> dict[str, Any]:
        opts = super()._check_options(options)
        if opts['sigma0'] > opts['sigma_max']:
            raise OptimizerError(
                f'safe: sigma0 {opts["sigma0"]:g} is larger than sigma_max '
                f'{opts["sigma_max"]:g} (the largest step)'
            )
        return opts

    def _setup(self, x0: np.ndarray | None) -> None:
        if x0 is None:  # (a real bench always has a start: this is for tests and studies)
            x0 = self._rng.random(self.dim)
        self.x = x0.copy()
        self.f = math.nan  # incumbent's mean measured loss (nan: not measured yet)
        self.f_n = 0  # measurements in that mean
        self.sigma = float(self._opts['sigma0'])
        self.step: np.ndarray | None = None  # last successful step (pattern move)
        self.successes = 0
        self.aborts = 0
        self.screened = 0  # candidates the screen turned away (not measured)
        self._kind = ''  # 'incumbent' or 'candidate'
        # the local model's data: every measured point and its loss (an aborted
        # candidate with ABORT_VALUE times the incumbent's loss)
        self._pts: list[list[float]] = []
        self._vals: list[float] = []
        # the model's point not yet proposed (first=identify: not given yet either)
        self.first_left = self._first is not None or self._identify
        # after the model's point failed: the point half-way back, and how many were asked
        self._back: list[float] | None = None
        self._backoffs = 0

    @property
    def iterations(self) -> int:
        return self.evaluations

    def slope(self) -> np.ndarray | None:
        """Slope g of the local linear model at x (None: fewer than dim + 1 measured points
        within the model radius, or a flat fit)."""
        if len(self._pts) <= self.dim:
            return None
        r = self.MODEL_RADIUS * self.sigma * math.sqrt(self.dim)
        P = np.array(self._pts) - self.x
        d = np.sqrt(np.einsum('ij,ij->i', P, P))
        near = d <= r
        if int(near.sum()) <= self.dim:
            return None
        w = np.exp(-((d[near] / r) ** 2))
        A = np.hstack([np.ones((int(near.sum()), 1)), P[near]]) * w[:, None]
        coef = np.linalg.lstsq(A, np.array(self._vals)[near] * w, rcond=None)[0]
        g = coef[1:]
        return g if np.all(np.isfinite(g)) and np.any(g) else None

    def _next(self) -> tuple[np.ndarray, str]:
        every = self._opts['remeasure_every']
        if self.f_n == 0 or (every and self.evaluations % every == every - 1):
            return self.x.copy(), 'incumbent'
        if self.first_left:
            if self._first is None:  # first=identify and no point given: none
                self.first_left = False
            else:
                return np.array(self._first), 'first'
        if self._back is not None:
            return np.array(self._back), 'first'
        if self.step is not None:
            return np.clip(self.x + self.step, 0.0, 1.0), 'candidate'
        z = self._rng.standard_normal(self.dim)
        m = self._opts['model_every']
        g = self.slope() if m and self.evaluations % m == 0 else None
        if g is None:
            s = self.sigma * z
        else:
            s = self.sigma * (
                -math.sqrt(self.dim) * g / float(np.linalg.norm(g)) + self.MODEL_NOISE * z
            )
        return np.clip(self.x + s, 0.0, 1.0), 'candidate'

    def _propose(self) -> list[float]:
        y, self._kind = self._next()
        tries = 0
        # a candidate the identified model predicts to abort is learnt as an aborted one
        # without an experiment (research/NOTES.md, "The abort screen")
        while self._kind == 'candidate' and self.screen is not None and self.screen(y.tolist()):
            self._update(y.tolist(), math.inf, True)
            self.aborts -= 1  # (not measured: counted as screened)
            self.screened += 1
            tries += 1
            if tries == self.SCREEN_TRIES:
                y, self._kind = self.x.copy(), 'incumbent'
                break
            y, self._kind = self._next()
        return y.tolist()

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        if self._first is not None or self._identify:  # (else the golden tests' state)
            state['first_left'] = self.first_left
            state['first_back'] = self._back
            state['first_backoffs'] = self._backoffs
            state['screened'] = self.screened
        if self._identify:
            state['first_point'] = None if self._first is None else list(self._first)
        return state

    def _update(self, u: list[float], loss: float, aborted: bool) -> None:
        """The (1+1) rule, the step size and the model's data."""
        y = np.array(u)
        first = self._kind == 'first'
        if first:  # the model's point is a candidate, but no pattern move repeats its step
            self.first_left = False
            self._back = None
            self._kind = 'candidate'
        if not aborted:
            self._pts.append(y.tolist())  # (the model's data)
            self._vals.append(loss)
        elif self._kind == 'candidate' and self.f_n:
            self._pts.append(y.tolist())
            self._vals.append(self.ABORT_VALUE * self.f)
        if self._kind == 'incumbent':
            if not aborted:  # (an incumbent that aborts keeps its mean)
                self.f = (self.f * self.f_n + loss) / (self.f_n + 1) if self.f_n else loss
                self.f_n += 1
        elif not aborted and loss < self.f:
            self.step = None if first else y - self.x
            if self.step is not None and not np.any(self.step):
                self.step = None
            self.x, self.f, self.f_n = y, loss, 1
            self.sigma = min(self.sigma * self._opts['grow'], self._opts['sigma_max'])
            if first and self._identify:  # its step was the model's, not the search's
                self.sigma = min(self.IDENTIFIED_SIGMA, self._opts['sigma_max'])
            self.successes += 1
        else:
            if first and not aborted and self._backoffs < self.FIRST_BACKOFFS:
                self._back = ((self.x + y) / 2.0).tolist()  # the model's direction, shorter
                self._backoffs += 1
            self.step = None
            factor = self._opts['abort_shrink'] if aborted else self._opts['grow'] ** -0.25
            self.sigma = max(self.sigma * factor, self.SIGMA_MIN)
            self.aborts += int(aborted)

    def _restored(self, state: dict[str, Any]) -> None:
        if self._identify:
            point = state['first_point']
            self._first = None if point is None else check_first(point, self.dim)
        if self._first is not None or self._identify:
            self.first_left = bool(state['first_left'])
            back = state['first_back']
            self._back = None if back is None else check_first(back, self.dim)
            self._backoffs = int(state['first_backoffs'])
            self.screened = int(state['screened'])
        if len(self._pts) != len(self._vals) or any(len(q) != self.dim for q in self._pts):
            raise OptimizerError('safe state: points and values do not match')
