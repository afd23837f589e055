"""Simultaneous perturbation stochastic approximation (SPSA), Spall 1998, as in the paper.

Two evaluations per iteration k = 0, 1, ... on u in [0, 1]^dim: y+ at u_k + c_k Delta_k,
y- at u_k - c_k Delta_k, the step a_k (y+ - y-)/(2 c_k) Delta_k capped at ``max_step``,
the iterate kept in [c_{k+1}, 1 - c_{k+1}] (``bounded``).  The equations, the index
convention and the gain presets: docs/optimisers.md, "SPSA".
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from .base import FLOAT, FLOATS, FLOATS_OR_NONE, INT, SAVED, Field, Optimizer, OptimizerError
from .options import GAIN_PRESETS


class SPSA(Optimizer):
    """SPSA with two evaluations per iteration; ``start`` None: a uniform random start in
    [c, 1 - c]^dim; ``bounded=False`` (constructor only): no projection."""

    algo: ClassVar[str] = 'spsa'
    #: iterations per random block (one rng call per block)
    _BLOCK: ClassVar[int] = 32
    STATE: ClassVar[tuple[Field, ...]] = (
        Field('k', INT),
        Field('evaluations', INT),
        Field('u', FLOATS, '_u'),
        Field('phase', INT, '_phase'),
        Field('delta', FLOATS, '_delta'),
        Field('ck', SAVED, '_ck'),  # (restored by _restored: it may be a function of k)
        Field('y_plus', FLOAT, '_y_plus'),
        Field('pending', FLOATS_OR_NONE, '_pending'),
        Field('last_gradient', FLOATS_OR_NONE, '_last_gradient'),
    )

    def _check_options(self, options: dict[str, Any]) -> dict[str, Any]:
        """``bounded`` (constructor only, for analytic oracles), the options, and alpha
        and gamma from the ``gains`` preset unless given."""
        bounded = options.pop('bounded', True)
        if not isinstance(bounded, bool):
            raise OptimizerError(f'bounded must be True or False, got {bounded!r}')
        self.bounded = bounded
        opts = super()._check_options(options)
        preset_alpha, preset_gamma = GAIN_PRESETS[opts['gains']]
        if opts['alpha'] is None:
            opts['alpha'] = preset_alpha
        if opts['gamma'] is None:
            opts['gamma'] = preset_gamma
        return opts

    def _setup(self, x0: np.ndarray | None) -> None:
        opts = self._opts
        self.a: float = opts['a']
        self.c: float = opts['c']
        self.A: float = opts['A']
        self.alpha: float = opts['alpha']
        self.gamma: float = opts['gamma']
        self.max_step: float = opts['max_step']
        if x0 is None:
            lo, hi = (self.c, 1.0 - self.c) if self.bounded else (0.0, 1.0)
            x0 = lo + (hi - lo) * self._rng.random(self.dim)
        # in [c_0, 1 - c_0] if bounded; python floats and lists, the vector form's
        # operations in its order (docs/optimisers.md, "Speed")
        self._u: list[float] = (np.clip(x0, self.c, 1.0 - self.c) if self.bounded else x0).tolist()
        self.k = 0  # iteration index of u_k
        self._phase = 0  # 0: y+ next, 1: y- next
        self._delta = [0.0] * self.dim  # Delta_k (+-1.0), drawn at the iteration's 1st ask
        self._ck = self.c / (self.k + 1) ** self.gamma  # c_k of the current iteration
        self._y_plus = 0.0
        self._last_gradient: list[float] | None = None

    def _block(self) -> list[float]:
        """Delta for _BLOCK iterations (the stream of one rng.random(dim) per iteration):
        +-1 with probability exactly 1/2 each (r - 1/2 < 0 on exactly half of the
        multiples of 2^-53 in [0, 1))."""
        r = self._rng.random(self._BLOCK * self.dim)
        return np.copysign(1.0, r - 0.5).tolist()

    def gains(self, k: int) -> tuple[float, float]:
        """(a_k, c_k) of iteration k (0-based): a/(k+1+A)^alpha, c/(k+1)^gamma."""
        return self.a / (k + 1 + self.A) ** self.alpha, self.c / (k + 1) ** self.gamma

    @property
    def iterations(self) -> int:
        """Completed iterations (= k of the current iterate u_k)."""
        return self.k

    def _propose(self) -> list[float]:
        """u_k + c_k Delta_k (first evaluation of an iteration) or u_k - c_k Delta_k."""
        ck: float = self._ck
        if self._phase == 0:
            i = self._draws(self.dim)
            self._delta = d = self._blk[i : i + self.dim]
            return [x + ck * di for x, di in zip(self._u, d, strict=True)]
        return [x - ck * di for x, di in zip(self._u, self._delta, strict=True)]

    def _update(self, u: list[float], loss: float, aborted: bool) -> None:
        """Record y+ (first call of an iteration) or y- and take the SPSA step."""
        if self._phase == 0:
            self._y_plus = loss
            self._phase = 1
            return
        # 1/Delta_i = Delta_i: g = (y+ - y-)/(2 c_k) Delta, and every |step_i| is the same
        # |a_k s|, so the cap scales that one number (docs/optimisers.md, "Speed").
        s = (self._y_plus - loss) / (2.0 * self._ck)
        c = self.a / (self.k + 1 + self.A) ** self.alpha * s
        biggest = abs(c)
        if biggest > self.max_step:
            c *= self.max_step / biggest
        self.k = k = self.k + 1
        self._ck = ck = self.c / (k + 1) ** self.gamma  # c_{k+1}, the next iteration's
        g: list[float] = []
        u_next: list[float] = []
        if self.bounded:
            hi = 1.0 - ck
            for x, d in zip(self._u, self._delta, strict=True):
                g.append(s * d)
                x -= d * c
                u_next.append(ck if x < ck else (hi if x > hi else x))
        else:
            for x, d in zip(self._u, self._delta, strict=True):
                g.append(s * d)
                u_next.append(x - d * c)
        self._u = u_next
        self._last_gradient = g
        self._phase = 0

    @property
    def iterate(self) -> np.ndarray:
        """The current point u_k (a copy): SPSA's estimate of the optimum."""
        return np.array(self._u)

    @property
    def last_gradient(self) -> np.ndarray | None:
        """The gradient estimate g_k of the last completed iteration (a copy), or None."""
        return None if self._last_gradient is None else np.array(self._last_gradient)

    def _settings(self) -> dict[str, Any]:
        return {'bounded': self.bounded, **self._opts}

    def _restored(self, state: dict[str, Any]) -> None:
        # ck is c_k of the current iteration once its first candidate is asked; before
        # that it is a function of k (a state may hold the previous iteration's).
        self._ck = (
            self.c / (self.k + 1) ** self.gamma
            if self._phase == 0 and self._pending is None
            else float(state['ck'])
        )
        if (
            len(self._u) != self.dim
            or len(self._delta) != self.dim
            or (self._pending is not None and len(self._pending) != self.dim)
            or (self._last_gradient is not None and len(self._last_gradient) != self.dim)
        ):
            raise OptimizerError('bad spsa state: vectors do not match dim')
