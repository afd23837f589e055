"""Real-valued compact GA (rcGA, Mininno, Cupertino, Naso 2008) with pe or ne elitism.

Per variable a mean mu_i and a spread sigma_i on x in [-1, 1]; a candidate samples each
x_i from N(mu_i, sigma_i^2) truncated to [-1, 1] (:func:`truncnorm_ppf`) and is handed
out as u = (x + 1)/2; each generation the winner of elite and newcomer replaces the loser
in a virtual population of n.  The equations, the elitism and the caveat on sigma0:
docs/optimisers.md, "Real-valued compact GA".
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import scipy.special as _sc

from .base import FLOAT, INT, Codec, Elitist, Field, Optimizer, OptimizerError
from .options import check_eta_below_n

#: converged() when every sigma is below this (x units; u resolution SIGMA_TOL/2, finer
#: than a 16-bit gene's 1.5e-5).
SIGMA_TOL = 1e-6

_SQRT2 = math.sqrt(2.0)
# bound once: one global lookup per call on the sampling path instead of two
_erfc, _sqrt = math.erfc, math.sqrt


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


def _vector(opt: RCGA, v: Any) -> list[float]:
    """A saved vector of dim floats."""
    out = [float(t) for t in v]
    if len(out) != opt.dim:
        raise OptimizerError(f'bad rcga state: vectors must have {opt.dim} values')
    return out


_VECTOR = Codec(_vector, lambda _o, v: list(v))
_VECTOR_OR_NONE = Codec(
    lambda o, v: None if v is None else _vector(o, v), lambda _o, v: None if v is None else list(v)
)


class RCGA(Elitist, Optimizer):
    """Real-valued compact GA with persistent ('pe') or non-persistent ('ne') elitism."""

    algo: ClassVar[str] = 'rcga'
    NO_START: ClassVar[str] = 'it starts from mu = 0, sigma = sigma0'
    STATE: ClassVar[tuple[Field, ...]] = (
        Field('mu', _VECTOR, '_mu'),
        Field('sigma', _VECTOR, '_sigma'),
        Field('evaluations', INT),
        Field('generation', INT),
        Field('theta', INT),
        Field('elite', _VECTOR_OR_NONE, '_elite'),
        Field('elite_loss', FLOAT, '_elite_loss'),
        Field('pending', _VECTOR_OR_NONE, '_px'),  # (x; u = (x + 1)/2 by _restored)
    )

    def _check_options(self, options: dict[str, Any]) -> dict[str, Any]:
        opts = super()._check_options(options)
        if opts['elitism'] == 'ne':  # (eta is unused with 'pe')
            check_eta_below_n(self.algo, opts)
        return opts

    def _setup(self, x0: np.ndarray | None) -> None:
        opts = self._opts
        self.n: int = opts['n']
        self.elitism: str = opts['elitism']
        self.eta: int = opts['eta']
        self._mu = [0.0] * self.dim  # python floats: scalar math is faster at dim 5
        self._sigma = [opts['sigma0']] * self.dim
        self.generation = 0
        self.theta = 0
        self._elite: list[float] | None = None
        self._elite_loss = 0.0
        self._px: list[float] | None = None  # the pending candidate's x

    @staticmethod
    def _to_u(x: list[float]) -> list[float]:
        return [(xi + 1.0) * 0.5 for xi in x]

    @property
    def iterations(self) -> int:
        return self.generation

    def _propose(self) -> list[float]:
        """The next candidate u = (x + 1)/2, x sampled from the truncated Gaussians."""
        i = self._draws(self.dim)
        rs = self._blk[i : i + self.dim]
        self._px = x = [
            truncnorm_ppf(r, m, s) for r, m, s in zip(rs, self._mu, self._sigma, strict=True)
        ]
        return self._to_u(x)

    def _update(self, u: list[float], loss: float, aborted: bool) -> None:
        """The competition of elite and newcomer and the moment update."""
        y = loss
        x = self._px
        assert x is not None  # asked: _propose set it
        self._px = None
        elite = self._elite
        if elite is None:  # first generation: the elite's evaluation
            self._elite, self._elite_loss = x, y
            return
        newcomer_wins = y < self._elite_loss  # ties -> the elite
        w, l = (x, elite) if newcomer_wins else (elite, x)
        # The winner replaces the loser in the virtual population of n.
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

    @property
    def mu(self) -> np.ndarray:
        """Means of the sampling distributions on [-1, 1] (a copy)."""
        return np.array(self._mu)

    @property
    def sigma(self) -> np.ndarray:
        """Spreads of the sampling distributions on [-1, 1] (a copy)."""
        return np.array(self._sigma)

    def _held_elite(self) -> tuple[list[float], float] | None:
        return None if self._elite is None else (self._to_u(self._elite), self._elite_loss)

    def solution(self) -> np.ndarray:
        """The distribution's centre as normalised parameters, (clip(mu, -1, 1) + 1)/2."""
        return (np.clip(np.array(self._mu), -1.0, 1.0) + 1.0) * 0.5

    def converged(self) -> bool:
        """Every sigma_i < SIGMA_TOL."""
        return max(self._sigma) < SIGMA_TOL

    def _restored(self, state: dict[str, Any]) -> None:
        self._pending = None if self._px is None else self._to_u(self._px)
