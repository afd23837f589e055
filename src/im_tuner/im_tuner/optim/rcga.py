"""Real-valued compact GA (rcGA, Mininno, Cupertino, Naso 2008) with pe or ne elitism.

Per variable a mean mu_i and a spread sigma_i on x in [-1, 1] (start mu = 0,
sigma = sigma0; the default 10 makes the first samples nearly uniform, as in Mininno's
rcGA).  A candidate samples each x_i from the Gaussian N(mu_i, sigma_i^2) truncated to
[-1, 1], by inverse CDF::

    x = mu + sigma ndtri(Phi(a) + r (Phi(b) - Phi(a))),  a = (-1 - mu)/sigma,
    b = (1 - mu)/sigma,  r ~ U[0, 1)

(Phi from math.erfc, Phi^-1 = ``scipy.special.ndtri``), and
is handed out as u = (x + 1)/2.  Each generation compares the elite with one newcomer
(one evaluation; the first generation also samples and evaluates the elite) and moves
the distribution as if the winner w replaced the loser l in a population of n points::

    mu'      = mu + (w - l)/n
    sigma'^2 = sigma^2 + mu^2 - mu'^2 + (w^2 - l^2)/n     (a rounding negative -> 0)

Ties go to the elite (the newcomer needs a strictly lower loss).  ``elitism='pe'``: the
winner is the elite.  ``elitism='ne'`` (default): theta counts consecutive elite wins
(reset when the newcomer wins); when it reaches eta the newcomer just evaluated becomes
the elite (Mininno's ne-rcGA: one evaluation per generation).  ``converged()`` when every
sigma_i < SIGMA_TOL.

Note: the update keeps the moments of a virtual population, whose variance cannot exceed
1 on [-1, 1]; from sigma0 = 10 the spread only comes down after O(sigma0^2 n) generations,
so with a budget of a few hundred evaluations the search is close to uniform random
sampling.  sigma0 ~ 0.5-1 (the spread of a uniform population is 0.577) is the option for
short budgets.  See docs/optimisers.md.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import scipy.special as _sc

from .base import (
    Optimizer,
    OptimizerError,
    OptionSpec,
    check_dim,
    check_options,
    check_seed,
    check_start,
    make_rng,
    rebuild,
    rng_state,
    seed_json,
    told_loss,
)
from .options import RCGA_OPTIONS

__all__ = ['RCGA', 'SIGMA_TOL', 'erfinv', 'ndtri', 'norm_cdf', 'truncnorm_ppf']

#: converged() when every sigma is below this (x units; u resolution SIGMA_TOL/2, finer
#: than a 16-bit gene's 1.5e-5).
SIGMA_TOL = 1e-6

_STATE_VERSION = 1
_SQRT2 = math.sqrt(2.0)
# bound once: one global lookup per call on the sampling path instead of two
_erfc, _sqrt = math.erfc, math.sqrt


def norm_cdf(x: float) -> float:
    """Phi(x) = erfc(-x/sqrt 2)/2 (accurate to a few ulp, relative, in the lower tail)."""
    return 0.5 * _erfc(-x / _SQRT2)


#: Phi^-1 and erf^-1: scipy's (cephes ndtri, ~1e-16 relative over (0, 1)); bound once.
ndtri = _sc.ndtri
erfinv = _sc.erfinv


def truncnorm_ppf(r: float, mu: float, sigma: float) -> float:
    """Quantile r in [0, 1) of N(mu, sigma^2) truncated to [-1, 1].

    Computed on the side where Phi is accurate: mu < 0 is mirrored (x -> -x, which maps
    quantile r to quantile 1 - r of the mirrored law, same distribution for uniform r);
    then a = (-1 - mu)/sigma < 0 and the upper half of the mass is inverted through the
    upper tail Q(b) = 1 - Phi(b).  sigma = 0, or a mass that underflows (mu far outside
    [-1, 1] with a tiny sigma), gives the point of [-1, 1] nearest to mu.
    """
    flip = mu < 0.0
    if flip:
        mu = -mu
    if sigma <= 0.0:
        x = mu
    else:
        a = (-1.0 - mu) / sigma
        b = (1.0 - mu) / sigma
        pa = 0.5 * _erfc(-a / _SQRT2)  # Phi(a), a < 0
        if b <= 0.0:
            mass = 0.5 * _erfc(-b / _SQRT2) - pa
            if mass <= 0.0:
                x = mu
            else:
                p = pa + r * mass
                x = mu + sigma * float(ndtri(p))
        else:
            qb = 0.5 * _erfc(b / _SQRT2)  # 1 - Phi(b)
            mass = (1.0 - pa) - qb
            p = pa + r * mass
            if p <= 0.5:
                x = mu + sigma * float(ndtri(p))
            else:
                q = qb + (1.0 - r) * mass  # 1 - p, without cancellation
                x = mu - sigma * float(ndtri(min(q, 0.5)))
    x = -1.0 if x < -1.0 else (1.0 if x > 1.0 else x)
    return -x if flip else x


class RCGA(Optimizer):
    """Real-valued compact GA with persistent ('pe') or non-persistent ('ne') elitism.

    ``RCGA(dim, seed, start=None, *, n=25, elitism='ne', eta=12, sigma0=10.0)``.
    """

    algo: ClassVar[str] = 'rcga'
    OPTIONS: ClassVar[dict[str, OptionSpec]] = RCGA_OPTIONS
    #: samples per random block (one rng call per block)
    _BLOCK: ClassVar[int] = 64

    def __init__(
        self,
        dim: int,
        seed: int | np.random.SeedSequence,
        start: np.ndarray | None = None,
        **options: Any,
    ) -> None:
        self.dim = check_dim(dim)
        seed = check_seed(seed)
        if start is not None:
            check_start(start, self.dim)
            raise OptimizerError(
                'rcga does not take a start point (it starts from mu = 0, '
                'sigma = sigma0); pass start=None'
            )
        opts = check_options(self.algo, self.OPTIONS, options)
        if opts['elitism'] == 'ne' and opts['eta'] >= opts['n']:  # (unused with 'pe')
            raise OptimizerError(
                f'rcga option eta must be an integer in [1, n - 1] = '
                f'[1, {opts["n"] - 1}] (eta < n), got {opts["eta"]!r}'
            )
        self._opts = opts
        self._seed_json = seed_json(seed)
        self.n: int = opts['n']
        self.elitism: str = opts['elitism']
        self.eta: int = opts['eta']
        self._rng = make_rng(seed)
        self._mu = [0.0] * self.dim  # python floats: scalar math is faster at dim 5
        self._sigma = [opts['sigma0']] * self.dim
        self.evaluations = 0
        self.generation = 0
        self.theta = 0
        self._elite: list[float] | None = None
        self._elite_loss = 0.0
        self._pu: list[float] | None = None  # the pending candidate (u)
        self._px: list[float] | None = None  # and its x
        # Uniforms drawn in blocks of _BLOCK samples (the same stream as one
        # rng.random(dim) per sample); _bi is the next unused one.
        self._blk: list[float] = []
        self._bi = 0

    # ----------------------------------------------------------------------- sampling
    @staticmethod
    def _to_u(x: list[float]) -> list[float]:
        return [(xi + 1.0) * 0.5 for xi in x]

    # ------------------------------------------------------------------------ ask/tell
    @property
    def iterations(self) -> int:
        return self.generation

    def ask(self) -> np.ndarray:
        """The next candidate u = (x + 1)/2, x sampled from the truncated Gaussians."""
        pu = self._pu
        if pu is None:
            i = self._bi
            if i == len(self._blk):
                self._blk = self._rng.random(self._BLOCK * self.dim).tolist()
                i = 0
            j = i + self.dim
            self._bi = j
            x, pu = [], []
            for r, m, s in zip(self._blk[i:j], self._mu, self._sigma, strict=True):
                xi = truncnorm_ppf(r, m, s)
                x.append(xi)
                pu.append((xi + 1.0) * 0.5)
            self._px, self._pu = x, pu
        return np.array(pu)

    def tell(self, u: np.ndarray, loss: float) -> None:
        pu = self._pu
        loss = told_loss(pu, u, loss)
        y = loss
        x = self._px
        assert x is not None  # told_loss refused a tell without an ask
        self._pu = self._px = None
        self.evaluations += 1
        elite = self._elite
        if elite is None:  # first generation: the elite's evaluation
            self._elite, self._elite_loss = x, y
            return
        newcomer_wins = y < self._elite_loss  # ties -> the elite
        w, l = (x, elite) if newcomer_wins else (elite, x)
        # The winner replaces the loser in the virtual population of n (module docstring).
        n = self.n
        mus: list[float] = []
        sigmas: list[float] = []
        # (sg * sg, correctly rounded; sg ** 2 goes through libm's pow, which is not)
        for mu, sg, wi, li in zip(self._mu, self._sigma, w, l, strict=True):
            mu1 = mu + (wi - li) / n
            var = sg * sg + mu * mu - mu1 * mu1 + (wi * wi - li * li) / n
            mus.append(mu1)
            sigmas.append(_sqrt(var) if var > 0.0 else 0.0)
        self._mu, self._sigma = mus, sigmas
        self.generation += 1
        if newcomer_wins:
            self._elite, self._elite_loss = x, y
            self.theta = 0
        elif self.elitism == 'ne':
            self.theta += 1
            if self.theta >= self.eta:
                self._elite, self._elite_loss = x, y
                self.theta = 0

    # ---------------------------------------------------------------------- reporting
    @property
    def mu(self) -> np.ndarray:
        """Means of the sampling distributions on [-1, 1] (a copy)."""
        return np.array(self._mu)

    @property
    def sigma(self) -> np.ndarray:
        """Spreads of the sampling distributions on [-1, 1] (a copy)."""
        return np.array(self._sigma)

    @property
    def elite(self) -> np.ndarray | None:
        """The elite's normalised parameters (None before its evaluation)."""
        return None if self._elite is None else np.array(self._to_u(self._elite))

    @property
    def elite_loss(self) -> float | None:
        return None if self._elite is None else self._elite_loss

    def solution(self) -> np.ndarray:
        """The distribution's centre as normalised parameters, (clip(mu, -1, 1) + 1)/2."""
        return (np.clip(np.array(self._mu), -1.0, 1.0) + 1.0) * 0.5

    def converged(self) -> bool:
        """Every sigma_i < SIGMA_TOL."""
        return max(self._sigma) < SIGMA_TOL

    def config(self) -> dict[str, Any]:
        return {'algo': self.algo, 'dim': self.dim, 'seed': self._seed_json, **self._opts}

    # ---------------------------------------------------------------------- state I/O
    def state_dict(self) -> dict[str, Any]:
        return {
            'algo': self.algo,
            'version': _STATE_VERSION,
            'config': self.config(),
            'rng': rng_state(self._rng, len(self._blk) - self._bi),
            'mu': list(self._mu),
            'sigma': list(self._sigma),
            'evaluations': self.evaluations,
            'generation': self.generation,
            'theta': self.theta,
            'elite': None if self._elite is None else list(self._elite),
            'elite_loss': self._elite_loss,
            'pending': None if self._px is None else list(self._px),
        }

    @classmethod
    def _from_state(cls, state: dict[str, Any]) -> RCGA:
        try:
            opt = rebuild(cls, state, _STATE_VERSION)

            def vec(v: Any) -> list[float]:
                out = [float(t) for t in v]
                if len(out) != opt.dim:
                    raise OptimizerError(f'bad rcga state: vectors must have {opt.dim} values')
                return out

            opt._mu, opt._sigma = vec(state['mu']), vec(state['sigma'])
            opt.evaluations = int(state['evaluations'])
            opt.generation = int(state['generation'])
            opt.theta = int(state['theta'])
            opt._elite = None if state['elite'] is None else vec(state['elite'])
            opt._elite_loss = float(state['elite_loss'])
            opt._px = None if state['pending'] is None else vec(state['pending'])
            opt._pu = None if opt._px is None else opt._to_u(opt._px)
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, OptimizerError):
                raise
            raise OptimizerError(f'bad rcga state: {e!r}') from None
        return opt
