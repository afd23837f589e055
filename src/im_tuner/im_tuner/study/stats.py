"""Tables I-III of the paper from a study, with 95 % intervals, and the paper's conclusions
checked against them.  Pure numpy and scipy (no rclpy, no plotting).

What each statistic is and why (normalised loss, final loss, satisfactory run, evaluations
and iterations to it, the intervals): docs/reproduction.md, "What is compared, and how".
The intervals are scipy's: ``scipy.stats.bootstrap(..., paired=True, method='percentile')``
with one fixed seed for every call (``BOOT_SEED``: every cell and every difference sees the
same resampled run indices, as run r of every cell shares its seeds), and
``scipy.stats.binomtest(k, n).proportion_ci(method='wilson')``.  A study of fewer than
``MIN_RUNS_FOR_INTERVALS`` runs has no bootstrap intervals: its means stand alone, and a
verdict that needs one is 'not significant'.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.stats

from ..runlog.ripple import DEFAULT_RIPPLE_LIMIT
from .results import StudyResult
from .spec import MIN_RUNS_FOR_INTERVALS, Cell

#: The paper's Tables I-III on its grid of configurations: (algo, row) -> each column's
#: (final loss (Table I), satisfactory runs [%] (Table II), iterations to satisfactory (III)).
_PAPER_GRID: dict[tuple[str, int], tuple[tuple[float, int, int], ...]] = {
    ('spsa', 0): ((0.91, 92, 92), (0.99, 64, 82), (0.99, 54, 93)),
    ('spsa', 1): ((0.83, 86, 46), (0.81, 90, 47), (0.88, 84, 64)),
    ('spsa', 2): ((0.97, 44, 46), (0.84, 90, 23), (0.83, 78, 25)),
    ('necga', 0): ((0.85, 90, 36), (0.70, 92, 25), (0.72, 85, 28)),
}
#: The same by statistic (a CellStats attribute): statistic -> (algo, row, col) -> value.
PAPER: dict[str, dict[tuple[str, int, int], float]] = {
    stat: {
        (algo, row, col): values[i]
        for (algo, row), columns in _PAPER_GRID.items()
        for col, values in enumerate(columns)
    }
    for i, stat in enumerate(('final', 'satisfactory', 'iterations'))
}
#: The paper's own configuration of each algorithm (the centre of its grid).
PAPER_CELL: dict[str, tuple[int, int]] = {'spsa': (1, 1), 'necga': (0, 1)}
#: The paper's optimiser time per iteration [us] (dSPACE 1104, 5 parameters x 16 bits).
PAPER_US_PER_ITERATION: dict[str, float] = {'spsa': 180.0, 'necga': 600.0}
EXPERIMENT_S = 1.625  # one experiment on the bench [s]: its 0.5 s settle + the 1.125 s measured
#: The second level of the comparison beyond the paper (normalised loss): "good", where
#: every sensible method ends (the comparison table: evaluations to <= 0.5, median).
FAST_LEVEL = 0.5
BOOT = 4000
BOOT_SEED = 20051


def wilson(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a proportion k/n (as fractions); (nan, nan) when n = 0."""
    if n == 0:
        return (math.nan, math.nan)
    ci = scipy.stats.binomtest(int(k), int(n)).proportion_ci(confidence, method='wilson')
    return (float(ci.low), float(ci.high))


@dataclass
class Interval:
    value: float
    lo: float
    hi: float
    n: int

    def excludes_zero(self) -> int:
        """+1 if the interval is above 0, -1 if below, 0 if it contains 0 (or is nan)."""
        if self.lo > 0:
            return 1
        if self.hi < 0:
            return -1
        return 0


