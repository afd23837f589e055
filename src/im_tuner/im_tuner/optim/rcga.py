"""Real-valued compact GA (rcGA, Mininno, Cupertino, Naso 2008) with pe or ne elitism.

Per variable a mean mu_i and a spread sigma_i on x in [-1, 1] (start mu = 0,
sigma = sigma0; the default 10 makes the first samples nearly uniform, as in Mininno's
rcGA).  A candidate samples each x_i from the Gaussian N(mu_i, sigma_i^2) truncated to
[-1, 1], by inverse CDF::

    x = mu + sigma ndtri(Phi(a) + r (Phi(b) - Phi(a))),  a = (-1 - mu)/sigma,
    b = (1 - mu)/sigma,  r ~ U[0, 1)

(Phi from math.erfc; ndtri below, Wichura's AS 241: numpy has no erfinv and scipy is
not a dependency), and
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

__all__ = ['RCGA', 'SIGMA_TOL', 'erfinv', 'ndtri', 'norm_cdf', 'truncnorm_ppf']

#: converged() when every sigma is below this (x units; u resolution SIGMA_TOL/2, finer
#: than a 16-bit gene's 1.5e-5).
SIGMA_TOL = 1e-6

_STATE_VERSION = 1
_SQRT2 = math.sqrt(2.0)
# bound once: one global lookup per call on the sampling path instead of two
_erfc, _log, _sqrt, _INF = math.erfc, math.log, math.sqrt, math.inf


def norm_cdf(x: float) -> float:
    """Phi(x) = erfc(-x/sqrt 2)/2 (accurate to a few ulp, relative, in the lower tail)."""
    return 0.5 * _erfc(-x / _SQRT2)


def _ndtri_lower(q: float) -> float:
    """Phi^-1(q) for 0 < q <= 1/2 (so the result is <= 0): Wichura's algorithm AS 241
    (PPND16, Applied Statistics 37, 1988), relative error about 1e-16.

    Rational functions only (no erfc/exp, unlike a rough approximation refined by a Newton
    or Halley step): q >= 0.075 in d = q - 1/2, smaller q in r = sqrt(-log q) (r <= 5, i.e.
    q >= 1.4e-11, and beyond).
    """
    d = q - 0.5
    if d >= -0.425:
        r = 0.180625 - d * d
        return (
            d
            * (
                (
                    (
                        (
                            (
                                (
                                    (r * 2509.0809287301226727 + 33430.575583588128105) * r
                                    + 67265.770927008700853
                                )
                                * r
                                + 45921.953931549871457
                            )
                            * r
                            + 13731.693765509461125
                        )
                        * r
                        + 1971.5909503065514427
                    )
                    * r
                    + 133.14166789178437745
                )
                * r
                + 3.387132872796366608
            )
            / (
                (
                    (
                        (
                            (
                                (
                                    (r * 5226.495278852854561 + 28729.085735721942674) * r
                                    + 39307.89580009271061
                                )
                                * r
                                + 21213.794301586595867
                            )
                            * r
                            + 5394.1960214247511077
                        )
                        * r
                        + 687.1870074920579083
                    )
                    * r
                    + 42.313330701600911252
                )
                * r
                + 1.0
            )
        )
    r = _sqrt(-_log(q))
    if r <= 5.0:
        r -= 1.6
        return -(
            (
                (
                    (
                        (
                            (
                                (
                                    (r * 7.7454501427834140764e-4 + 0.0227238449892691845833) * r
                                    + 0.24178072517745061177
                                )
                                * r
                                + 1.27045825245236838258
                            )
                            * r
                            + 3.64784832476320460504
                        )
                        * r
                        + 5.7694972214606914055
                    )
                    * r
                    + 4.6303378461565452959
                )
                * r
                + 1.42343711074968357734
            )
            / (
                (
                    (
                        (
                            (
                                (
                                    (r * 1.05075007164441684324e-9 + 5.475938084995344946e-4) * r
                                    + 0.0151986665636164571966
                                )
                                * r
                                + 0.14810397642748007459
                            )
                            * r
                            + 0.68976733498510000455
                        )
                        * r
                        + 1.6763848301838038494
                    )
                    * r
                    + 2.05319162663775882187
                )
                * r
                + 1.0
            )
        )
    r -= 5.0
    return -(
        (
            (
                (
                    (
                        (
                            (
                                (r * 2.01033439929228813265e-7 + 2.71155556874348757815e-5) * r
                                + 0.0012426609473880784386
                            )
                            * r
                            + 0.026532189526576123093
                        )
                        * r
                        + 0.29656057182850489123
                    )
                    * r
                    + 1.7848265399172913358
                )
                * r
                + 5.4637849111641143699
            )
            * r
            + 6.6579046435011037772
        )
        / (
            (
                (
                    (
                        (
                            (
                                (r * 2.04426310338993978564e-15 + 1.4215117583164458887e-7) * r
                                + 1.8463183175100546818e-5
                            )
                            * r
                            + 7.868691311456132591e-4
                        )
                        * r
                        + 0.0148753612908506148525
                    )
                    * r
                    + 0.13692988092273580531
                )
                * r
                + 0.59983220655588793769
            )
            * r
            + 1.0
        )
    )


def ndtri(p: float) -> float:
    """Inverse of the standard normal CDF, Phi^-1(p); -inf at 0, +inf at 1.

    Wichura's AS 241 (PPND16): ~1e-16 relative for p <= 1/2, down to the smallest
    subnormal (tested to 2e-13 down to p = 1e-300 against 40-digit references, and equal
    to the standard library's ``statistics.NormalDist().inv_cdf``, the same algorithm);
    above 1/2 through ``ndtri(p) = -ndtri(1 - p)`` (1 - p is exact there).
    """
    if not 0.0 < p < 1.0:
        if p == 0.0:
            return -math.inf
        if p == 1.0:
            return math.inf
        raise ValueError(f'ndtri: p must be in [0, 1], got {p!r}')
    if p <= 0.5:
        return _ndtri_lower(p)
    return -_ndtri_lower(1.0 - p)  # 1 - p is exact for p >= 1/2 (Sterbenz)


def erfinv(y: float) -> float:
    """Inverse error function on [-1, 1]: erf(erfinv(y)) = y; erfinv(y) = Phi^-1((1+y)/2)/sqrt 2."""
    if not -1.0 <= y <= 1.0:
        raise ValueError(f'erfinv: y must be in [-1, 1], got {y!r}')
    if y < 0.0:
        return -erfinv(-y)
    # (1 - y)/2 is exact for y in [0, 1], keeps the tail accurate.
    return -ndtri(0.5 * (1.0 - y)) / _SQRT2


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
                x = mu + sigma * (_ndtri_lower(p) if p > 0.0 else -_INF)
        else:
            qb = 0.5 * _erfc(b / _SQRT2)  # 1 - Phi(b)
            mass = (1.0 - pa) - qb
            p = pa + r * mass
            if p <= 0.5:
                x = mu + sigma * (_ndtri_lower(p) if p > 0.0 else -_INF)
            else:
                q = qb + (1.0 - r) * mass  # 1 - p, without cancellation
                x = mu - sigma * _ndtri_lower(min(q, 0.5))
    x = -1.0 if x < -1.0 else (1.0 if x > 1.0 else x)
    return -x if flip else x


class RCGA(Optimizer):
    """Real-valued compact GA with persistent ('pe') or non-persistent ('ne') elitism.

    ``RCGA(dim, seed, start=None, *, n=25, elitism='ne', eta=12, sigma0=10.0)``.
    """

    algo: ClassVar[str] = 'rcga'
    OPTIONS: ClassVar[dict[str, OptionSpec]] = {
        'n': OptionSpec(
            int,
            25,
            'virtual population size n: a competition moves mu by (w - l)/n',
            low=2,
            high=1_000_000,
        ),
        'elitism': OptionSpec(
            str,
            'ne',
            "'ne' (elite replaced by the newcomer after eta "
            "consecutive wins) or 'pe' (persistent elite)",
            choices=('ne', 'pe'),
        ),
        'eta': OptionSpec(
            int,
            12,
            "allowed length of inheritance with elitism='ne' (consecutive elite wins; must be < n)",
            low=1,
            high=1_000_000,
        ),
        'sigma0': OptionSpec(
            float,
            10.0,
            'initial spread of every variable on x in '
            '[-1, 1] (10: nearly uniform; 0.577: a uniform population)',
            low=0.0,
            high=1e6,
            low_strict=True,
        ),
    }
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
            opt._seed_json = state['config']['seed']
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, OptimizerError):
                raise
            raise OptimizerError(f'bad rcga state: {e!r}') from None
        return opt
