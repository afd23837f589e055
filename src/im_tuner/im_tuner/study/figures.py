"""The study's figures: the tables as bars beside the paper's values, convergence."""

from __future__ import annotations

import math
import warnings

import numpy as np

from .spec import PAPER_ALGOS
from .stats import FAST_LEVEL, PAPER_CELL, StudyStats
from .summary import GOAL as DEFAULT_GOAL
from .text import ALGO_NAME, STATS


# -- figures --------------------------------------------------------------------------------------
def _bars(cells: list, stat: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bar lengths (nan -> 0) and the error bars below and above them of one statistic of
    each cell (its Interval): the lengths to the interval's ends, 0 where an end is nan."""
    ivs = [getattr(c, stat) for c in cells]
    v = np.array([i.value for i in ivs])
    # (a percentile interval of a small sample need not contain the point)
    lo = np.array([max(i.value - i.lo, 0.0) if math.isfinite(i.lo) else 0.0 for i in ivs])
    hi = np.array([max(i.hi - i.value, 0.0) if math.isfinite(i.hi) else 0.0 for i in ivs])
    return np.nan_to_num(v), lo, hi


def fig_tables(st: StudyStats):
    from matplotlib.figure import Figure

    cells = [c for c in st.cells if c.cell.algo in PAPER_ALGOS]  # Tables I-III
    fig = Figure(figsize=(12, 9.5), layout='constrained')
    axes = fig.subplots(3, 1)
    labels = [f'{ALGO_NAME[c.cell.algo]}\n' + c.cell.label.replace(' ', '\n') for c in cells]
    x = np.arange(len(cells))
    colours = ['tab:blue' if c.cell.algo == 'spsa' else 'tab:orange' for c in cells]
    for ax, (stat, title, _), ylab in zip(
        axes,
        (STATS[0], STATS[1], STATS[3]),
        ('final loss (hand-tuned = 1)', 'satisfactory runs [%]', 'iterations to satisfactory'),
        strict=True,
    ):
        v, lo, hi = _bars(cells, stat)
        ax.bar(
            x,
            v,
            color=colours,
            alpha=0.75,
            gid=f'ours:{stat}',
            label='simulation (mean, 95 % interval)',
        )
        ax.errorbar(x, v, yerr=[lo, hi], fmt='none', ecolor='k', capsize=3)
        pv = np.array([c.paper(stat) if c.paper(stat) is not None else np.nan for c in cells])
        ax.plot(
            x, pv, 'D', color='tab:red', markersize=7, gid=f'paper:{stat}', label='paper (bench)'
        )
        if stat == 'final':
            ax.axhline(
                st.threshold,
                color='tab:green',
                ls='--',
                lw=1,
                label=f'satisfactory threshold {st.threshold:g}',
            )
            ax.axhline(1.0, color='0.4', ls=':', lw=1, label='hand-tuned start')
        ax.set_title(title)
        ax.set_ylabel(ylab)
        ax.set_xticks(x, labels, fontsize=7)
        ax.legend(fontsize=7, loc='best', framealpha=0.9)
        ax.grid(axis='y', alpha=0.3)
    return fig


def fig_convergence(st: StudyStats):
    from matplotlib.figure import Figure

    res = st.res
    Ln = np.where(res.aborted, np.inf, res.losses / res.l_ref)
    best = np.minimum.accumulate(Ln, axis=2)  # best-so-far per run
    evals = np.arange(1, res.spec.budget + 1)
    algos = list(res.spec.algos)
    ncol = min(4, len(algos))
    nrow = -(-len(algos) // ncol)
    fig = Figure(figsize=(6 * ncol, 4.5 * nrow), layout='constrained')
    grid = np.atleast_1d(fig.subplots(nrow, ncol, sharey=True)).ravel()
    for ax in grid[len(algos) :]:
        ax.set_visible(False)
    axes = grid[: len(algos)]
    import matplotlib

    cmap = matplotlib.colormaps['tab10']
    for ax, algo in zip(axes, algos, strict=True):
        idx = [c for c, cell in enumerate(res.cells) if cell.algo == algo]
        for k, c in enumerate(idx):
            b = best[c]
            with np.errstate(invalid='ignore'):
                med = np.median(b, axis=0)
            # the paper's configuration; beyond the paper, the grid's second (default) cell
            centre = (res.cells[c].row, res.cells[c].col) == PAPER_CELL.get(algo, (0, 1))
            ax.plot(
                evals,
                np.where(np.isfinite(med), med, np.nan),
                color=cmap(k % 10),
                lw=2.5 if centre else 1.2,
                gid=f'median:{res.cells[c].label}',
                label=res.cells[c].label
                + ((" (paper's)" if algo in PAPER_CELL else ' (default)') if centre else ''),
            )
            if centre:
                # an evaluation no run has a measured loss at yet (an aborted start: every
                # run with one run) has no quartiles: a gap, not a warning on stderr
                with np.errstate(invalid='ignore'), warnings.catch_warnings():
                    warnings.simplefilter('ignore', RuntimeWarning)
                    q1, q3 = np.nanquantile(
                        np.where(np.isfinite(b), b, np.nan), [0.25, 0.75], axis=0
                    )
                ax.fill_between(evals, q1, q3, color=cmap(k % 10), alpha=0.2)
        ax.axhline(st.threshold, color='tab:green', ls='--', lw=1, label='satisfactory')
        ax.axhline(1.0, color='0.4', ls=':', lw=1, label='hand-tuned start')
        ax.set_title(f'{ALGO_NAME[algo]}: median best-so-far loss of {res.spec.runs} runs')
        ax.set_xlabel('loss evaluations (experiments: 0.5 s settle + 1.125 s)')
        ax.set_ylabel('best loss so far (hand-tuned = 1)')
        ax.set_ylim(0.0, 1.6)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return fig


#: The goal for a real-bench default (drawn on the comparison figure): the default's
#: (``summary.GOAL``), the re-measured loss as a level.
GOAL = {'remeasured': 0.46, **{k: DEFAULT_GOAL[k] for k in ('evals', 'fast', 'aborted_per_run')}}


def fig_comparison(st: StudyStats):
    """Every configuration side by side: re-measured final loss, evaluations to the
    satisfactory level and to FAST_LEVEL, aborted experiments per run (95 % intervals)."""
    from matplotlib.figure import Figure

    cells = st.cells
    fig = Figure(figsize=(15, 0.32 * len(cells) + 2.2), layout='constrained')
    axes = fig.subplots(1, 4, sharey=True)
    y = np.arange(len(cells))[::-1]
    labels = [f'{ALGO_NAME.get(c.cell.algo, c.cell.algo)} {c.cell.label}' for c in cells]
    algos = list(dict.fromkeys(c.cell.algo for c in cells))
    cmap = {a: f'C{i % 10}' for i, a in enumerate(algos)}
    titles = (
        ('remeasured', 're-measured final loss (mean)'),
        ('evals', f'evaluations to <= {st.threshold:g} (mean)'),
        ('fast', f'evaluations to <= {FAST_LEVEL:g} (median)'),
        ('aborted_per_run', 'aborted experiments per run (mean)'),
    )
    for ax, (stat, title) in zip(axes, titles, strict=True):
        v, lo, hi = _bars(cells, stat)
        ax.barh(
            y,
            v,
            color=[cmap[c.cell.algo] for c in cells],
            alpha=0.75,
            gid=f'ours:{stat}',
        )
        ax.errorbar(v, y, xerr=[lo, hi], fmt='none', ecolor='k', capsize=2)
        ax.axvline(GOAL[stat], color='tab:red', ls='--', lw=1, label='goal of a real-bench default')
        ax.set_title(title, fontsize=9)
        ax.grid(axis='x', alpha=0.3)
    axes[0].set_yticks(y, labels, fontsize=8)
    axes[0].legend(fontsize=8, loc='lower right')
    fig.suptitle(
        'Beyond the paper: every configuration on the same seeds (normalised loss, '
        '95 % intervals; bars missing where no run reached the level)',
        fontsize=10,
    )
    return fig