@dataclass
class CellStats:
    cell: Cell
    runs: int
    final: Interval  #: mean final L_n over runs with one
    final_median: float
    no_final: int  #: runs in which every experiment was aborted
    remeasured: Interval  #: mean re-measured L_n of the final controllers
    satisfactory: Interval  #: % of runs (Wilson)
    evals: Interval  #: mean evaluations to satisfactory (satisfactory runs)
    iterations: Interval  #: the same in the optimiser's iterations
    start: float  #: mean L_n of the reference (start) experiments
    aborted_pct: float  #: % of evaluations aborted
    faults: int  #: safety faults
    fast: Interval  #: median evaluations to <= FAST_LEVEL (runs that reach it)
    fast_reached: Interval  #: % of runs reaching FAST_LEVEL (Wilson)
    aborted_per_run: Interval  #: mean aborted experiments per run
    #: median over runs of the final choice's standstill rms of isq* / the start's (the
    #: larger of the two windows; a median: a quiet random start makes one ratio huge);
    #: nan: not measured
    ripple_ratio: Interval
    #: % of runs whose ripple ratio exceeds the default limit (runlog.ripple.DEFAULT_RIPPLE_LIMIT)
    ripple_over: Interval
    #: as ``ripple_ratio``, peak to peak (what the limit does not bound: a point within it
    #: in rms can still swing further)
    ripple_pp_ratio: Interval

    def paper(self, stat: str) -> float | None:
        """The paper's value of statistic ``stat`` (an attribute) in this cell; None: none."""
        return PAPER.get(stat, {}).get((self.cell.algo, self.cell.row, self.cell.col))


@dataclass
class Conclusion:
    claim: str  #: the paper's claim
    paper: str  #: the paper's evidence
    ours: str  #: our numbers with intervals
    verdict: str  #: 'holds', 'does not hold', 'reversed', 'not significant'


@dataclass
class StudyStats:
    res: StudyResult
    threshold: float
    cells: list[CellStats]
    conclusions: list[Conclusion] = field(default_factory=list)
    us_per_eval: dict[str, float] = field(default_factory=dict)
    us_per_iteration: dict[str, float] = field(default_factory=dict)

    def cell(self, algo: str, row: int, col: int) -> CellStats | None:
        for c in self.cells:
            if (c.cell.algo, c.cell.row, c.cell.col) == (algo, row, col):
                return c
        return None


# -- per-run quantities ------------------------------------------------------------------------
def per_run(res: StudyResult, threshold: float) -> dict[str, np.ndarray]:
    """[cells, runs] arrays: final L_n (nan: none), satisfactory, evaluations and
    iterations to satisfactory (nan: not reached), re-measured L_n, start L_n,
    evaluations to FAST_LEVEL (nan: not reached), aborted experiments."""
    Ln = res.losses / res.l_ref
    ok = ~res.aborted
    masked = np.where(ok, Ln, np.inf)
    final = masked.min(axis=2)
    final[~np.isfinite(final)] = np.nan
    hit = ok & (Ln <= threshold)
    reached = hit.any(axis=2)
    first = np.argmax(hit, axis=2)  # 0-based index of the first hit
    evals = np.where(reached, first + 1.0, np.nan)
    fast_hit = ok & (Ln <= FAST_LEVEL)  # the same count at the comparison's second level
    fast = np.where(fast_hit.any(axis=2), np.argmax(fast_hit, axis=2) + 1.0, np.nan)
    iters = np.take_along_axis(res.iteration, first[..., None], axis=2)[..., 0]
    iters = np.where(reached, iters.astype(float), np.nan)
    return {
        'final': final,
        'satisfactory': reached,
        'evals': evals,
        'iterations': iters,
        'remeasured': res.remeasured / res.l_ref,
        'start': res.ref_loss / res.l_ref,
        'fast': fast,
        'aborted': res.aborted.sum(axis=2).astype(float),
        'ripple_ratio': ripple_ratio(res),
        'ripple_pp_ratio': ripple_ratio(res, 'pp'),
    }


