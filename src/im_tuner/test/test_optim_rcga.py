"""Real-valued compact GA (im_tuner.optim.rcga): the normal quantile (AS 241), the
truncated-normal sampler (Kolmogorov-Smirnov against the exact CDF built from math.erf,
statistic and p-value computed here), the update as a population swap, tie rule and
elitism.
"""

from __future__ import annotations

import math
import statistics

import numpy as np
import pytest

from im_tuner.optim import RCGA, make_optimizer
from im_tuner.optim.rcga import erfinv, ndtri, truncnorm_ppf


def norm_cdf(x: float) -> float:
    """Phi(x) = erfc(-x/sqrt 2)/2 (accurate to a few ulp, relative, in the lower tail)."""
    return 0.5 * math.erfc(-x / math.sqrt(2.0))


# ------------------------------------------------------------------ ndtri and erfinv
@pytest.mark.parametrize(
    'p, x',
    [
        # Reference values from 40-digit arithmetic (mpmath).
        (0.975, 1.9599639845400542355),
        (0.9, 1.281551565544600467),
        (0.3, -0.52440051270804078404),
        (1e-10, -6.3613409024040562047),
        (1e-20, -9.2623400897984075737),
        (1e-50, -14.933337534788488981),
        (1e-300, -37.047096299361199237),
        (0.5, 0.0),
    ],
)
def test_ndtri_reference_values(p, x):
    assert ndtri(p) == pytest.approx(x, rel=1e-13, abs=1e-15)
    if 1e-9 < p < 0.5:  # (1 - p rounds to 1 for tinier p)
        assert ndtri(1 - p) == pytest.approx(-x, rel=1e-12)


def test_ndtri_round_trip_and_edges():
    # Lower tail through erfc (relative accuracy): ndtri(Phi(x)) = x to ~1e-13.
    for x in np.linspace(-37.5, 0.0, 751):  # Phi(-37.5) ~ 5e-308: normal floats
        p = norm_cdf(float(x))
        assert ndtri(p) == pytest.approx(x, rel=2e-13, abs=1e-14)
    for p in np.linspace(1e-6, 1 - 1e-6, 1001):
        x = ndtri(float(p))
        assert 0.5 * math.erfc(-x / math.sqrt(2)) == pytest.approx(p, rel=1e-13)
        assert ndtri(1.0 - float(p)) == pytest.approx(-x, rel=1e-9, abs=1e-12)
    assert ndtri(0.0) == -math.inf and ndtri(1.0) == math.inf
    assert math.isnan(ndtri(1.5))  # scipy's domain: nan outside [0, 1]


def test_scipy_ndtri_agrees_with_as241():
    # The hand-written AS 241 became scipy.special.ndtri.  The standard library's
    # statistics.NormalDist.inv_cdf is Wichura's AS 241 (what rcga used before): the two
    # agree within their stated precision (~1e-16 relative; 1e-14 allowed) over the range.
    inv = statistics.NormalDist().inv_cdf
    r = np.random.Generator(np.random.PCG64(3))
    ps = np.concatenate(
        [
            r.random(20_000),
            10.0 ** -r.uniform(0.0, 300.0, 20_000),
            [0.075, 0.925, math.exp(-25.0), 0.5, 1e-300],
        ]
    )
    worst = 0.0
    for p in ps.tolist():
        if 0.0 < p < 1.0:
            a, b = float(ndtri(p)), inv(p)
            worst = max(worst, abs(a - b) / max(abs(b), 1e-300))
    assert worst < 1e-14, worst


def test_truncnorm_ppf_unchanged_within_precision():
    # The sampler's numbers before (AS 241) and after (scipy): the same within 1e-13 in x.
    inv = statistics.NormalDist().inv_cdf

    def ref(q: float, mu: float, sigma: float) -> float:
        if mu < 0.0:  # the sampler mirrors mu < 0 (the same law for a uniform q)
            return -ref(q, -mu, sigma)
        a, b = norm_cdf((-1.0 - mu) / sigma), norm_cdf((1.0 - mu) / sigma)
        p = min(max(a + q * (b - a), 1e-300), 1.0 - 1e-16)
        return min(max(mu + sigma * inv(p), -1.0), 1.0)

    r = np.random.Generator(np.random.PCG64(11))
    for mu, sigma, q in zip(
        r.uniform(-1.5, 1.5, 2000), 10.0 ** r.uniform(-3, 1, 2000), r.random(2000), strict=True
    ):
        mu, sigma, q = float(mu), float(sigma), float(q)
        if norm_cdf((1.0 - abs(mu)) / sigma) - norm_cdf((-1.0 - abs(mu)) / sigma) < 1e-6:
            continue  # a vanishing mass: the sampler works in the upper tail instead
        x_ref = ref(q, mu, sigma)
        assert truncnorm_ppf(q, mu, sigma) == pytest.approx(x_ref, abs=1e-9)


