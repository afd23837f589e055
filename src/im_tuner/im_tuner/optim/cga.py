"""Binary compact genetic algorithms: cGA (Harik et al. 1999), peCGA and neCGA (Ahn and
Ramakrishna 2003), as in the paper's Figs. 1-3.

Genome: ``dim`` contiguous genes of ``bits`` bits (m = dim x bits), most significant bit
first; gene i holds v_i = sum_j b_(i,j) 2^(bits-1-j) in [0, 2^bits - 1] and decodes to
u_i = v_i / (2^bits - 1) in [0, 1] (DEAP's bin2float).  ``coding='gray'`` reads each gene
as a reflected Gray code first: b_0 = g_0, b_j = b_(j-1) xor g_j.

Probability vector (PV): integer offsets k_j with p_j = clip((n + 2 k_j)/(2 n), 0, 1),
i.e. 0.5 + k_j/n without the float drift of repeated +-1/n (0.5 + 5 x 0.1 is not 1.0).
k_j is clamped to [-K, K], K = ceil(n/2): for odd n the last step to 0 or 1 is clamped
(0.9 -> 1.0 for n = 5).  A sampled bit is 1 when a uniform draw r in [0, 1) is < p_j.
A competition moves k_j by +1 (winner's bit 1) or -1 (winner's bit 0) where winner and
loser differ.  ``converged()`` when every p_j is 0 or 1.

* cGA (Fig. 1): per generation two samples a, b (2 evaluations); the lower loss wins,
  ties go to a (the first sampled), which keeps E[p] a martingale on flat fitness.
* peCGA (Fig. 2): an elite and its stored loss; the first generation samples the elite
  (1 evaluation) and then every generation samples one newcomer (1 evaluation); the
  newcomer wins only with a strictly lower loss (ties -> the elite); the winner is the
  new elite.
* neCGA (Fig. 3): as peCGA, plus theta = consecutive wins of the current elite (reset to
  0 when a newcomer wins and becomes the elite).  When theta reaches eta the elite is
  replaced and theta reset: ``elite_replacement='sample'`` (default, the paper's figure):
  the next ask is a fresh sample from the PV, one extra evaluation whose loss becomes the
  stored elite loss; ``'newcomer'`` (the authors' Java code): the newcomer just evaluated
  (the loser) becomes the elite with its loss, exactly one evaluation per generation.

Minimisation: "wins" means the lower loss.  See docs/optimisers.md.
"""
from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from .base import (OptimizerError, Optimizer, OptionSpec, PendingCheck, check_dim,
                   check_options, check_seed, check_start, check_told, make_rng, rng_state,
                   seed_json, set_rng_state)

__all__ = ['CGA', 'PECGA', 'NECGA', 'BinaryCGA']

_STATE_VERSION = 1

# Phases: what the next ask samples.
_FIRST = 'first'        # cGA: individual a of a generation
_SECOND = 'second'      # cGA: individual b
_ELITE = 'elite'        # pe/neCGA: an elite sampled from the PV (first generation, resample)
_NEWCOMER = 'newcomer'  # pe/neCGA: the newcomer that competes with the elite


def _bits_str(b: np.ndarray | None) -> str | None:
    return None if b is None else ''.join('1' if x else '0' for x in b.tolist())


def _bits_arr(s: str | None, m: int) -> np.ndarray | None:
    if s is None:
        return None
    if not isinstance(s, str) or len(s) != m or set(s) - {'0', '1'}:
        raise OptimizerError(f'bad cga state: a bit string of length {m} expected')
    return np.frombuffer(s.encode(), dtype=np.uint8) == ord('1')


_COMMON_OPTIONS: dict[str, OptionSpec] = {
    'n': OptionSpec(int, 25, 'virtual population size n: each competition moves a '
                    'probability by 1/n', low=2, high=1_000_000),
    'bits': OptionSpec(int, 16, 'bits per parameter (resolution 1/(2^bits - 1) of the '
                       'normalised range)', low=1, high=32),
    'coding': OptionSpec(str, 'binary', "gene coding: 'binary' (plain, most significant "
                         "bit first) or 'gray' (reflected Gray code)",
                         choices=('binary', 'gray')),
}