def ripple_ratio(res: StudyResult, measure: str = 'rms') -> np.ndarray:
    """[cells, runs]: the final choice's standstill rms of isq* (``measure`` 'pp': peak to
    peak) over the start's, the larger of the two windows (after the move, after the
    load); nan: not measured."""
    rip = np.asarray(res.ripple if measure == 'rms' else res.ripple_pp, dtype=float)
    with np.errstate(invalid='ignore', divide='ignore'):
        r = rip[..., 2:] / rip[..., :2]
    out = np.max(r, axis=-1)
    out[np.any(np.isnan(r), axis=-1)] = np.nan
    return out


def _mean_defined(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Mean over ``axis`` of the defined (non-nan) values; nan where none is (no warning)."""
    ok = ~np.isnan(x)
    cnt = np.sum(ok, axis=axis)
    tot = np.sum(np.where(ok, x, 0.0), axis=axis)
    with np.errstate(invalid='ignore', divide='ignore'):
        return np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan)


class _Boot:
    """Paired percentile bootstrap over run indices (``scipy.stats.bootstrap``): every call
    uses the same seed, hence the same resampled run indices, for every cell."""

    def __init__(self, runs: int) -> None:
        self.runs = runs

    @property
    def defined(self) -> bool:
        """Whether there are intervals: a resample of a single run is that run (scipy
        refuses a sample of one), so a 1-run study reports its means without them."""
        return self.runs >= MIN_RUNS_FOR_INTERVALS

    def dist(self, statistic, *samples: np.ndarray) -> np.ndarray:
        """Bootstrap distribution [BOOT] of ``statistic(*samples, axis=-1)`` (runs paired);
        all nan when there are too few runs (:attr:`defined`)."""
        if not self.defined:
            return np.full(BOOT, np.nan)
        with warnings.catch_warnings():
            # a constant sample is "degenerate" to scipy; its percentile interval is fine
            warnings.simplefilter('ignore', scipy.stats.DegenerateDataWarning)
            res = scipy.stats.bootstrap(
                samples,
                statistic,
                n_resamples=BOOT,
                paired=True,
                vectorized=True,
                confidence_level=0.95,
                method='percentile',
                rng=np.random.default_rng(BOOT_SEED),
            )
        return np.asarray(res.bootstrap_distribution, dtype=float)

    def mean(self, x: np.ndarray) -> np.ndarray:
        """Bootstrap distribution of the mean of the defined values of x[runs]."""
        return self.dist(_mean_defined, x)

    def mean_of(self, x: np.ndarray) -> Interval:
        """The mean of the defined values of x[runs], with its interval."""
        return self.interval(_nanmean(x), self.mean(x), _defined(x))

    def median_of(self, x: np.ndarray) -> Interval:
        """The median of the defined values of x[runs], with its interval."""
        n = _defined(x)
        point = float(_median_defined(x)) if n else math.nan
        return self.interval(point, self.dist(_median_defined, x), n)

    @staticmethod
    def interval(point: float, dist: np.ndarray, n: int) -> Interval:
        """The percentile interval of ``dist``, over the resamples where the statistic is
        defined (a mean of runs that reached a level is undefined in a resample that drew
        none of them); no interval if fewer than half are."""
        d = dist[np.isfinite(dist)]
        if not math.isfinite(point) or d.size < BOOT // 2:
            return Interval(point, math.nan, math.nan, n)
        lo, hi = np.percentile(d, [2.5, 97.5])
        return Interval(point, float(lo), float(hi), n)


def _median_defined(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Median over ``axis`` of the defined values; nan where none is (no warning)."""
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)
        return np.nanmedian(x, axis=axis)


def _defined(x: np.ndarray) -> int:
    """How many values of ``x`` are defined (not nan)."""
    return int(np.sum(~np.isnan(x)))


