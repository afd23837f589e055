"""Tables I-III and the conclusions of the study, against hand computations on
constructed results (no experiments)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from im_tuner.study import runs as S, stats as ST
from im_tuner.study.stats import PAPER, compute, per_run, wilson

L_REF = 2.0


def make_result(
    runs: int, budget: int, finals: dict[tuple[str, int, int], float] | None = None, seed: int = 0
) -> S.StudyResult:
    """A StudyResult whose run losses decay from 1.2 to the cell's final level (normalised),
    with a little noise; nothing aborted."""
    spec = S.StudySpec(runs=runs, budget=budget)
    cells = spec.cells
    rng = np.random.default_rng(seed)
    len(cells)
    arrays = S._allocate(spec, cells)
    for c, cell in enumerate(cells):
        level = (finals or {}).get((cell.algo, cell.row, cell.col), 0.8)
        for r in range(runs):
            target = level + 0.02 * rng.standard_normal()
            curve = target + (1.2 - target) * np.exp(-np.arange(budget) / (budget / 5))
            arrays['losses'][c, r] = L_REF * curve
            arrays['iteration'][c, r] = (
                np.arange(budget) // 2 + 1 if cell.algo == 'spsa' else np.arange(budget) + 1
            )
            arrays['ref_loss'][c, r] = L_REF
    arrays['remeasured'][:] = L_REF * 0.9
    return S.StudyResult(
        spec=spec,
        cells=cells,
        l_ref=L_REF,
        l_ref_sem=0.001,
        l_first=1.8,
        wall_s=1.0,
        jobs=1,
        **arrays,
    )


def test_wilson_interval_known_values():
    # 90/100: the notes' "a 95 % interval around 90 % is about [83, 95]"
    lo, hi = wilson(90, 100)
    assert lo == pytest.approx(0.82564, abs=2e-5) and hi == pytest.approx(0.94477, abs=2e-5)
    assert wilson(0, 10)[0] == 0.0 and wilson(10, 10)[1] == pytest.approx(1.0, abs=1e-15)
    assert all(math.isnan(x) for x in wilson(0, 0))


def _wilson_by_hand(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """The hand-written Wilson score interval the study used before scipy (the oracle)."""
    p = k / n
    d = 1.0 + z * z / n
    mid = (p + z * z / (2 * n)) / d
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (max(0.0, mid - half), min(1.0, mid + half))


def test_scipy_wilson_equals_the_hand_written_one():
    for n in (1, 3, 10, 100, 1000):
        for k in range(0, n + 1, max(1, n // 10)):
            assert wilson(k, n) == pytest.approx(_wilson_by_hand(k, n), abs=1e-12), (k, n)


def _boot_by_hand(x: np.ndarray, runs: int) -> tuple[float, float]:
    """The hand-written percentile bootstrap of a nan-aware mean used before scipy."""
    idx = np.random.default_rng(ST.BOOT_SEED).integers(0, runs, size=(ST.BOOT, runs))
    v = x[idx]
    cnt = np.sum(~np.isnan(v), axis=1)
    with np.errstate(invalid='ignore', divide='ignore'):
        d = np.where(cnt > 0, np.nansum(v, axis=1) / np.maximum(cnt, 1), np.nan)
    lo, hi = np.quantile(d[np.isfinite(d)], [0.025, 0.975])
    return float(lo), float(hi)


def test_scipy_bootstrap_matches_the_hand_written_one_within_monte_carlo_error():
    # Different resampling streams: the interval ends agree within Monte Carlo precision
    # (4000 resamples: a few % of the interval's width), with and without undefined runs.
    rng = np.random.default_rng(5)
    boot = ST._Boot(100)
    for trial in range(6):
        x = rng.normal(0.5, 0.05 * (trial + 1), 100)
        if trial % 2:
            x[rng.random(100) < 0.4] = np.nan  # runs that never reached the level
        iv = boot.interval(ST._nanmean(x), boot.mean(x), 100)
        lo, hi = _boot_by_hand(x, 100)
        width = hi - lo
        assert abs(iv.lo - lo) < 0.08 * width and abs(iv.hi - hi) < 0.08 * width, (iv, lo, hi)
        assert iv.lo < iv.value < iv.hi


def test_bootstrap_resamples_the_same_runs_for_every_cell():
    # common random numbers: the same seed gives the same run indices in every call, so
    # a cell against itself differs by exactly 0 in every resample
    rng = np.random.default_rng(6)
    a, b = rng.normal(size=50), rng.normal(size=50)
    boot = ST._Boot(50)
    assert np.all(boot.mean(a) - boot.mean(a) == 0.0)
    joint = boot.dist(lambda x, y, axis=-1: np.mean(x, axis=axis) - np.mean(y, axis=axis), a, b)
    np.testing.assert_allclose(boot.mean(a) - boot.mean(b), joint, rtol=0, atol=1e-12)


def test_final_loss_satisfactory_and_evaluations_by_hand():
    res = make_result(runs=3, budget=4)
    c = 0
    # run 0: normalised 1.0, 0.8, 0.95, 0.6 -> final 0.6, satisfactory at evaluation 2
    res.losses[c, 0] = L_REF * np.array([1.0, 0.8, 0.95, 0.6])
    res.iteration[c, 0] = [1, 1, 2, 2]
    # run 1: everything aborted -> no final controller, not satisfactory
    res.losses[c, 1] = L_REF * np.array([0.1, 0.2, 0.3, 0.4])
    res.aborted[c, 1] = True
    # run 2: a tiny aborted (penalised) loss first must not count; final 0.91 > 0.9
    res.losses[c, 2] = L_REF * np.array([0.05, 0.95, 0.925, 0.91])
    res.aborted[c, 2, 0] = True
    pr = per_run(res, 0.9)
    np.testing.assert_array_equal(pr['final'][c], [0.6, np.nan, 0.91])
    np.testing.assert_array_equal(pr['satisfactory'][c], [True, False, False])
    np.testing.assert_array_equal(pr['evals'][c], [2.0, np.nan, np.nan])
    np.testing.assert_array_equal(pr['iterations'][c], [1.0, np.nan, np.nan])
    st = compute(res, 0.9)
    cs = st.cells[c]
    assert cs.final.value == pytest.approx((0.6 + 0.91) / 2, abs=1e-15)
    assert cs.final.n == 2 and cs.no_final == 1
    assert cs.satisfactory.value == pytest.approx(100 / 3)
    lo, hi = wilson(1, 3)
    assert (cs.satisfactory.lo, cs.satisfactory.hi) == pytest.approx((100 * lo, 100 * hi))
    assert cs.evals.value == 2.0 and cs.evals.n == 1
    assert cs.remeasured.value == pytest.approx(0.9)
    assert cs.aborted_pct == pytest.approx(100 * 5 / 12)
    # a looser threshold: run 2 becomes satisfactory at its 4th evaluation
    st2 = compute(res, 0.92)
    assert st2.cells[c].satisfactory.value == pytest.approx(200 / 3)
    assert st2.cells[c].evals.value == pytest.approx((2 + 4) / 2)


def test_intervals_are_reproducible_and_cover_the_mean():
    res = make_result(runs=100, budget=20)
    a, b = compute(res), compute(res)
    for ca, cb in zip(a.cells, b.cells, strict=True):
        assert (ca.final.lo, ca.final.hi) == (cb.final.lo, cb.final.hi)
        assert ca.final.lo < ca.final.value < ca.final.hi
        # 100 runs with sd about 0.02: the 95 % half-width is about 1.96 * 0.002
        assert 0.002 < ca.final.hi - ca.final.lo < 0.012


def test_paper_tables_are_the_papers():
    # spot checks against the paper's Tables I-III
    assert PAPER['final'][('necga', 0, 1)] == 0.70
    assert PAPER['satisfactory'][('spsa', 2, 0)] == 44
    assert PAPER['iterations'][('spsa', 2, 1)] == 23
    assert all(len(t) == 12 for t in PAPER.values())


@pytest.mark.parametrize('necga_better', [True, False])
def test_conclusions_follow_the_data(necga_better):
    spsa, necga = (0.8, 0.6) if necga_better else (0.6, 0.8)
    finals = {('spsa', i, j): spsa for i in range(3) for j in range(3)}
    finals.update({('necga', 0, j): necga for j in range(3)})
    st = compute(make_result(runs=60, budget=40, finals=finals))
    lower = st.conclusions[0]
    assert lower.claim.startswith('neCGA reaches a lower average final loss')
    assert lower.verdict == ('holds' if necga_better else 'reversed')
    # every cell of a grid has the same level: the configuration makes no difference
    assert st.conclusions[1].verdict == 'not significant'


def test_threshold_must_be_positive():
    res = make_result(runs=2, budget=2)
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match='threshold'):
            compute(res, bad)


def test_comparison_rows_by_hand():
    """The comparison table: each column against a hand computation on constructed
    runs, and each row named once by its algorithm, configuration and start."""
    from im_tuner.study.text import comparison_rows

    spec = S.StudySpec(runs=3, budget=4, algos=('cmaes', 'safe'))
    arrays = S._allocate(spec, spec.cells)
    res = S.StudyResult(
        spec=spec, cells=spec.cells, l_ref=L_REF, l_ref_sem=0.001, l_first=1.8, **arrays
    )
    res.losses[:] = L_REF * 1.0
    c = next(
        i for i, cell in enumerate(res.cells) if cell.algo == 'safe' and cell.label == 'defaults'
    )
    # run 0: 0.9 at evaluation 2, 0.5 at 4; run 1: 0.85 at 3 (never 0.5), 1 aborted;
    # run 2: 0.45 at evaluation 1 after 2 aborted tries
    res.losses[c] = L_REF * np.array(
        [[1.0, 0.9, 0.7, 0.5], [1.0, 0.95, 0.85, 2.0], [0.1, 0.1, 0.45, 0.6]]
    )
    res.aborted[c, 1, 3] = True
    res.aborted[c, 2, :2] = True
    res.remeasured[c] = L_REF * np.array([0.52, 0.88, 0.47])
    # standstill rms [A] (the start's after the move, after the load; the choice's): the
    # larger ratio of the two windows per run, their median (run 2 a quiet start)
    res.ripple[c] = [[0.2, 0.25, 0.3, 0.25], [0.2, 0.25, 0.1, 0.5], [1e-9, 0.2, 2.0, 0.2]]
    # peak to peak [A]: ratios 2.0, 1.0, 3.0 (the larger window's), median 2.0
    res.ripple_pp[c] = [[1.0, 1.0, 2.0, 1.5], [1.0, 1.0, 1.0, 0.5], [1.0, 1.0, 1.0, 3.0]]
    st = compute(res, 0.9)
    head, rows = comparison_rows(st)
    assert head[0] == 'method (configuration, start)' and len(head) == 9
    assert head[7] == 'ripple / start, median' and head[8] == 'peak-to-peak / start'
    labels = [r[0] for r in rows]
    assert 'safe defaults (hand-tuned start)' in labels
    assert 'CMA-ES sigma0=0.3 random start' in labels  # the start is not said twice
    assert len(set(labels)) == len(labels)
    row = rows[labels.index('safe defaults (hand-tuned start)')]
    value = [float(x.split(' [')[0]) for x in row[1:]]
    assert value[0] == pytest.approx((0.5 + 0.85 + 0.45) / 3, abs=5e-4)  # final: min measured
    assert value[1] == pytest.approx((0.52 + 0.88 + 0.47) / 3, abs=5e-4)  # re-measured
    assert value[2] == pytest.approx((2 + 3 + 3) / 3, abs=0.05)  # evaluations to <= 0.9
    assert value[3] == pytest.approx((4 + 3) / 2, abs=0.05)  # to <= 0.5: median of 2 runs
    assert value[4] == pytest.approx(100 * 2 / 3, abs=0.5)  # runs reaching 0.5 [%]
    assert value[5] == pytest.approx((0 + 1 + 2) / 3, abs=0.05)  # aborted per run
    assert value[6] == pytest.approx(2.0, abs=5e-3)  # ripple ratio: 1.5, 2.0, 2e9
    assert value[7] == pytest.approx(2.0, abs=5e-3)  # peak to peak: 2.0, 1.0, 3.0
    cs = next(x for x in st.cells if x.cell.algo == 'safe' and x.cell.label == 'defaults')
    assert cs.ripple_over.value == pytest.approx(200 / 3) and cs.ripple_over.n == 3
    assert cs.ripple_ratio.n == 3


def test_one_run_per_configuration_has_means_without_intervals():
    """A 1-run study (a smoke test) is tabulated: scipy's bootstrap refuses a sample of
    one run, so every mean stands alone (no interval) and a verdict that needs one is
    'not significant'; Wilson's interval of a percentage is defined for n = 1 and kept."""
    from im_tuner.study.text import comparison_rows, tables_text

    finals = {('spsa', i, j): 0.8 for i in range(3) for j in range(3)}
    finals.update({('necga', 0, j): 0.6 for j in range(3)})
    res = make_result(runs=1, budget=10, finals=finals)
    st = compute(res)
    for c, cs in enumerate(st.cells):
        for name in ('final', 'remeasured', 'evals', 'iterations', 'aborted_per_run'):
            iv = getattr(cs, name)
            assert math.isfinite(iv.value) and math.isnan(iv.lo) and math.isnan(iv.hi), name
        # the mean of one run is that run (nothing aborted: the smallest loss)
        assert cs.final.value == pytest.approx(float(res.losses[c, 0].min() / L_REF), abs=1e-15)
        lo, hi = wilson(1, 1)
        assert cs.satisfactory.value == 100.0
        assert (cs.satisfactory.lo, cs.satisfactory.hi) == pytest.approx((100 * lo, 100 * hi))
    verdicts = {c.claim: c.verdict for c in st.conclusions}
    assert verdicts['neCGA reaches a lower average final loss than SPSA'] == 'not significant'
    assert verdicts['neCGA reaches a satisfactory loss faster than SPSA'] == 'not significant'
    text = tables_text(st)
    assert '1 run per configuration: means without intervals' in text
    assert '[' not in text.split('Table I:')[1].split('Table II:')[0]  # no interval in Table I
    _head, rows = comparison_rows(st)
    assert all(' [' not in r[1] for r in rows)  # the final loss column
    # two runs: intervals again, and no note
    st2 = compute(make_result(runs=2, budget=10, finals=finals))
    assert all(math.isfinite(c.final.lo) for c in st2.cells)
    assert 'means without intervals' not in tables_text(st2)


def test_the_study_has_a_grid_for_every_tuner_algorithm():
    from im_tuner import optim
    from im_tuner.study import spec

    # every tuner algorithm, then the outside reference rows (Py-BOBYQA)
    assert spec.STUDY_ALGOS == (*optim.ALGOS, 'bobyqa') == optim.ALGOS + spec.REFERENCE_ALGOS
    for algo in optim.ALGOS:
        cells = spec.grid((algo,))
        assert len(cells) >= 3 and {c.algo for c in cells} == {algo}, algo
    with pytest.raises(ValueError, match="no study grid for 'simplex'"):
        S.StudySpec(algos=('spsa', 'simplex'))