class BinaryCGA(Optimizer):
    """Shared machinery of the binary compact GAs (PV, sampling, decoding, state I/O)."""

    OPTIONS: ClassVar[dict[str, OptionSpec]] = _COMMON_OPTIONS
    _ELITIST: ClassVar[bool] = False

    def __init__(self, dim: int, seed: int | np.random.SeedSequence,
                 start: np.ndarray | None = None, **options: Any) -> None:
        self.dim = check_dim(dim)
        seed = check_seed(seed)
        if start is not None:
            check_start(start, self.dim)
            raise OptimizerError(f'{self.algo} does not take a start point (a compact GA '
                                 'starts from p = 0.5); pass start=None')
        opts = check_options(self.algo, self.OPTIONS, options)
        self._check_more(opts)
        self._opts = opts
        self._seed_json = seed_json(seed)
        self.n: int = opts['n']
        self.bits: int = opts['bits']
        self.gray: bool = opts['coding'] == 'gray'
        self.m = self.dim * self.bits
        self._K = (self.n + 1) // 2            # |k_j| = K <=> p_j in {0, 1}
        self._rng = make_rng(seed)
        self._k = np.zeros(self.m, dtype=np.int64)
        offsets = np.arange(-self._K, self._K + 1)
        self._ptable = np.clip((self.n + 2 * offsets) / (2.0 * self.n), 0.0, 1.0)
        self._p = np.full(self.m, 0.5)
        # Decoding: v = genes @ weights, weights 2^(bits-1) ... 1 (exact in float64 up to
        # 32 bits); u = v / (2^bits - 1).
        self._weights = 2.0 ** np.arange(self.bits - 1, -1, -1)
        self._vmax = float(2 ** self.bits - 1)
        self.evaluations = 0
        self.generation = 0               # completed competitions (PV updates)
        self._phase = _ELITE if self._ELITIST else _FIRST
        self._pending: PendingCheck | None = None
        self._pending_bits: np.ndarray | None = None
        # cGA: the first individual of the generation; pe/neCGA: the elite.
        self._held: np.ndarray | None = None
        self._held_loss = 0.0
        self.theta = 0                    # neCGA: consecutive wins of the current elite

    def _check_more(self, opts: dict[str, Any]) -> None:
        """Cross-option checks of subclasses."""

    # ----------------------------------------------------------------- PV and decoding
    def _refresh_p(self) -> None:
        # p_j = table[k_j + K]; the table holds one correctly rounded division per offset,
        # exactly 0.0 and 1.0 at the ends (a lookup is 3x cheaper than recomputing).
        np.take(self._ptable, self._k + self._K, out=self._p)

    def _sample(self) -> np.ndarray:
        return self._rng.random(self.m) < self._p

    def decode(self, bits: np.ndarray) -> np.ndarray:
        """Normalised parameters u (dim,) of a genome (m bools or 0/1 ints), see module doc."""
        g = np.asarray(bits, dtype=bool).reshape(self.dim, self.bits)
        if self.gray:
            g = np.logical_xor.accumulate(g, axis=1)
        return g.dot(self._weights) / self._vmax

    def _update(self, winner: np.ndarray, loser: np.ndarray) -> None:
        """k_j += +1/-1 toward the winner's bit where winner and loser differ; clamp."""
        self._k += winner
        self._k -= loser
        np.minimum(self._k, self._K, out=self._k)
        np.maximum(self._k, -self._K, out=self._k)
        self._refresh_p()
        self.generation += 1

    @property
    def p(self) -> np.ndarray:
        """The probability vector (m,) (a copy)."""
        return self._p.copy()

    @property
    def offsets(self) -> np.ndarray:
        """The integer offsets k (m,), p = clip((n + 2k)/(2n), 0, 1) (a copy)."""
        return self._k.copy()

    def converged(self) -> bool:
        """Every p_j is 0 or 1 (the PV is a single genome)."""
        return bool(np.all(np.abs(self._k) == self._K))

    def solution(self) -> np.ndarray:
        """The PV rounded to a genome (p_j >= 1/2 -> 1), decoded to u."""
        return self.decode(self._k >= 0)

    # ------------------------------------------------------------------------ ask/tell
    def ask(self) -> np.ndarray:
        """The next candidate: a fresh sample from the PV (kept until told)."""
        if self._pending is None:
            b = self._sample()
            self._pending_bits = b
            self._pending = PendingCheck(self.decode(b))
        return self._pending.u.copy()

    def tell(self, u: np.ndarray, loss: float) -> None:
        y = check_told(self._pending, u, loss)
        bits = self._pending_bits
        self._pending = None
        self._pending_bits = None
        self.evaluations += 1
        self._told(bits, y)

    def _told(self, bits: np.ndarray, y: float) -> None:
        raise NotImplementedError

    # ---------------------------------------------------------------------- reporting
    def config(self) -> dict[str, Any]:
        return {'algo': self.algo, 'dim': self.dim, 'seed': self._seed_json, **self._opts}

    # ---------------------------------------------------------------------- state I/O
    def state_dict(self) -> dict[str, Any]:
        return {
            'algo': self.algo, 'version': _STATE_VERSION, 'config': self.config(),
            'rng': rng_state(self._rng), 'k': self._k.tolist(),
            'evaluations': self.evaluations, 'generation': self.generation,
            'phase': self._phase, 'theta': self.theta,
            'held': _bits_str(self._held), 'held_loss': self._held_loss,
            'pending': _bits_str(self._pending_bits),
        }

    @classmethod
    def _from_state(cls, state: dict[str, Any]) -> 'BinaryCGA':
        try:
            if state.get('version') != _STATE_VERSION:
                raise OptimizerError(f"{cls.algo} state version {state.get('version')!r} "
                                     f'not supported (expected {_STATE_VERSION})')
            cfg = dict(state['config'])
            dim = cfg.pop('dim')
            cfg.pop('algo'), cfg.pop('seed')
            opt = cls(dim, 0, None, **cfg)
            set_rng_state(opt._rng, state['rng'])
            k = np.array(state['k'], dtype=np.int64)
            if k.shape != (opt.m,) or np.any(np.abs(k) > opt._K):
                raise OptimizerError(f'bad {cls.algo} state: k must be {opt.m} integers '
                                     f'in [-{opt._K}, {opt._K}]')
            opt._k = k
            opt._refresh_p()
            opt.evaluations = int(state['evaluations'])
            opt.generation = int(state['generation'])
            if state['phase'] not in ((_ELITE, _NEWCOMER) if cls._ELITIST
                                      else (_FIRST, _SECOND)):
                raise OptimizerError(f"bad {cls.algo} state: phase {state['phase']!r}")
            opt._phase = state['phase']
            opt.theta = int(state['theta'])
            opt._held = _bits_arr(state['held'], opt.m)
            opt._held_loss = float(state['held_loss'])
            opt._pending_bits = _bits_arr(state['pending'], opt.m)
            opt._pending = (None if opt._pending_bits is None
                            else PendingCheck(opt.decode(opt._pending_bits)))
            opt._seed_json = state['config']['seed']
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, OptimizerError):
                raise
            raise OptimizerError(f'bad {cls.algo} state: {e!r}') from None
        return opt


