"""Binary compact GAs (im_tuner.optim.cga): decoding, PV arithmetic, tie rules, the
neCGA replacement, and the Monte Carlo oracles of the shared notes (seeded, |z| < 4):

* cGA neutral drift, flat fitness, ties to the first: E[p(1-p)] = (1/4)(1 - 2/n^2)^t;
* peCGA on flat fitness, ties to the elite: E|p - 1/2| = (1/2)(1 - (1 - 1/n)^t), while a
  newcomer that wins ties gives ~0.026 (so the test tells the tie rules apart);
* cGA on OneMax (100 bits) against the gambler's-ruin bound, evaluations/n ~ 32;
* deceptive trap-4 x 10: elitism solves more blocks, and the cGA gets worse with n.

Flat fitness leaves the bits independent, so one run of 100 one-bit genes gives 100
samples of the per-bit process; standard errors are taken over runs.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from im_tuner.optim import CGA, NECGA, PECGA, Optimizer, OptimizerError, make_optimizer


def _set_offsets(opt, k):
    """A copy of ``opt`` with PV offsets ``k`` (through the public state round trip)."""
    st = opt.state_dict()
    st['k'] = [int(v) for v in k]
    return Optimizer.from_state(st)


# ------------------------------------------------------------------------ decoding
def test_bit_order_msb_first_by_hand():
    opt = CGA(2, 0, n=10, bits=3)
    # p = 1 where k = +5, p = 0 where k = -5 (n = 10): genes 100 | 011.
    opt = _set_offsets(opt, [5, -5, -5, -5, 5, 5])
    np.testing.assert_array_equal(opt.p, [1, 0, 0, 0, 1, 1])
    assert opt.converged()
    u = opt.ask()
    np.testing.assert_array_equal(u, [4 / 7, 3 / 7])
    np.testing.assert_array_equal(opt.decode([1, 1, 1, 0, 0, 1]), [1.0, 1 / 7])


def test_gray_decoding_by_hand():
    opt = CGA(2, 0, n=10, bits=3, coding='gray')
    # Gray 100 -> binary 111 = 7; Gray 011 -> binary 010 = 2.
    opt = _set_offsets(opt, [5, -5, -5, -5, 5, 5])
    np.testing.assert_array_equal(opt.ask(), [1.0, 2 / 7])
    # Every 4-bit Gray code decodes to its rank: consecutive values differ in one bit.
    g4 = CGA(1, 0, bits=4, coding='gray')
    for v in range(16):
        gray = v ^ (v >> 1)
        bits = [(gray >> (3 - j)) & 1 for j in range(4)]
        assert g4.decode(bits)[0] * 15 == v


@pytest.mark.parametrize('bits', [1, 16, 32])
def test_decoding_range(bits):
    opt = CGA(3, 0, bits=bits)
    ones = np.ones(3 * bits, dtype=bool)
    np.testing.assert_array_equal(opt.decode(ones), [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(opt.decode(~ones), [0.0, 0.0, 0.0])
    one = np.zeros(3 * bits, dtype=bool)
    one[bits - 1] = True  # least significant bit of gene 0
    assert opt.decode(one)[0] == 1 / (2**bits - 1)
    assert opt.m == 3 * bits and opt.p.shape == (3 * bits,)


# -------------------------------------------------------------------- PV arithmetic
@pytest.mark.parametrize(
    'n, path', [(10, [0.5, 0.6, 0.7, 0.8, 0.9, 1.0]), (5, [0.5, 0.7, 0.9, 1.0])]
)
def test_pv_steps_land_exactly_on_one(n, path):
    # One bit, loss -bit: every differing pair moves p up by 1/n; the last step of odd n
    # is clamped (0.9 -> 1.0).  Float accumulation would give 0.9999999999999999.
    opt = CGA(1, 3, n=n, bits=1)
    seen = [float(opt.p[0])]
    while not opt.converged():
        u = opt.ask()
        opt.tell(u, -float(u[0]))
        if float(opt.p[0]) != seen[-1]:
            seen.append(float(opt.p[0]))
    assert seen == path
    assert opt.p[0] == 1.0 and opt.offsets[0] == (n + 1) // 2


def test_cga_tie_goes_to_the_first_sampled():
    opt = CGA(40, 11, n=10, bits=1)
    a = opt.ask()
    opt.tell(a, 1.0)
    b = opt.ask()
    opt.tell(b, 1.0)  # tie
    k = opt.offsets
    np.testing.assert_array_equal(k, (a - b).astype(int))  # +1 toward a's 1, -1 toward a's 0
    assert np.any(a != b) and opt.generation == 1 and opt.evaluations == 2


def test_cga_lower_loss_wins():
    opt = CGA(40, 12, n=10, bits=1)
    a = opt.ask()
    opt.tell(a, 2.0)
    b = opt.ask()
    opt.tell(b, 1.0)  # b wins
    np.testing.assert_array_equal(opt.offsets, (b - a).astype(int))


def test_pecga_tie_goes_to_the_elite():
    opt = PECGA(40, 13, n=10, bits=1)
    e = opt.ask()
    opt.tell(e, 1.0)
    assert opt.generation == 0 and opt.evaluations == 1  # the elite costs an evaluation
    x = opt.ask()
    opt.tell(x, 1.0)  # tie -> elite stays
    np.testing.assert_array_equal(opt.elite, e)
    assert opt.elite_loss == 1.0
    np.testing.assert_array_equal(opt.offsets, (e - x).astype(int))
    y = opt.ask()
    opt.tell(y, 0.5)  # strictly better -> newcomer is the elite
    np.testing.assert_array_equal(opt.elite, y)
    assert opt.elite_loss == 0.5 and opt.generation == 2 and opt.evaluations == 3


# ---------------------------------------------------------------- neCGA replacement
def test_necga_sample_replacement_costs_one_extra_evaluation():
    eta = 3
    opt = NECGA(30, 21, n=10, bits=1, eta=eta, elite_replacement='sample')
    e = opt.ask()
    opt.tell(e, 0.0)
    for i in range(eta):  # eta consecutive elite wins (ties)
        assert opt.theta == i
        x = opt.ask()
        opt.tell(x, 0.0)
    assert opt.theta == 0 and opt.generation == eta and opt.evaluations == eta + 1
    assert opt.elite is None  # replaced: the next ask is the new elite
    k_before = opt.offsets
    r = opt.ask()
    opt.tell(r, 5.0)  # the replacement's loss is the stored one
    np.testing.assert_array_equal(opt.offsets, k_before)  # no competition, no PV move
    assert opt.generation == eta and opt.evaluations == eta + 2
    np.testing.assert_array_equal(opt.elite, r)
    assert opt.elite_loss == 5.0
    x = opt.ask()
    opt.tell(x, 4.0)  # beats 5.0 (it would not beat the old 0.0)
    np.testing.assert_array_equal(opt.elite, x)
    assert opt.theta == 0


def test_necga_newcomer_replacement_is_one_evaluation_per_generation():
    eta = 3
    opt = NECGA(30, 22, n=10, bits=1, eta=eta, elite_replacement='newcomer')
    e = opt.ask()
    opt.tell(e, 0.0)
    for i in range(eta - 1):
        x = opt.ask()
        opt.tell(x, 1.0)  # elite wins
        assert opt.theta == i + 1
        np.testing.assert_array_equal(opt.elite, e)
    x = opt.ask()
    opt.tell(x, 7.0)  # eta-th consecutive win: the newcomer takes over
    assert opt.theta == 0 and opt.elite_loss == 7.0
    np.testing.assert_array_equal(opt.elite, x)
    assert opt.evaluations == eta + 1 and opt.generation == eta
    y = opt.ask()
    opt.tell(y, 6.0)
    np.testing.assert_array_equal(opt.elite, y)
    # Over many generations: exactly one evaluation each (plus the first elite).
    for _ in range(100):
        u = opt.ask()
        opt.tell(u, 0.0)
    assert opt.evaluations == opt.generation + 1


def test_necga_counter_resets_when_the_newcomer_wins():
    opt = NECGA(30, 23, n=10, bits=1, eta=3)
    opt.tell(opt.ask(), 10.0)
    opt.tell(opt.ask(), 11.0)
    opt.tell(opt.ask(), 11.0)
    assert opt.theta == 2
    x = opt.ask()
    opt.tell(x, 9.0)
    assert opt.theta == 0
    np.testing.assert_array_equal(opt.elite, x)


def test_necga_paper_defaults():
    opt = make_optimizer('necga', 5, 0)
    assert (opt.n, opt.eta, opt.bits, opt.elite_replacement) == (25, 12, 16, 'sample')
    assert opt.m == 80


# --------------------------------------------------------------- Monte Carlo oracles
def _z(sample: np.ndarray, exact: float) -> float:
    return (sample.mean() - exact) / (sample.std(ddof=1) / math.sqrt(sample.size))


def test_cga_neutral_drift():
    n, runs = 10, 200
    ts = (10, 50, 100)
    got = {t: [] for t in ts}
    for r in range(runs):
        opt = CGA(100, 1000 + r, n=n, bits=1)
        for t in range(1, ts[-1] + 1):
            opt.tell(opt.ask(), 0.0)
            opt.tell(opt.ask(), 0.0)
            if t in got:
                p = opt.p
                got[t].append(float(np.mean(p * (1 - p))))
    for t, exact in zip(ts, (0.20427, 0.09104, 0.03315), strict=True):
        assert round(0.25 * (1 - 2 / n**2) ** t, 5) == exact
        z = _z(np.array(got[t]), 0.25 * (1 - 2 / n**2) ** t)
        assert abs(z) < 4, (t, z)


def _pecga_flat(newcomer_wins: bool, n: int, ts: tuple[int, ...], runs: int):
    got = {t: [] for t in ts}
    for r in range(runs):
        opt = PECGA(100, 2000 + r, n=n, bits=1)
        opt.tell(opt.ask(), 0.0)
        for t in range(1, ts[-1] + 1):
            # Flat fitness; the variant makes every newcomer strictly better instead.
            opt.tell(opt.ask(), -float(t) if newcomer_wins else 0.0)
            if t in got:
                got[t].append(float(np.mean(np.abs(opt.p - 0.5))))
    return {t: np.array(v) for t, v in got.items()}


def test_pecga_flat_fitness_elite_wins_ties():
    n = 20
    ts = (5, 20, 60)
    got = _pecga_flat(False, n, ts, runs=100)
    for t, exact in zip(ts, (0.1131, 0.3208, 0.4770), strict=True):
        assert round(0.5 * (1 - (1 - 1 / n) ** t), 4) == exact
        z = _z(got[t], 0.5 * (1 - (1 - 1 / n) ** t))
        assert abs(z) < 4, (t, z)
    # Were ties won by the newcomer, E|p - 1/2| would stay at ~0.026: far from the oracle.
    other = _pecga_flat(True, n, ts, runs=100)
    for t in ts:
        assert abs(other[t].mean() - 0.026) < 0.002
        assert abs(_z(other[t], 0.5 * (1 - (1 - 1 / n) ** t))) > 40


def test_cga_onemax_gamblers_ruin():
    runs = 24
    bound = {10: 0.756, 20: 0.906, 40: 0.989}
    frac, per_n = {}, {}
    for n in bound:
        f, e = [], []
        for r in range(runs):
            opt = CGA(100, 3000 + r, n=n, bits=1)
            while not opt.converged():
                u = opt.ask()
                opt.tell(u, -float(u.sum()))  # minimise -(number of ones)
            f.append(float(opt.solution().mean()))
            e.append(opt.evaluations / n)
        frac[n], per_n[n] = np.array(f), np.array(e)
        assert frac[n].mean() >= bound[n], (n, frac[n].mean())
    assert frac[10].mean() < frac[20].mean() < frac[40].mean()
    for n in (20, 40):
        assert abs(per_n[n].mean() - 32) < 3, (n, per_n[n].mean())


def _trap_loss(u: np.ndarray) -> float:
    ones = u.reshape(10, 4).sum(axis=1)
    return -float(np.where(ones == 4, 4.0, 3.0 - ones).sum())  # deceptive trap-4


def _trap_blocks(algo: str, n: int, seed: int, budget: int = 20_000) -> int:
    opts = {'eta': n // 2} if algo == 'necga' else {}
    opt = make_optimizer(algo, 40, seed, n=n, bits=1, **opts)
    while opt.evaluations < budget and not opt.converged():
        u = opt.ask()
        opt.tell(u, _trap_loss(u))
    return int(np.sum(opt.solution().reshape(10, 4).sum(axis=1) == 4))


def test_elitism_on_deceptive_trap():
    runs = 16
    mean = {
        (a, n): np.mean([_trap_blocks(a, n, 4000 + r) for r in range(runs)])
        for a in ('cga', 'pecga', 'necga')
        for n in (20, 100)
    }
    # Elitism solves clearly more blocks at n = 100 ...
    assert mean['pecga', 100] > mean['cga', 100] + 2.0
    assert mean['necga', 100] > mean['cga', 100] + 2.0
    assert mean['pecga', 100] >= 2.5 and mean['necga', 100] >= 2.5
    # ... and the cGA gets worse as n grows (it learns the deceptive slope more surely).
    assert mean['cga', 20] > mean['cga', 100] + 0.5
    assert mean['cga', 100] <= 1.4


# ------------------------------------------------- the packed PV against a plain model
class _PlainCGA:
    """The binary compact GAs written plainly (numpy arrays of offsets and bits, one
    rng.random(m) per sample): the model the packed implementation must reproduce."""

    def __init__(self, algo, dim, seed, n, bits, coding, eta=12, rep='sample'):
        self.algo, self.n, self.bits, self.gray = algo, n, bits, coding == 'gray'
        self.dim, self.m, self.K = dim, dim * bits, (n + 1) // 2
        self.eta, self.rep = eta, rep
        self.rng = np.random.Generator(np.random.PCG64(seed))
        self.k = np.zeros(self.m, dtype=np.int64)
        self.held, self.held_loss, self.theta, self.pending = None, 0.0, 0, None

    def p(self):
        return np.clip((self.n + 2 * self.k) / (2.0 * self.n), 0.0, 1.0)

    def decode(self, b):
        g = b.reshape(self.dim, self.bits)
        if self.gray:
            g = np.logical_xor.accumulate(g, axis=1)
        return g.dot(2.0 ** np.arange(self.bits - 1, -1, -1)) / (2**self.bits - 1)

    def ask(self):
        if self.pending is None:
            self.pending = self.rng.random(self.m) < self.p()
        return self.decode(self.pending)

    def tell(self, y):
        b, self.pending = self.pending, None
        if self.held is None:
            self.held, self.held_loss = b, y
            return
        if self.algo == 'cga':
            w, l = (self.held, b) if self.held_loss <= y else (b, self.held)
        else:
            new = y < self.held_loss
            w, l = (b, self.held) if new else (self.held, b)
        self.k = np.clip(self.k + w.astype(int) - l.astype(int), -self.K, self.K)
        if self.algo == 'cga':
            self.held = None
        elif new:
            self.held, self.held_loss, self.theta = b, y, 0
        elif self.algo == 'necga':
            self.theta += 1
            if self.theta >= self.eta:
                self.theta = 0
                if self.rep == 'newcomer':
                    self.held, self.held_loss = b, y
                else:
                    self.held = None


@pytest.mark.parametrize(
    'algo, n, bits, coding, extra',
    [
        ('cga', 4, 3, 'binary', {}),
        ('pecga', 5, 2, 'gray', {}),  # 1-byte fields
        ('necga', 3, 1, 'binary', {'eta': 2}),
        ('necga', 6, 5, 'gray', {'eta': 2, 'elite_replacement': 'newcomer'}),
        ('pecga', 300, 1, 'binary', {}),  # 2-byte fields
        ('necga', 70_001, 2, 'binary', {'eta': 3}),  # 4-byte fields
        ('cga', 25, 16, 'binary', {}),
    ],
)
def test_packed_pv_equals_the_plain_model(algo, n, bits, coding, extra):
    """Sampling (r < p), the clamped +-1 competitions with every tie rule, the elite
    replacements and the decoding, evaluation by evaluation, until the PV converges (small
    n) or for 600 evaluations; losses with many ties."""
    for seed in range(4):
        opt = make_optimizer(algo, 3, seed, n=n, bits=bits, coding=coding, **extra)
        ref = _PlainCGA(
            algo,
            3,
            seed,
            n,
            bits,
            coding,
            extra.get('eta', 12),
            extra.get('elite_replacement', 'sample'),
        )
        loss_rng = np.random.Generator(np.random.PCG64(seed + 77))
        for _ in range(600):
            u = opt.ask()
            assert u.tobytes() == ref.ask().tobytes()
            y = float(loss_rng.integers(0, 3))  # 0, 1, 2: ties are frequent
            opt.tell(u, y)
            ref.tell(y)
            np.testing.assert_array_equal(opt.offsets, ref.k)
        np.testing.assert_array_equal(opt.p, ref.p())
        assert opt.converged() == bool(np.all(np.abs(ref.k) == ref.K))


def test_state_with_an_impossible_sample_is_refused():
    opt = CGA(2, 0, n=10, bits=3)
    opt.ask()
    st = opt.state_dict()
    st['k'] = [5] * 6  # p = 1 everywhere: the sample must be 111111
    st['pending'] = '011111'
    with pytest.raises(OptimizerError, match='cannot produce'):
        Optimizer.from_state(st)
    st['pending'] = '111111'
    np.testing.assert_array_equal(Optimizer.from_state(st).ask(), [1.0, 1.0])
    st['phase'] = 'second'  # nothing is held: the phase is 'first'
    with pytest.raises(OptimizerError, match='phase'):
        Optimizer.from_state(st)