@pytest.mark.parametrize(
    'y, x',
    [
        (0.5, 0.47693627620446987338),
        (0.999, 2.3267537655135246706),
        (-0.3, -0.27246271472675435562),
        (0.999999999999, 5.0420297456390593742),
    ],
)
def test_erfinv_reference_values(y, x):
    # 0.999999999999 is not exact in binary: its own rounding limits the agreement.
    assert erfinv(y) == pytest.approx(x, rel=1e-12 if abs(y) < 0.9999 else 1e-6)


def test_erfinv_round_trip():
    for x in np.linspace(-2.0, 2.0, 401):
        assert erfinv(math.erf(float(x))) == pytest.approx(x, rel=1e-12, abs=1e-15)
    for y in np.linspace(-0.999, 0.999, 999):
        assert math.erf(erfinv(float(y))) == pytest.approx(y, rel=1e-14, abs=1e-16)
    assert erfinv(1.0) == math.inf and erfinv(-1.0) == -math.inf and erfinv(0.0) == 0.0


# --------------------------------------------------------------- the sampler, KS test
def _truncnorm_cdf(x: float, mu: float, sigma: float) -> float:
    """Exact CDF of N(mu, sigma^2) truncated to [-1, 1], from math.erf."""
    phi = lambda z: 0.5 * (1.0 + math.erf(z / math.sqrt(2.0)))  # noqa: E731
    fa, fb = phi((-1.0 - mu) / sigma), phi((1.0 - mu) / sigma)
    return (phi((x - mu) / sigma) - fa) / (fb - fa)


def _ks(sample: np.ndarray, cdf) -> tuple[float, float]:
    """One-sample KS statistic D and its asymptotic p-value (Stephens' correction)."""
    x = np.sort(sample)
    n = x.size
    f = np.array([cdf(float(v)) for v in x])
    i = np.arange(1, n + 1)
    d = float(max(np.max(i / n - f), np.max(f - (i - 1) / n)))
    lam = (math.sqrt(n) + 0.12 + 0.11 / math.sqrt(n)) * d
    p = 2.0 * sum((-1) ** (k - 1) * math.exp(-2.0 * k * k * lam * lam) for k in range(1, 101))
    return d, min(max(p, 0.0), 1.0)


def test_ks_helper_by_hand():
    # Three points against U(0, 1): D = max(1/3 - 0.1, 0.5 - 1/3, 1 - 0.9, ...) = 0.2333.
    d, _p = _ks(np.array([0.1, 0.5, 0.9]), lambda v: v)
    assert d == pytest.approx(
        max(1 / 3 - 0.1, 0.1 - 0, 2 / 3 - 0.5, 0.5 - 1 / 3, 1 - 0.9, 0.9 - 2 / 3)
    )
    # Kolmogorov's distribution: P(K > 1.3581) = 0.05.
    lam = 1.3581
    p05 = 2 * sum((-1) ** (k - 1) * math.exp(-2 * k * k * lam * lam) for k in range(1, 101))
    assert p05 == pytest.approx(0.05, abs=1e-4)


@pytest.mark.parametrize(
    'mu, sigma',
    [
        (0.0, 10.0),
        (0.3, 0.4),
        (-0.8, 0.15),
        (0.95, 0.02),
        (0.99, 0.5),
        (1.3, 0.2),
        (-1.2, 0.05),
        (0.0, 1e-3),
    ],
)
def test_truncnorm_sampler_ks(mu, sigma):
    n = 4000
    r = np.random.Generator(np.random.PCG64(7)).random(n)
    x = np.array([truncnorm_ppf(float(v), mu, sigma) for v in r])
    assert np.all((x >= -1.0) & (x <= 1.0))
    d, p = _ks(x, lambda v: _truncnorm_cdf(v, mu, sigma))
    assert p > 1e-3, (d, p)
    # The test has power: a slightly wrong law (spread 20 % too large) is rejected.
    if sigma < 5:
        _, p_bad = _ks(x, lambda v: _truncnorm_cdf(v, mu, 1.2 * sigma))
        assert p_bad < 1e-3


