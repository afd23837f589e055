"""CMA-ES (Hansen's pycma, ``cma.CMAEvolutionStrategy``) behind the one-at-a-time contract.

pycma samples a population of lambda candidates per generation (``es.ask()``) and updates
mean, step size sigma and covariance from all their losses at once (``es.tell``).  Here
the population is handed out one candidate at a time; the generation is told to pycma
once its lambda losses are in.  The box is [0, 1]^dim through pycma's ``BoundTransform``
(every candidate pycma returns is inside it).

Randomness: pycma draws its normal deviates through the ``randn`` option; it is bound to
the optimiser's own PCG64 generator (``_Randn``), so pycma never touches numpy's global
RNG and a seed gives the same run in any process.

State: pycma has no stable serialisation (a pickle of the same strategy differs from
one dump to the next), so the state is the seed, the configuration and every candidate
and loss told so far.  ``from_state`` rebuilds the strategy by replaying the told
losses (each replayed candidate is checked bit for bit against the saved one, so a
pycma that behaves differently is refused rather than silently continued); CMA-ES's own
cost is ~0.1 ms per evaluation, so replaying 1000 evaluations takes ~0.1 s.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import cma
import numpy as np

from .base import (
    Optimizer,
    OptimizerError,
    OptionSpec,
    check_version,
    make_rng,
    seed_from_json,
    told_history,
    told_loss,
)
from .options import CMAES_OPTIONS

__all__ = ['CMAES']

_STATE_VERSION = 1


class _Randn:
    """pycma's ``randn(lam, N)`` drawn from our own generator."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng

    def __call__(self, *shape: int) -> np.ndarray:
        return self.rng.standard_normal(shape)


class CMAES(Optimizer):
    """CMA-ES on [0, 1]^dim (pycma).

    ``CMAES(dim, seed, start=None, *, sigma0=0.1, popsize=None)``; ``start`` None draws a
    uniform start in [0, 1]^dim from the optimiser's generator.
    """

    algo: ClassVar[str] = 'cmaes'
    OPTIONS: ClassVar[dict[str, OptionSpec]] = CMAES_OPTIONS

    def __init__(
        self,
        dim: int,
        seed: int | np.random.SeedSequence,
        start: np.ndarray | None = None,
        **options: Any,
    ) -> None:
        seed, x0 = self._init_checked(dim, seed, start, options)
        opts = self._opts
        self._rng = make_rng(seed)
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
        self._pending: list[float] | None = None
        self._history_u: list[list[float]] = []
        self._history_loss: list[float] = []
        self.evaluations = 0

    @property
    def iterations(self) -> int:
        """Generations completed (pycma's countiter)."""
        return int(self._es.countiter)

    @property
    def popsize(self) -> int:
        return int(self._es.popsize)

    def ask(self) -> np.ndarray:
        if self._pending is None:
            if not self._pop:
                self._pop = [np.asarray(x, dtype=np.float64) for x in self._es.ask()]
            u = np.clip(self._pop[len(self._losses)], 0.0, 1.0)
            self._pending = u.tolist()
        return np.array(self._pending)

    def tell(self, u: np.ndarray, loss: float) -> None:
        loss = told_loss(self._pending, u, loss)
        self._history_u.append(self._pending)  # type: ignore[arg-type]  # checked above
        self._history_loss.append(loss)
        self._losses.append(loss)
        self._pending = None
        self.evaluations += 1
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

    def config(self) -> dict[str, Any]:
        return {
            'algo': self.algo,
            'dim': self.dim,
            'seed': self._seed_json,
            **self._opts,
            'popsize_used': self.popsize,
            'start': self._x0.tolist() if self._start_given else None,
            'pycma': cma.__version__,
        }

    def state_dict(self) -> dict[str, Any]:
        return {
            'algo': self.algo,
            'version': _STATE_VERSION,
            'config': self.config(),
            'told_u': [list(u) for u in self._history_u],
            'told_loss': list(self._history_loss),
            'pending': None if self._pending is None else list(self._pending),
            'evaluations': self.evaluations,
        }

    @classmethod
    def _from_state(cls, state: dict[str, Any]) -> CMAES:
        check_version(cls, state, _STATE_VERSION)
        try:
            cfg = state['config']
            start = cfg['start']
            opt = cls(
                int(cfg['dim']),
                seed_from_json(cfg['seed']),
                None if start is None else np.array(start, dtype=np.float64),
                **{k: cfg[k] for k in cls.OPTIONS},
            )
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
        except OptimizerError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise OptimizerError(f'not a cmaes state ({exc!r:.80})') from None
        return opt
