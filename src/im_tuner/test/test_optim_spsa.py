"""SPSA (im_tuner.optim.spsa): exact oracles from docs/optimisers.md and the shared notes.

* the second-moment recursion of SPSA on L = u'u + N(0, s^2) (unbounded), checked both
  by iterating it here and by Monte Carlo on the real class (2000 seeded runs: enough
  that the off-by-one a_k = a/(k + A)^alpha, m_50 = 2.894, would fail);
* the first step by hand (g = (4, 4) for Delta = (1, 1), g = 0 for Delta = (1, -1));
* the gain index convention, Delta's distribution, the step cap and feasibility.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from im_tuner.optim import SPSA, make_optimizer
from im_tuner.optim.spsa import GAIN_PRESETS

# The moment oracle of the notes: p = 10, u_0 = 1, a = 0.05, c = 0.1, A = 10, s = 0.1,
# Spall's exponents (alpha = 0.602, gamma = 0.101).
P, A_GAIN, C_GAIN, A_STAB, NOISE = 10, 0.05, 0.1, 10.0, 0.1
ALPHA, GAMMA = GAIN_PRESETS['spall']
EXPECTED = {10: 6.993, 50: 2.976, 100: 1.518}
OFF_BY_ONE_100 = 1.469


def moments(kmax: int, index_offset: int = 1) -> list[float]:
    """m_k = E||u_k||^2 for k = 0..kmax from the exact recursion (offset 0 = the off-by-one).

    u_{k+1} = u_k - a_k g_k with g_k = 2 Delta Delta'u_k + (e+ - e-) Delta/(2 c_k):
    E||u_{k+1}||^2 = (1 - 4 a_k + 4 p a_k^2) m_k + p a_k^2 s^2/(2 c_k^2).
    """
    m = [float(P)]  # u_0 = (1, ..., 1)
    for k in range(kmax):
        ak = A_GAIN / (k + index_offset + A_STAB) ** ALPHA
        ck = C_GAIN / (k + 1) ** GAMMA
        m.append((1 - 4 * ak + 4 * P * ak * ak) * m[-1] + P * ak * ak * NOISE**2 / (2 * ck * ck))
    return m


def test_moment_recursion_gives_the_notes_numbers():
    m = moments(100)
    for k, v in EXPECTED.items():
        assert round(m[k], 3) == v
    assert round(moments(100, index_offset=0)[100], 3) == OFF_BY_ONE_100


def test_moment_oracle_monte_carlo():
    runs, iters = 2000, 100
    checkpoints = sorted(EXPECTED)
    sq = np.empty((len(checkpoints), runs))
    # Measurement noise from its own stream (never the optimiser's).
    noise = np.random.Generator(np.random.PCG64(20240611)).normal(0.0, NOISE, (runs, 2 * iters))
    for r in range(runs):
        opt = SPSA(
            P,
            seed=r,
            start=np.ones(P),
            a=A_GAIN,
            c=C_GAIN,
            A=A_STAB,
            gains='spall',
            max_step=math.inf,
            bounded=False,
        )
        e = noise[r]
        j = 0
        for k in range(1, iters + 1):
            u = opt.ask()
            opt.tell(u, float(u @ u) + e[2 * k - 2])
            u = opt.ask()
            opt.tell(u, float(u @ u) + e[2 * k - 1])
            if k in EXPECTED:
                it = opt.iterate
                sq[j, r] = it @ it
                j += 1
        assert opt.evaluations == 2 * iters and opt.iterations == iters
    exact = moments(100)
    for j, k in enumerate(checkpoints):
        mean = sq[j].mean()
        se = sq[j].std(ddof=1) / math.sqrt(runs)
        z = (mean - exact[k]) / se
        assert abs(z) < 4, f'm_{k}: MC {mean:.4f} +- {se:.4f} vs exact {exact[k]:.4f} (z = {z:.2f})'
    # The same sample rejects the off-by-one index in a_k (at k = 50 the difference is
    # the most standard errors: 2.976 against 2.894)
    j = checkpoints.index(50)
    se50 = sq[j].std(ddof=1) / math.sqrt(runs)
    z_off = abs(sq[j].mean() - moments(50, index_offset=0)[50]) / se50
    assert z_off > 4, z_off


def _seed_with_delta(want: tuple[float, float], c: float) -> int:
    """A seed whose first Delta is ``want`` (read back from the first asked point)."""
    for seed in range(200):
        opt = SPSA(2, seed, start=np.ones(2), c=c, bounded=False)
        delta = np.sign(opt.ask() - 1.0)
        if tuple(delta) == want:
            return seed
    raise AssertionError('no seed found')


@pytest.mark.parametrize('delta, g_expected', [((1.0, 1.0), (4.0, 4.0)), ((1.0, -1.0), (0.0, 0.0))])
def test_first_step_by_hand(delta, g_expected):
    c = 1e-3
    seed = _seed_with_delta(delta, c)
    opt = SPSA(
        2,
        seed,
        start=np.ones(2),
        a=0.05,
        c=c,
        A=10,
        gains='spall',
        max_step=math.inf,
        bounded=False,
    )
    up = opt.ask()
    np.testing.assert_array_equal(up, 1.0 + c * np.array(delta))  # c_0 = c
    opt.tell(up, float(up @ up))
    um = opt.ask()
    np.testing.assert_array_equal(um, 1.0 - c * np.array(delta))
    assert opt.last_gradient is None
    opt.tell(um, float(um @ um))
    g = opt.last_gradient
    # y+ - y- = 4 c Delta'u_0: g = 2 Delta (Delta'u_0) = (4, 4) or 0.
    np.testing.assert_allclose(g, g_expected, rtol=0, atol=1e-9)
    a0 = 0.05 / (0 + 1 + 10) ** ALPHA  # k = 0: a/(k + 1 + A)^alpha
    np.testing.assert_allclose(opt.iterate, 1.0 - a0 * g, rtol=0, atol=1e-15)


def test_gain_index_convention_and_presets():
    opt = SPSA(3, 0)  # paper defaults
    assert (opt.a, opt.c, opt.A, opt.alpha, opt.gamma, opt.max_step) == (
        0.0183,
        0.03,
        20.0,
        0.3,
        0.3,
        0.1,
    )
    a0, c0 = opt.gains(0)
    assert a0 == 0.0183 / 21**0.3 and c0 == 0.03
    a99, c99 = opt.gains(99)
    assert a99 == 0.0183 / 120**0.3 and c99 == 0.03 / 100**0.3
    # The paper's alpha = gamma = 0.3 keeps a_k/c_k nearly constant (0.24 -> 0.58).
    assert round(a0 / c0, 2) == 0.24 and round(a99 / c99, 2) == 0.58
    s = SPSA(3, 0, gains='spall')
    assert (s.alpha, s.gamma) == (0.602, 0.101)
    o = SPSA(3, 0, gains='spall', alpha=0.7)  # explicit overrides the preset
    assert (o.alpha, o.gamma) == (0.7, 0.101)
    o = SPSA(3, 0, gamma=0.2)
    assert (o.alpha, o.gamma) == (0.3, 0.2)


def test_delta_is_fair_plus_minus_one():
    opt = SPSA(8, 3)
    plus, total = 0, 0
    for _ in range(2000):
        u = opt.ask()
        it = opt.iterate
        d = (u - it) / opt.gains(opt.iterations)[1]
        np.testing.assert_allclose(np.abs(d), 1.0, rtol=1e-9)
        plus += int(np.sum(d > 0))
        total += d.size
        opt.tell(u, 0.0)
        opt.tell(opt.ask(), 0.0)  # flat loss: g = 0, the iterate stays
    z = (plus - total / 2) / math.sqrt(total / 4)
    assert abs(z) < 4


def test_start_projection_and_random_start():
    opt = SPSA(3, 0, start=np.array([0.0, 0.5, 1.0]))
    np.testing.assert_array_equal(opt.iterate, [0.03, 0.5, 0.97])  # [c_0, 1 - c_0]
    free = SPSA(3, 0, start=np.array([0.0, 0.5, 1.0]), bounded=False)
    np.testing.assert_array_equal(free.iterate, [0.0, 0.5, 1.0])
    starts = np.array([SPSA(2, s).iterate for s in range(500)])
    assert np.all((starts >= 0.03) & (starts <= 0.97))
    assert abs(starts.mean() - 0.5) < 4 * (0.94 / math.sqrt(12)) / math.sqrt(starts.size)
    np.testing.assert_array_equal(SPSA(2, 7).iterate, SPSA(2, 7).iterate)
    assert not np.array_equal(SPSA(2, 7).iterate, SPSA(2, 8).iterate)


def test_step_cap_against_a_penalised_loss():
    opt = make_optimizer('spsa', 5, 1, start=np.full(5, 0.5))
    before = opt.iterate
    u = opt.ask()
    opt.tell(u, 1e6)  # an aborted experiment: loss x penalty
    u = opt.ask()
    opt.tell(u, 1.0)
    moved = np.abs(opt.iterate - before)
    # |a_0 g_0| would be ~1e6 per coordinate: the whole step is scaled to max_step.
    assert moved.max() == pytest.approx(0.1, abs=1e-15)
    np.testing.assert_allclose(moved, 0.1, atol=1e-15)  # |g_i| all equal: every entry
    uncapped = SPSA(5, 1, start=np.full(5, 0.5), max_step=math.inf)
    u = uncapped.ask()
    uncapped.tell(u, 1e6)
    uncapped.tell(uncapped.ask(), 1.0)
    assert np.all(np.isin(uncapped.iterate, [uncapped.gains(1)[1], 1 - uncapped.gains(1)[1]]))


def test_every_asked_point_is_feasible():
    rng = np.random.Generator(np.random.PCG64(5))
    for seed in range(20):
        opt = SPSA(5, seed, max_step=0.5, a=1.0)  # big steps: the projection must work
        for _ in range(200):
            u = opt.ask()
            assert np.all((u >= 0.0) & (u <= 1.0))
            loss = 1e6 if rng.random() < 0.1 else float(rng.normal(0, 1) + np.sum(u))
            opt.tell(u, loss)
            ck = opt.gains(opt.iterations)[1]
            it = opt.iterate
            assert np.all((it >= ck) & (it <= 1 - ck))


def test_spsa_descends_a_quadratic():
    opt = make_optimizer('spsa', 5, 2, gains='spall', a=0.2, c=0.05)
    target = np.array([0.2, 0.4, 0.6, 0.8, 0.5])
    for _ in range(400):
        u = opt.ask()
        opt.tell(u, float(np.sum((u - target) ** 2)))
    assert np.max(np.abs(opt.iterate - target)) < 0.05
