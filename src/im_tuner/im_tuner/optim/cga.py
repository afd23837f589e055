"""Binary compact genetic algorithms: cGA (Harik et al. 1999), peCGA and neCGA (Ahn and
Ramakrishna 2003), as in the paper's Figs. 1-3 (minimisation: "wins" is the lower loss).

The genome and its decoding, the probability vector as integer offsets k_j, the tie rules
and neCGA's two elite replacements: docs/optimisers.md, "Binary compact GAs"; the packed
representation below, its "Speed".
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from .base import FLOAT, INT, SAVED, Codec, Elitist, Field, Optimizer, OptimizerError
from .options import check_eta_below_n

# A genome's guard bytes (0x80 = bit 1, 0x00 = bit 0) <-> its '0'/'1' string.
_TO_CHARS = bytes.maketrans(b'\x00\x80', b'01')
_FROM_CHARS = bytes.maketrans(b'01', b'\x00\x80')


class BinaryCGA(Optimizer):
    """The binary compact GAs; ``CGA``, ``PECGA``, ``NECGA`` differ only in ``_ELITIST``
    and ``_NE``.  The PV and genomes are python ints of m fields of W bytes (SWAR,
    docs/optimisers.md "Speed"): ``_Y`` holds 2^(8W-1) + k_j + K per field, a sample is
    ``(_Y - L) & _H`` (L: the uniforms' levels), a competition one add and one subtract."""

    NO_START: ClassVar[str] = 'a compact GA starts from p = 0.5'
    _ELITIST: ClassVar[bool] = False  # pe/neCGA: an elite and one newcomer
    _NE: ClassVar[bool] = False  # neCGA: theta and the elite replacement
    eta: int  # neCGA only (set by NECGA._setup)
    elite_replacement: str  # neCGA only

    def _setup(self, x0: np.ndarray | None) -> None:
        opts = self._opts
        self.n: int = opts['n']
        self.bits: int = opts['bits']
        self.gray: bool = opts['coding'] == 'gray'
        self.m = m = self.dim * self.bits
        self._K = K = (self.n + 1) // 2  # |k_j| = K <=> p_j in {0, 1}
        offsets = np.arange(-K, K + 1)
        # p_j = table[k_j + K]: one correctly rounded division per offset, exactly 0.0 and
        # 1.0 at the ends.
        self._ptable = np.clip((self.n + 2 * offsets) / (2.0 * self.n), 0.0, 1.0)
        # Fields: W bytes per genome bit, the guard bit 2^(8W-1) above values up to 2K.
        self._W = W = next(w for w in (1, 2, 4) if 1 << (8 * w - 1) > 2 * K)
        self._fdtype = np.dtype(f'>u{W}')
        self._guard = 1 << (8 * W - 1)
        self._shift = 8 * W - 1  # guard bit -> field unit
        self._nbytes = m * W
        self._H = int.from_bytes((bytes([0x80]) + bytes(W - 1)) * m, 'big')
        self._T = self._pack(np.full(m, 2 * K))  # every field at P_j = 2K
        self._Y = self._pack(np.full(m, K))  # p = 1/2
        # Decoding: gene i = (genome >> shift_i) & mask, u_i = v_i / (2^bits - 1).
        self._shifts = [self.bits * (self.dim - 1 - i) for i in range(self.dim)]
        self._mask = (1 << self.bits) - 1
        self._vmax = float(2**self.bits - 1)
        self._gray_shifts = [s for s in (1, 2, 4, 8, 16) if s < self.bits]
        self.generation = 0  # completed competitions (PV updates)
        self._pg: int | None = None  # the pending candidate's genome (guard-bit form)
        # cGA: the first individual of the generation; pe/neCGA: the elite (None while a
        # sampled replacement is pending).
        self._held: int | None = None
        self._held_loss = 0.0
        self.theta = 0  # neCGA: consecutive wins of the current elite

    def _pack(self, values: np.ndarray) -> int:
        """Field values (m,) -> an int with the guard bit set in every field."""
        return self._H | int.from_bytes(np.asarray(values).astype(self._fdtype).tobytes(), 'big')

    def _fields(self, y: int) -> np.ndarray:
        """An int of m fields -> the field values below the guard bit (m,) int64."""
        v = np.frombuffer(y.to_bytes(self._nbytes, 'big'), dtype=self._fdtype)
        return v.astype(np.int64) & (self._guard - 1)

    def _chars(self, s: int) -> bytes:
        """A genome (guard-bit form) -> its bits as b'0'/b'1', genome order."""
        b = s.to_bytes(self._nbytes, 'big')
        return (b[:: self._W] if self._W > 1 else b).translate(_TO_CHARS)

    def _decode_g(self, s: int) -> list[float]:
        """A genome (guard-bit form) -> u as python floats."""
        g = int(self._chars(s), 2)
        mask, vmax = self._mask, self._vmax
        if not self.gray:
            return [((g >> sh) & mask) / vmax for sh in self._shifts]
        pu = []
        for sh in self._shifts:
            v = (g >> sh) & mask
            for t in self._gray_shifts:  # prefix xor from the MSB
                v ^= v >> t
            pu.append(v / vmax)
        return pu

    def _to_str(self, s: int | None) -> str | None:
        return None if s is None else self._chars(s).decode()

    def _from_str(self, text: Any) -> int | None:
        if text is None:
            return None
        if not isinstance(text, str) or len(text) != self.m or set(text) - {'0', '1'}:
            raise OptimizerError(f'bad {self.algo} state: a bit string of length {self.m} expected')
        b = text.encode().translate(_FROM_CHARS)
        if self._W > 1:
            b = b''.join(c + bytes(self._W - 1) for c in (b[i : i + 1] for i in range(self.m)))
        return int.from_bytes(b, 'big')

    def _extremes(self) -> tuple[int, int]:
        """(fields with p_j = 1, fields with p_j = 0), as guard-bit masks."""
        Y, H = self._Y, self._H
        return (H - (Y ^ self._T)) & H, (H - (Y ^ H)) & H

    def _block(self) -> list[int]:
        """The next block: per sample, m uniforms r_j (rng.random(m), as one call), kept
        as the packed levels L_j (the same sample bits as r_j < p_j)."""
        B, nb = self._BLOCK, self._nbytes
        lev = np.searchsorted(self._ptable, self._rng.random(B * self.m), side='right')
        buf = lev.astype(self._fdtype).tobytes()
        return [int.from_bytes(buf[o : o + nb], 'big') for o in range(0, B * nb, nb)]

    def _unread(self) -> int:
        return (len(self._blk) - self._bi) * self.m  # m doubles a sample

    def decode(self, bits: np.ndarray) -> np.ndarray:
        """Normalised parameters u (dim,) of a genome (m bools or 0/1 ints) (docs/optimisers.md)."""
        g = np.asarray(bits, dtype=bool).reshape(self.dim, self.bits)
        if self.gray:
            g = np.logical_xor.accumulate(g, axis=1)
        return g.dot(2.0 ** np.arange(self.bits - 1, -1, -1)) / self._vmax

    @property
    def p(self) -> np.ndarray:
        """The probability vector (m,) (a copy)."""
        return self._ptable[self._fields(self._Y)]

    @property
    def offsets(self) -> np.ndarray:
        """The integer offsets k (m,), p = clip((n + 2k)/(2n), 0, 1) (a copy)."""
        return self._fields(self._Y) - self._K

    def converged(self) -> bool:
        """Every p_j is 0 or 1 (the PV is a single genome)."""
        top, zero = self._extremes()
        return top | zero == self._H

    def solution(self) -> np.ndarray:
        """The PV rounded to a genome (p_j >= 1/2 -> 1), decoded to u."""
        return self.decode(self.offsets >= 0)

    @property
    def iterations(self) -> int:
        return self.generation

    def _propose(self) -> list[float]:
        """A fresh sample from the PV (its genome kept in ``_pg`` until told)."""
        # Field j keeps its guard bit <=> P_j >= L_j <=> r_j < p_j.
        i = self._draws(1)
        self._pg = s = (self._Y - self._blk[i]) & self._H
        return self._decode_g(s)

    def _update(self, u: list[float], loss: float, aborted: bool) -> None:
        """The competitions of Figs. 1-3."""
        s = self._pg
        assert s is not None  # asked: _propose set it
        self._pg = None
        held = self._held
        if held is None:  # cGA: a; pe/neCGA: the first or a new elite
            self._held, self._held_loss = s, loss
            return
        # The competition: winner w, loser l; k_j += 1 where w_j = 1 != l_j, -= 1 where
        # w_j = 0 != l_j (in guard-bit form, moved down to the fields' units).  Ties: the
        # elite (pe/neCGA), a, the first sampled (cGA).
        newcomer_wins = loss < self._held_loss
        w = s if newcomer_wins else held
        x = s ^ held
        up = x & w
        down = x ^ up
        if self._ELITIST and newcomer_wins:
            # The beaten elite came from an older PV: clamp k_j to [-K, K], i.e. no +1
            # where P_j = 2K and no -1 where P_j = 0.  (In every other case the loser is
            # a sample of the current PV, which agrees with it there.)
            top, zero = self._extremes()
            up ^= up & top
            down ^= down & zero
        sh = self._shift
        self._Y = self._Y + (up >> sh) - (down >> sh)
        self.generation += 1
        if not self._ELITIST:
            self._held = None
        elif newcomer_wins:
            self._held, self._held_loss = s, loss
            self.theta = 0
        elif self._NE:
            self.theta += 1
            if self.theta >= self.eta:
                self.theta = 0
                if self.elite_replacement == 'newcomer':
                    self._held, self._held_loss = s, loss
                else:
                    self._held = None  # the next ask samples the new elite

    @property
    def phase(self) -> str:
        """What the next ask samples (in the state), from whether an individual is held:
        cGA 'first' (a of a generation) or 'second' (b); pe/neCGA 'elite' (sampled from the
        PV: the first generation, or a replacement) or 'newcomer'."""
        if self._ELITIST:
            return 'elite' if self._held is None else 'newcomer'
        return 'first' if self._held is None else 'second'

    def _load_k(self, k: Any) -> int:
        """The PV from the saved offsets k (m integers in [-K, K])."""
        a = np.array(k, dtype=np.int64)
        if a.shape != (self.m,) or np.any(np.abs(a) > self._K):
            raise OptimizerError(
                f'bad {self.algo} state: k must be {self.m} integers in [-{self._K}, {self._K}]'
            )
        return self._pack(a + self._K)

    def _dump_k(self, y: int) -> list[int]:
        return (self._fields(y) - self._K).tolist()

    #: a genome as its bit string ('0'/'1', genome order) or None
    _GENOME = Codec(_from_str, _to_str)
    STATE: ClassVar[tuple[Field, ...]] = (
        Field('k', Codec(_load_k, _dump_k), '_Y'),
        Field('evaluations', INT),
        Field('generation', INT),
        Field('phase', SAVED),  # (checked against held by _restored)
        Field('theta', INT),
        Field('held', _GENOME, '_held'),
        Field('held_loss', FLOAT, '_held_loss'),
        Field('pending', _GENOME, '_pg'),
    )

    def _restored(self, state: dict[str, Any]) -> None:
        if state['phase'] != self.phase:
            raise OptimizerError(
                f'bad {self.algo} state: phase {state["phase"]!r} with '
                f'held {"None" if self._held is None else "a genome"}'
            )
        # What the state_dict of a real run always satisfies (and tell relies on): the
        # pending sample, and the cGA's a, were drawn from this PV (1 where p_j = 1, 0
        # where p_j = 0).
        top, zero = self._extremes()
        for s in (self._pg, None if self._ELITIST else self._held):
            if s is not None and not (s & top == top and s & zero == 0):
                raise OptimizerError(
                    f'bad {self.algo} state: a sample that this PV '
                    'cannot produce (1 where p = 0 or 0 where p = 1)'
                )
        self._pending = None if self._pg is None else self._decode_g(self._pg)


class CGA(BinaryCGA):
    """Compact GA, Fig. 1: two samples per generation, the first sampled wins ties."""

    algo: ClassVar[str] = 'cga'


class PECGA(Elitist, BinaryCGA):
    """Persistent elitist compact GA, Fig. 2: elite vs one newcomer, ties -> the elite."""

    algo: ClassVar[str] = 'pecga'
    _ELITIST: ClassVar[bool] = True

    def _held_elite(self) -> tuple[list[float], float] | None:
        return None if self._held is None else (self._decode_g(self._held), self._held_loss)


class NECGA(PECGA):
    """Non-persistent elitist compact GA, Fig. 3 (the paper's tuner)."""

    algo: ClassVar[str] = 'necga'
    _NE: ClassVar[bool] = True

    def _check_options(self, options: dict[str, Any]) -> dict[str, Any]:
        opts = super()._check_options(options)
        check_eta_below_n(self.algo, opts)
        return opts

    def _setup(self, x0: np.ndarray | None) -> None:
        super()._setup(x0)
        self.eta = self._opts['eta']
        self.elite_replacement = self._opts['elite_replacement']
