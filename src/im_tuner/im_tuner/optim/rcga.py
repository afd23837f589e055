"""Real-valued compact GA (rcGA, Mininno, Cupertino, Naso 2008) with pe or ne elitism.

Per variable a mean mu_i and a spread sigma_i on x in [-1, 1] (start mu = 0,
sigma = sigma0; the default 10 makes the first samples nearly uniform, as in Mininno's
rcGA).  A candidate samples each x_i from the Gaussian N(mu_i, sigma_i^2) truncated to
[-1, 1], by inverse CDF::

    x = mu + sigma ndtri(Phi(a) + r (Phi(b) - Phi(a))),  a = (-1 - mu)/sigma,
    b = (1 - mu)/sigma,  r ~ U[0, 1)

(Phi from math.erfc; ndtri below, numpy has no erfinv and scipy is not a dependency), and
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

from .base import (OptimizerError, Optimizer, OptionSpec, PendingCheck, check_dim,
                   check_options, check_seed, check_start, check_told, make_rng, rng_state,
                   seed_json, set_rng_state)

__all__ = ['RCGA', 'ndtri', 'erfinv', 'norm_cdf', 'truncnorm_ppf', 'SIGMA_TOL']

#: converged() when every sigma is below this (x units; u resolution SIGMA_TOL/2, finer
#: than a 16-bit gene's 1.5e-5).
SIGMA_TOL = 1e-6

_STATE_VERSION = 1
_SQRT2 = math.sqrt(2.0)
_SQRT2PI = math.sqrt(2.0 * math.pi)

# Acklam's rational approximation of the normal quantile (relative error < 1.2e-9),
# refined by one Halley step on math.erfc below.
_A = (-3.969683028665376e+01, 2.209460984245205e+02, -2.759285104469687e+02,
      1.383577518672690e+02, -3.066479806614716e+01, 2.506628277459239e+00)
_B = (-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02,
      6.680131188771972e+01, -1.328068155288572e+01)
_C = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00,
      -2.549732539343734e+00, 4.374664141464968e+00, 2.938163982698783e+00)
_D = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00,
      3.754408661907416e+00)
_P_LOW = 0.02425


def norm_cdf(x: float) -> float:
    """Phi(x) = erfc(-x/sqrt 2)/2 (accurate to a few ulp, relative, in the lower tail)."""
    return 0.5 * math.erfc(-x / _SQRT2)


def _ndtri_lower(q: float) -> float:
    """Phi^-1(q) for 0 < q <= 1/2 (so the result is <= 0)."""
    # One Halley step on f(x) = Phi(x) - q after Acklam: cubic convergence takes the
    # 1e-9 relative error to rounding level.  u = f/f' = (Phi(x) - q) sqrt(2 pi) e^(x^2/2).
    if q < _P_LOW:
        log_q = math.log(q)
        t = math.sqrt(-2.0 * log_q)
        x = ((((((_C[0] * t + _C[1]) * t + _C[2]) * t + _C[3]) * t + _C[4]) * t + _C[5])
             / ((((_D[0] * t + _D[1]) * t + _D[2]) * t + _D[3]) * t + 1.0))
        # In the tail, written as (Phi(x)/q - 1) q e^(x^2/2) sqrt(2 pi) with q e^(x^2/2) =
        # exp(log q + x^2/2) ~ 1/|x|: no overflow of e^(x^2/2) (|x| > 37.6) and a
        # residual relative to q, accurate down to the smallest normal q.
        u = ((0.5 * math.erfc(-x / _SQRT2) / q - 1.0) * math.exp(log_q + 0.5 * x * x)
             * _SQRT2PI)
    else:
        r = q - 0.5
        s = r * r
        x = ((((((_A[0] * s + _A[1]) * s + _A[2]) * s + _A[3]) * s + _A[4]) * s + _A[5]) * r
             / (((((_B[0] * s + _B[1]) * s + _B[2]) * s + _B[3]) * s + _B[4]) * s + 1.0))
        u = (0.5 * math.erfc(-x / _SQRT2) - q) * _SQRT2PI * math.exp(0.5 * x * x)
    return x - u / (1.0 + 0.5 * x * u)


def ndtri(p: float) -> float:
    """Inverse of the standard normal CDF, Phi^-1(p); -inf at 0, +inf at 1.

    Acklam's rational approximation plus one Halley step with math.erfc: ~1e-15
    relative for normal p <= 1/2 (tested to 2e-13 down to p = 1e-300); above 1/2 through
    ``ndtri(p) = -ndtri(1 - p)`` (1 - p is exact there).
    """
    if not 0.0 < p < 1.0:
        if p == 0.0:
            return -math.inf
        if p == 1.0:
            return math.inf
        raise ValueError(f'ndtri: p must be in [0, 1], got {p!r}')
    if p <= 0.5:
        return _ndtri_lower(p)
    return -_ndtri_lower(1.0 - p)   # 1 - p is exact for p >= 1/2 (Sterbenz)


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
        pa = 0.5 * math.erfc(-a / _SQRT2)             # Phi(a), a < 0
        if b <= 0.0:
            mass = 0.5 * math.erfc(-b / _SQRT2) - pa
            if mass <= 0.0:
                x = mu
            else:
                p = pa + r * mass
                x = mu + sigma * (_ndtri_lower(p) if p > 0.0 else -math.inf)
        else:
            qb = 0.5 * math.erfc(b / _SQRT2)          # 1 - Phi(b)
            mass = (1.0 - pa) - qb
            p = pa + r * mass
            if p <= 0.5:
                x = mu + sigma * (_ndtri_lower(p) if p > 0.0 else -math.inf)
            else:
                q = qb + (1.0 - r) * mass               # 1 - p, without cancellation
                x = mu - sigma * _ndtri_lower(min(q, 0.5))
    x = -1.0 if x < -1.0 else (1.0 if x > 1.0 else x)
    return -x if flip else x


class RCGA(Optimizer):
    """Real-valued compact GA with persistent ('pe') or non-persistent ('ne') elitism.

    ``RCGA(dim, seed, start=None, *, n=25, elitism='ne', eta=12, sigma0=10.0)``.
    """

    algo: ClassVar[str] = 'rcga'
    OPTIONS: ClassVar[dict[str, OptionSpec]] = {
        'n': OptionSpec(int, 25, 'virtual population size n: a competition moves mu by '
                        '(w - l)/n', low=2, high=1_000_000),
        'elitism': OptionSpec(str, 'ne', "'ne' (elite replaced by the newcomer after eta "
                              "consecutive wins) or 'pe' (persistent elite)",
                              choices=('ne', 'pe')),
        'eta': OptionSpec(int, 12, "allowed length of inheritance with elitism='ne' "
                          '(consecutive elite wins; must be < n)', low=1, high=1_000_000),
        'sigma0': OptionSpec(float, 10.0, 'initial spread of every variable on x in '
                             '[-1, 1] (10: nearly uniform; 0.577: a uniform population)',
                             low=0.0, high=1e6, low_strict=True),
    }

    def __init__(self, dim: int, seed: int | np.random.SeedSequence,
                 start: np.ndarray | None = None, **options: Any) -> None:
        self.dim = check_dim(dim)
        seed = check_seed(seed)
        if start is not None:
            check_start(start, self.dim)
            raise OptimizerError('rcga does not take a start point (it starts from mu = 0, '
                                 'sigma = sigma0); pass start=None')
        opts = check_options(self.algo, self.OPTIONS, options)
        if opts['elitism'] == 'ne' and opts['eta'] >= opts['n']:   # (unused with 'pe')
            raise OptimizerError(f"rcga option eta must be an integer in [1, n - 1] = "
                                 f"[1, {opts['n'] - 1}] (eta < n), got {opts['eta']!r}")
        self._opts = opts
        self._seed_json = seed_json(seed)
        self.n: int = opts['n']
        self.elitism: str = opts['elitism']
        self.eta: int = opts['eta']
        self._rng = make_rng(seed)
        self._mu = [0.0] * self.dim           # python floats: scalar math is faster at dim 5
        self._sigma = [opts['sigma0']] * self.dim
        self.evaluations = 0
        self.generation = 0
        self.theta = 0
        self._elite: list[float] | None = None
        self._elite_loss = 0.0
        self._pending: PendingCheck | None = None
        self._pending_x: list[float] | None = None

    # ----------------------------------------------------------------------- sampling
    def _sample(self) -> list[float]:
        r = self._rng.random(self.dim).tolist()
        return [truncnorm_ppf(ri, m, s) for ri, m, s in zip(r, self._mu, self._sigma)]

    @staticmethod
    def _to_u(x: list[float]) -> np.ndarray:
        return (np.array(x) + 1.0) * 0.5

    def _update(self, w: list[float], l: list[float]) -> None:
        n = self.n
        for i in range(self.dim):
            mu = self._mu[i]
            mu1 = mu + (w[i] - l[i]) / n
            var = self._sigma[i] ** 2 + mu * mu - mu1 * mu1 + (w[i] * w[i] - l[i] * l[i]) / n
            self._mu[i] = mu1
            self._sigma[i] = math.sqrt(var) if var > 0.0 else 0.0
        self.generation += 1

    # ------------------------------------------------------------------------ ask/tell
    def ask(self) -> np.ndarray:
        """The next candidate u = (x + 1)/2, x sampled from the truncated Gaussians."""
        if self._pending is None:
            x = self._sample()
            self._pending_x = x
            self._pending = PendingCheck(self._to_u(x))
        return self._pending.u.copy()

    def tell(self, u: np.ndarray, loss: float) -> None:
        y = check_told(self._pending, u, loss)
        x = self._pending_x
        self._pending = None
        self._pending_x = None
        self.evaluations += 1
        if self._elite is None:                 # first generation: the elite's evaluation
            self._elite, self._elite_loss = x, y
            return
        if y < self._elite_loss:                # ties -> the elite
            self._update(x, self._elite)
            self._elite, self._elite_loss = x, y
            self.theta = 0
            return
        self._update(self._elite, x)
        if self.elitism == 'ne':
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
        return None if self._elite is None else self._to_u(self._elite)

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
            'algo': self.algo, 'version': _STATE_VERSION, 'config': self.config(),
            'rng': rng_state(self._rng), 'mu': list(self._mu), 'sigma': list(self._sigma),
            'evaluations': self.evaluations, 'generation': self.generation,
            'theta': self.theta, 'elite': None if self._elite is None else list(self._elite),
            'elite_loss': self._elite_loss,
            'pending': None if self._pending_x is None else list(self._pending_x),
        }

    @classmethod
    def _from_state(cls, state: dict[str, Any]) -> 'RCGA':
        try:
            if state.get('version') != _STATE_VERSION:
                raise OptimizerError(f"rcga state version {state.get('version')!r} "
                                     f'not supported (expected {_STATE_VERSION})')
            cfg = dict(state['config'])
            dim = cfg.pop('dim')
            cfg.pop('algo'), cfg.pop('seed')
            opt = cls(dim, 0, None, **cfg)
            set_rng_state(opt._rng, state['rng'])

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
            opt._pending_x = None if state['pending'] is None else vec(state['pending'])
            opt._pending = (None if opt._pending_x is None
                            else PendingCheck(opt._to_u(opt._pending_x)))
            opt._seed_json = state['config']['seed']
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, OptimizerError):
                raise
            raise OptimizerError(f'bad rcga state: {e!r}') from None
        return opt