def _percent(k: int, n: int) -> Interval:
    """``k`` runs of ``n`` as a percentage, with Wilson's interval (nan: ``n`` = 0)."""
    lo, hi = wilson(k, n)
    return Interval(100.0 * k / n if n else math.nan, 100 * lo, 100 * hi, n)


def _nanmean(x: np.ndarray) -> float:
    x = x[~np.isnan(x)]
    return float(x.mean()) if x.size else math.nan


def compute(res: StudyResult, threshold: float | None = None) -> StudyStats:
    """Tables and conclusions of ``res`` at the satisfactory ``threshold`` (normalised;
    None: the study's)."""
    thr = res.spec.satisfactory if threshold is None else float(threshold)
    if not (thr > 0 and math.isfinite(thr)):
        raise ValueError(f'the satisfactory threshold must be a normalised loss > 0, got {thr!r}')
    pr = per_run(res, thr)
    runs = res.spec.runs
    boot = _Boot(runs)
    cells = []
    for c, cell in enumerate(res.cells):
        fin, rr = pr['final'][c], pr['ripple_ratio'][c]
        nf, nr = _defined(fin), _defined(rr)
        cells.append(
            CellStats(
                cell=cell,
                runs=runs,
                final=boot.mean_of(fin),
                final_median=float(np.nanmedian(fin)) if nf else math.nan,
                no_final=runs - nf,
                remeasured=boot.mean_of(pr['remeasured'][c]),
                satisfactory=_percent(int(pr['satisfactory'][c].sum()), runs),
                evals=boot.mean_of(pr['evals'][c]),
                iterations=boot.mean_of(pr['iterations'][c]),
                start=_nanmean(pr['start'][c]),
                aborted_pct=100.0 * float(res.aborted[c].mean()),
                faults=int(res.faults[c].sum()),
                fast=boot.median_of(pr['fast'][c]),
                fast_reached=_percent(_defined(pr['fast'][c]), runs),
                aborted_per_run=boot.mean_of(pr['aborted'][c]),
                ripple_ratio=boot.median_of(rr),
                ripple_over=_percent(int(np.sum(rr[~np.isnan(rr)] > DEFAULT_RIPPLE_LIMIT)), nr),
                ripple_pp_ratio=boot.median_of(pr['ripple_pp_ratio'][c]),
            )
        )
    st = StudyStats(res=res, threshold=thr, cells=cells)
    _timing(st)
    st.conclusions = _conclusions(st, pr, boot)
    return st


def _timing(st: StudyStats) -> None:
    """Median optimiser time per evaluation and per iteration [us] by algorithm (timing:
    machine-dependent, not part of the reproducible results)."""
    res = st.res
    for algo in res.spec.algos:
        idx = [c for c, cell in enumerate(res.cells) if cell.algo == algo]
        per_eval = res.opt_s[idx] / res.spec.budget * 1e6
        iters = res.iteration[idx][..., -1].astype(float)  # iterations of the whole run
        per_iter = res.opt_s[idx] / np.maximum(iters, 1.0) * 1e6
        st.us_per_eval[algo] = float(np.median(per_eval))
        st.us_per_iteration[algo] = float(np.median(per_iter))


# -- the paper's conclusions --------------------------------------------------------------------
def _fmt_iv(iv: Interval, digits: int = 3, none: str = 'n/a') -> str:
    """``value [lo, hi]`` (``value`` alone without an interval; ``none``: no value)."""
    if not math.isfinite(iv.value):
        return none
    if not math.isfinite(iv.lo):
        return f'{iv.value:.{digits}f}'
    return f'{iv.value:.{digits}f} [{iv.lo:.{digits}f}, {iv.hi:.{digits}f}]'


def _verdict(iv: Interval, expected_sign: int) -> str:
    s = iv.excludes_zero()
    if s == 0:
        return 'not significant'
    return 'holds' if s == expected_sign else 'reversed'