class CGA(BinaryCGA):
    """Compact GA, Fig. 1: two samples per generation, the first sampled wins ties.

    ``CGA(dim, seed, start=None, *, n=25, bits=16, coding='binary')``.
    """

    algo: ClassVar[str] = 'cga'

    def _told(self, bits: np.ndarray, y: float) -> None:
        if self._phase == _FIRST:
            self._held, self._held_loss = bits, y
            self._phase = _SECOND
            return
        if self._held_loss <= y:      # ties -> a, the first sampled
            self._update(self._held, bits)
        else:
            self._update(bits, self._held)
        self._held = None
        self._phase = _FIRST


class PECGA(BinaryCGA):
    """Persistent elitist compact GA, Fig. 2: elite vs one newcomer, ties -> the elite.

    ``PECGA(dim, seed, start=None, *, n=25, bits=16, coding='binary')``.
    """

    algo: ClassVar[str] = 'pecga'
    _ELITIST: ClassVar[bool] = True

    @property
    def elite(self) -> np.ndarray | None:
        """The elite's normalised parameters (None before its evaluation)."""
        return None if self._held is None else self.decode(self._held)

    @property
    def elite_loss(self) -> float | None:
        """The elite's stored loss (measured once, when it was evaluated)."""
        return None if self._held is None else self._held_loss

    def _told(self, bits: np.ndarray, y: float) -> None:
        if self._phase == _ELITE:
            self._held, self._held_loss = bits, y
            self._phase = _NEWCOMER
            return
        newcomer_wins = y < self._held_loss        # ties -> the elite
        if newcomer_wins:
            self._update(bits, self._held)
        else:
            self._update(self._held, bits)
        self._after_competition(bits, y, newcomer_wins)

    def _after_competition(self, bits: np.ndarray, y: float, newcomer_wins: bool) -> None:
        if newcomer_wins:
            self._held, self._held_loss = bits, y


class NECGA(PECGA):
    """Non-persistent elitist compact GA, Fig. 3 (the paper's tuner; defaults n=25, eta=12).

    ``NECGA(dim, seed, start=None, *, n=25, bits=16, coding='binary', eta=12,
    elite_replacement='sample')``.
    """

    algo: ClassVar[str] = 'necga'
    OPTIONS: ClassVar[dict[str, OptionSpec]] = {
        **_COMMON_OPTIONS,
        'eta': OptionSpec(int, 12, 'allowed length of inheritance eta: after eta '
                          'consecutive wins the elite is replaced (must be < n)',
                          low=1, high=1_000_000),
        'elite_replacement': OptionSpec(
            str, 'sample', "what replaces an elite that won eta times in a row: 'sample' "
            "(a fresh PV sample, one extra evaluation; the paper's Fig. 3) or 'newcomer' "
            "(the newcomer just evaluated; the authors' Java code)",
            choices=('sample', 'newcomer')),
    }

    def _check_more(self, opts: dict[str, Any]) -> None:
        if opts['eta'] >= opts['n']:
            raise OptimizerError(f"necga option eta must be an integer in [1, n - 1] = "
                                 f"[1, {opts['n'] - 1}] (eta < n), got {opts['eta']!r}")
        self.eta: int = opts['eta']
        self.elite_replacement: str = opts['elite_replacement']

    def _after_competition(self, bits: np.ndarray, y: float, newcomer_wins: bool) -> None:
        if newcomer_wins:
            self._held, self._held_loss = bits, y
            self.theta = 0
            return
        self.theta += 1
        if self.theta >= self.eta:
            self.theta = 0
            if self.elite_replacement == 'newcomer':
                self._held, self._held_loss = bits, y
            else:
                self._held = None
                self._phase = _ELITE
