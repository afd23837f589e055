"""CMA-ES (Hansen's pycma, ``cma.CMAEvolutionStrategy``) behind the one-at-a-time contract.

pycma's population is handed out one candidate at a time and told once its lambda losses
are in; its normal deviates come from the optimiser's own PCG64 stream.  The state is the
told history, replayed on restore (pycma has no stable serialisation).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import cma
import numpy as np

from .base import HISTORY, INT, Field, Optimizer, OptimizerError, told_history


class _Randn:
    """pycma's ``randn(lam, N)`` drawn from our own generator."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng

    def __call__(self, *shape: int) -> np.ndarray:
        return self.rng.standard_normal(shape)


class CMAES(Optimizer):
    """CMA-ES on [0, 1]^dim (pycma); ``start`` None: a uniform random start."""

    algo: ClassVar[str] = 'cmaes'
    REPLAYS: ClassVar[bool] = True
    STATE: ClassVar[tuple[Field, ...]] = (
        *HISTORY,
        Field('evaluations', INT),
    )
    BAD_STATE: ClassVar[str] = 'not a cmaes state ({error!r:.80})'

    def _setup(self, x0: np.ndarray | None) -> None:
        opts = self._opts
        self._start_given = x0 is not None
        if x0 is None:
            x0 = self._rng.random(self.dim)
        self._x0 = x0
        cma_opts: dict[str, Any] = {
            'bounds': [0.0, 1.0],
            'randn': _Randn(self._rng),
            'seed': math.nan,  # "do nothing" to numpy's global RNG
            'verbose': -9,
            'verb_log': 0,
            'verb_disp': 0,
            'verb_filenameprefix': '',
            'maxiter': math.inf,
            'maxfevals': math.inf,
            'tolfun': 0.0,
            'tolfunhist': 0.0,
            'tolx': 0.0,
            'tolstagnation': math.inf,
            'tolflatfitness': math.inf,
        }
        if opts['popsize'] is not None:
            cma_opts['popsize'] = opts['popsize']
        self._es = cma.CMAEvolutionStrategy(x0.tolist(), opts['sigma0'], cma_opts)
        self._pop: list[np.ndarray] = []  # pycma's candidates of this generation
        self._losses: list[float] = []  # losses told in this generation

    @property
    def iterations(self) -> int:
        """Generations completed (pycma's countiter)."""
        return int(self._es.countiter)

    @property
    def popsize(self) -> int:
        return int(self._es.popsize)

    def _propose(self) -> list[float]:
        """The next of pycma's population (a new generation asked when none is left)."""
        if not self._pop:
            self._pop = [np.asarray(x, dtype=np.float64) for x in self._es.ask()]
        u: list[float] = np.clip(self._pop[len(self._losses)], 0.0, 1.0).tolist()
        return u

    def _update(self, u: list[float], loss: float, aborted: bool) -> None:
        """Collect the generation's losses; pycma updates once it has all lambda."""
        self._losses.append(loss)
        if len(self._losses) == len(self._pop):
            self._es.tell(self._pop, self._losses)
            self._pop, self._losses = [], []

    def converged(self) -> bool:
        """pycma's own termination (its tolerances on x and f are off: the budget rules)."""
        return bool(self._es.stop(check=True)) and not self._pop

    @property
    def mean(self) -> np.ndarray:
        """The distribution's mean (pycma's xmean), in [0, 1]^dim."""
        return np.clip(np.asarray(self._es.mean, dtype=np.float64), 0.0, 1.0)

    @property
    def sigma(self) -> float:
        return float(self._es.sigma)

    def _settings(self) -> dict[str, Any]:
        return {
            **self._opts,
            'popsize_used': self.popsize,
            'start': self._x0.tolist() if self._start_given else None,
            'pycma': cma.__version__,
        }

    @classmethod
    def _restore(cls, state: dict[str, Any]) -> CMAES:
        """From the seed and configuration, the told losses replayed."""
        opt = cls._replica(state, state['config']['start'])
        us, losses = told_history(cls.algo, state)
        for u, loss in zip(us, losses, strict=True):
            a = opt.ask()
            if a.tolist() != u:
                raise OptimizerError(
                    f'cmaes state does not replay with pycma {cma.__version__} '
                    '(a candidate differs from the saved one)'
                )
            opt.tell(a, loss)
        pending = state['pending']
        if pending is not None and opt.ask().tolist() != [float(x) for x in pending]:
            raise OptimizerError('cmaes state: the pending candidate does not replay')
        return opt