def _diff(boot: _Boot, a: np.ndarray, b: np.ndarray) -> Interval:
    """mean(a) - mean(b) (nan-aware), paired bootstrap interval."""
    point = _nanmean(a) - _nanmean(b)
    return boot.interval(point, boot.mean(a) - boot.mean(b), _defined(a))


def _range_dist(boot: _Boot, rows: list[np.ndarray], pct: bool) -> tuple[float, np.ndarray]:
    """max - min over cells of the per-cell mean (or % true), with its bootstrap
    distribution (runs resampled together)."""
    if pct:
        pts = [100.0 * float(r.mean()) for r in rows]
        dists = [
            boot.dist(lambda x, axis=-1: 100.0 * np.mean(x, axis=axis), r.astype(float))
            for r in rows
        ]
    else:
        pts = [_nanmean(r) for r in rows]
        dists = [boot.mean(r) for r in rows]
    return max(pts) - min(pts), np.max(dists, axis=0) - np.min(dists, axis=0)


def _conclusions(st: StudyStats, pr: dict[str, np.ndarray], boot: _Boot) -> list[Conclusion]:
    res = st.res
    algos = set(res.spec.algos)
    if not {'spsa', 'necga'} <= algos or not res.spec.full_grid:
        return []
    ci = {(c.algo, c.row, c.col): i for i, c in enumerate(res.cells)}
    sp, ne = ci[('spsa', *PAPER_CELL['spsa'])], ci[('necga', *PAPER_CELL['necga'])]
    sp_all = [i for i, c in enumerate(res.cells) if c.algo == 'spsa']
    ne_all = [i for i, c in enumerate(res.cells) if c.algo == 'necga']
    S, N = st.cells[sp], st.cells[ne]
    out: list[Conclusion] = []
    thr = st.threshold

    # 1. lower average final loss
    d1 = _diff(boot, pr['final'][sp], pr['final'][ne])
    grand_s = np.nanmean(pr['final'][sp_all], axis=0)
    grand_n = np.nanmean(pr['final'][ne_all], axis=0)
    d1g = _diff(boot, grand_s, grand_n)
    out.append(
        Conclusion(
            claim='neCGA reaches a lower average final loss than SPSA',
            paper='Table I: 0.70 (n=25) vs 0.81 (a=0.0183, c=0.03); over the grid 0.76 vs 0.89',
            ours=(
                f'{_fmt_iv(N.final)} vs {_fmt_iv(S.final)}; difference SPSA - neCGA '
                f'{_fmt_iv(d1)}; over the grid (mean of the cells) difference {_fmt_iv(d1g)}'
            ),
            verdict=_verdict(d1, +1),
        )
    )

    # 2. less influenced by the configuration
    rs, dist_s = _range_dist(boot, [pr['satisfactory'][i] for i in sp_all], pct=True)
    rn, dist_n = _range_dist(boot, [pr['satisfactory'][i] for i in ne_all], pct=True)
    d2 = boot.interval(rs - rn, dist_s - dist_n, res.spec.runs)
    fs, fdist_s = _range_dist(boot, [pr['final'][i] for i in sp_all], pct=False)
    fn, fdist_n = _range_dist(boot, [pr['final'][i] for i in ne_all], pct=False)
    d2f = boot.interval(fs - fn, fdist_s - fdist_n, res.spec.runs)
    out.append(
        Conclusion(
            claim='neCGA is less sensitive to its configuration (n) than SPSA to (a, c)',
            paper=(
                'Table II: satisfactory runs range over 85-92 % for neCGA (7 points) and '
                '44-92 % for SPSA (48 points); Table I: 0.70-0.85 vs 0.81-0.99'
            ),
            ours=(
                f'range of % satisfactory: SPSA {rs:.0f} points, neCGA {rn:.0f} points, '
                f'difference {_fmt_iv(d2, 0)}; range of the average final loss: SPSA {fs:.3f}, '
                f'neCGA {fn:.3f}, difference {_fmt_iv(d2f)}'
            ),
            verdict=_verdict(d2, +1),
        )
    )

    # 3. faster to a satisfactory loss
    d3 = _diff(boot, pr['evals'][sp], pr['evals'][ne])
    d3i = _diff(boot, pr['iterations'][sp], pr['iterations'][ne])
    out.append(
        Conclusion(
            claim='neCGA reaches a satisfactory loss faster than SPSA',
            paper='Table III: 25 iterations (n=25) vs 47 (a=0.0183, c=0.03)',
            ours=(
                f'evaluations: {_fmt_iv(N.evals, 1)} vs {_fmt_iv(S.evals, 1)}, difference '
                f'{_fmt_iv(d3, 1)}; iterations: {_fmt_iv(N.iterations, 1)} vs '
                f'{_fmt_iv(S.iterations, 1)}, difference {_fmt_iv(d3i, 1)} (threshold {thr:g})'
            ),
            verdict=_verdict(d3, +1),
        )
    )

    # 4. the paper's configurations are the best of their grids
    for algo, centre, idxs in (('spsa', sp, sp_all), ('necga', ne, ne_all)):
        best = min(idxs, key=lambda i: (st.cells[i].final.value, i))
        if best == centre:
            v, txt = 'holds', f'{res.cells[centre].label} has the lowest average final loss'
        else:
            d = _diff(boot, pr['final'][centre], pr['final'][best])
            v = 'does not hold' if d.excludes_zero() == 1 else 'not significant'
            txt = (
                f'best is {res.cells[best].label} ({_fmt_iv(st.cells[best].final)}); the '
                f"paper's {res.cells[centre].label} is {_fmt_iv(st.cells[centre].final)}, "
                f'difference {_fmt_iv(d)}'
            )
        name = 'SPSA (a=0.0183, c=0.03)' if algo == 'spsa' else 'neCGA (n=25, eta=12)'
        out.append(
            Conclusion(
                claim=f"the paper's configuration of {name} is the best of its grid",
                paper=(
                    'chosen after a preliminary configuration study; Table I agrees (0.81 and '
                    '0.70 are the lowest)'
                ),
                ours=txt,
                verdict=v,
            )
        )

    # 5. an effective controller within three minutes of bench time
    t_s = (1 + S.evals.value) * EXPERIMENT_S
    t_n = (1 + N.evals.value) * EXPERIMENT_S
    out.append(
        Conclusion(
            claim='both reach a very effective controller in less than three minutes on the bench',
            paper='"less than three minutes" (160 experiments of 1.125 s)',
            ours=(
                f'mean time to a satisfactory loss (reference + evaluations, 1.625 s each: '
                f'0.5 s settle + 1.125 s): '
                f'SPSA {t_s:.0f} s, neCGA {t_n:.0f} s'
            ),
            verdict='holds' if max(t_s, t_n) < 180.0 else 'does not hold',
        )
    )

    # 6. computation per iteration
    us_s, us_n = st.us_per_iteration.get('spsa'), st.us_per_iteration.get('necga')
    ratio = us_s / us_n if us_s and us_n else math.nan
    out.append(
        Conclusion(
            claim='SPSA needs about a third of the computation of neCGA per iteration',
            paper=(
                f'{PAPER_US_PER_ITERATION["spsa"]:.0f} us vs {PAPER_US_PER_ITERATION["necga"]:.0f} '
                'us per iteration on the dSPACE board (ratio 0.30)'
            ),
            ours=(
                f'median ask + tell per iteration on this machine: SPSA {us_s:.1f} us, neCGA '
                f'{us_n:.1f} us (ratio {ratio:.2f}); per evaluation {st.us_per_eval["spsa"]:.1f} '
                f'vs {st.us_per_eval["necga"]:.1f} us (timing: machine-dependent)'
            ),
            verdict='holds' if ratio < 0.5 else 'does not hold',
        )
    )
    return out