def test_truncnorm_degenerate_spread():
    assert truncnorm_ppf(0.3, 0.25, 0.0) == 0.25
    assert truncnorm_ppf(0.3, 3.0, 1e-3) == 1.0  # all mass underflows: nearest bound
    assert truncnorm_ppf(0.3, -3.0, 1e-3) == -1.0


def test_class_samples_with_the_sampler():
    opt = RCGA(5, 42)
    r = np.random.Generator(np.random.PCG64(42)).random(5)
    x = np.array([truncnorm_ppf(float(v), 0.0, 10.0) for v in r])
    np.testing.assert_array_equal(opt.ask(), (x + 1.0) * 0.5)


# --------------------------------------------------------------- update = population swap
@pytest.mark.parametrize('newcomer_wins', [False, True])
def test_update_equals_population_swap(newcomer_wins):
    n = 30
    opt = RCGA(4, 5, n=n, sigma0=0.45, elitism='pe')
    e = opt.ask()
    opt.tell(e, 1.0)
    mu, sigma = opt.mu, opt.sigma
    x = opt.ask()
    opt.tell(x, 0.0 if newcomer_wins else 2.0)
    xe, xn = 2 * e - 1, 2 * x - 1  # back to [-1, 1]
    w, l = (xn, xe) if newcomer_wins else (xe, xn)
    rng = np.random.Generator(np.random.PCG64(1))
    for i in range(4):
        # A population of n points with mean mu_i, population variance sigma_i^2, holding l_i.
        m_q = (n * mu[i] - l[i]) / (n - 1)
        s2_q = (n * (sigma[i] ** 2 + mu[i] ** 2) - l[i] ** 2) / (n - 1) - m_q**2
        z = rng.normal(size=n - 1)
        z = (z - z.mean()) / z.std()
        pop = np.concatenate([[l[i]], m_q + math.sqrt(s2_q) * z])
        assert pop.mean() == pytest.approx(mu[i], abs=1e-13)
        assert pop.var() == pytest.approx(sigma[i] ** 2, abs=1e-13)
        pop[0] = w[i]  # the winner replaces the loser
        assert opt.mu[i] == pytest.approx(pop.mean(), abs=1e-12)
        assert opt.sigma[i] ** 2 == pytest.approx(pop.var(), abs=1e-12)


def test_rcga_tie_goes_to_the_elite_and_ne_replacement():
    opt = RCGA(3, 9, n=10, eta=2, elitism='ne')
    e = opt.ask()
    opt.tell(e, 1.0)
    x = opt.ask()
    opt.tell(x, 1.0)  # tie -> elite
    np.testing.assert_array_equal(opt.elite, e)
    assert opt.theta == 1
    y = opt.ask()
    opt.tell(y, 3.0)  # second consecutive win = eta: replaced
    np.testing.assert_array_equal(opt.elite, y)  # by the newcomer just evaluated
    assert opt.elite_loss == 3.0 and opt.theta == 0
    assert opt.evaluations == 3 and opt.generation == 2


def test_rcga_pe_keeps_its_elite():
    opt = RCGA(3, 9, n=10, eta=2, elitism='pe')
    e = opt.ask()
    opt.tell(e, 0.0)
    for _ in range(50):
        opt.tell(opt.ask(), 1.0)
    np.testing.assert_array_equal(opt.elite, e)
    assert opt.evaluations == 51 and opt.generation == 50


def test_rcga_descends_a_quadratic():
    target = np.array([0.2, 0.7, 0.4])
    opt = make_optimizer('rcga', 3, 3, sigma0=0.6, n=50)
    best = math.inf
    for _ in range(3000):
        u = opt.ask()
        loss = float(np.sum((u - target) ** 2))
        best = min(best, loss)
        opt.tell(u, loss)
    assert np.max(np.abs((opt.mu + 1) / 2 - target)) < 0.02
    assert best < 1e-4 and float(opt.sigma.max()) < 0.05
