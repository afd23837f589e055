"""``ros2 run im_tuner study``: the paper's configuration study (Tables I-III) offline.

    ros2 run im_tuner study                          # the paper's grid: 12 x 100 x 200
    ros2 run im_tuner study --runs 20 --budget 100   # a quicker look
    ros2 run im_tuner study --from bags/study_X --satisfactory 0.8   # re-tabulate

Writes into ``--out`` (default ``bags/study_<model>_<UTC time>/``):

* ``tables.txt``   -- Tables I-III with 95 % intervals and the paper's values beside
  them, and the paper's conclusions checked (also printed);
* ``tables.csv``   -- the same, one row per cell and statistic;
* ``runs.csv``     -- one row per run: seeds, start, final loss and gains, evaluations to
  a satisfactory loss, and the tuner command that repeats the run on the ROS bench;
* ``tables.png``   -- Tables I-III as bars with intervals against the paper's values;
* ``convergence.png`` -- median best-so-far loss against evaluations, per configuration;
* ``reproduction.md`` -- the write-up (docs/reproduction.md is this file of a full run);
* ``study.npz``, ``study.json`` -- every loss of every run and the study's definition
  (``--from`` reads them back);
* ``starts/run_<r>.yaml`` -- the tuner parameter file of SPSA run r (its random start).

No rclpy: it runs the numba kernels of the nodes in a process pool (docs/reproduction.md).
"""

from __future__ import annotations

import argparse
import csv
import datetime as _dt
import math
import os
import shlex
import sys
from pathlib import Path

import numpy as np
import yaml

from im_controller.config import GAIN_NAMES
from im_drive_sim.cli import Parser, UsageError, int_in

from . import study as S
from .space import TunerParamsError
from .study_stats import (
    EXPERIMENT_S,
    PAPER_CELL,
    PAPER_US_PER_ITERATION,
    CellStats,
    Interval,
    StudyStats,
    compute,
    per_run,
)

__all__ = ['main', 'reproduction_md', 'tables_text', 'tuner_command', 'write_outputs']

EXIT_USAGE = 2
ALGO_NAME = {'spsa': 'SPSA', 'necga': 'neCGA'}
STATS = (
    ('final', 'Table I: average final loss (normalised: hand-tuned start = 1)', 3),
    ('satisfactory', 'Table II: satisfactory runs [%]', 0),
    ('evals', 'Table III: average evaluations to a satisfactory loss', 1),
    (
        'iterations',
        'Table III: the same in iterations (SPSA: 2 evaluations each; neCGA: generations)',
        1,
    ),
)
PAPER_KEY = {
    'final': 'final',
    'satisfactory': 'satisfactory_pct',
    'iterations': 'iterations',
    'evals': None,
}


class StudyError(Exception):
    """Bad input: one line, exit 2, nothing written."""


# -- text -----------------------------------------------------------------------------------------
def _iv(iv: Interval, d: int) -> str:
    if not math.isfinite(iv.value):
        return '-'
    if not math.isfinite(iv.lo):
        return f'{iv.value:.{d}f}'
    return f'{iv.value:.{d}f} [{iv.lo:.{d}f}, {iv.hi:.{d}f}]'


def _paper(c: CellStats, stat: str, d: int) -> str:
    key = PAPER_KEY.get(stat)
    v = c.paper(key) if key else None
    return '' if v is None else (f'{v:.2f}' if d == 3 else f'{v:.0f}')


def _grids(
    st: StudyStats,
) -> list[tuple[str, list[str], list[str], dict[tuple[int, int], CellStats]]]:
    """(algo, row labels, column labels, (row, col) -> stats) per algorithm."""
    out = []
    for algo in st.res.spec.algos:
        cs = [c for c in st.cells if c.cell.algo == algo]
        by = {(c.cell.row, c.cell.col): c for c in cs}
        if algo == 'spsa':
            rows = [c.cell.label.split()[0] for c in cs if c.cell.col == 0]
            cols = [c.cell.label.split()[1] for c in cs if c.cell.row == 0]
        else:
            rows = ['eta=n/2']
            cols = [c.cell.label.split()[0] for c in cs]
        out.append((algo, rows, cols, by))
    return out


def tables_text(st: StudyStats) -> str:
    res = st.res
    sp = res.spec
    L = [
        f'Offline configuration study: {len(res.cells)} configurations x {sp.runs} runs x '
        f'{sp.budget} evaluations, {sp.model} model, seed {sp.seed}',
        f'loss normalised by L_ref = {res.l_ref:.5f} (+- {res.l_ref_sem:.5f}), the hand-tuned '
        f'start over {S.REF_EXPERIMENTS} experiments; satisfactory: final loss <= '
        f'{st.threshold:g}',
        'cells: ours mean [95 % interval] | paper',
        '',
    ]
    for stat, title, d in STATS:
        L.append(title)
        for algo, rows, cols, by in _grids(st):
            w = 24
            L.append(f'  {ALGO_NAME[algo]:<12}' + ''.join(f'{c:<{w + 7}}' for c in cols))
            for i, rl in enumerate(rows):
                line = f'  {rl:<12}'
                for j in range(len(cols)):
                    c = by[(i, j)]
                    iv = getattr(c, stat)
                    p = _paper(c, stat, d)
                    cell = _iv(iv, d) + (f' | {p}' if p else '')
                    line += f'{cell:<{w + 7}}'
                L.append(line.rstrip())
        L.append('')
    notes = [c for c in st.cells if c.no_final]
    if notes:
        L.append(
            'runs in which every experiment was aborted (no final controller; left out of '
            'Table I, not satisfactory): '
            + ', '.join(f'{c.cell.label}: {c.no_final}' for c in notes)
        )
    if st.conclusions:
        L.append("The paper's conclusions in simulation:")
        for k, concl in enumerate(st.conclusions, 1):
            L.append(f'  {k}. {concl.claim}: {concl.verdict.upper()}')
            L.append(f'     paper: {concl.paper}')
            L.append(f'     here:  {concl.ours}')
    rate = res.experiments / res.wall_s if res.wall_s > 0 else math.nan
    L.append('')
    L.append(
        f'{res.experiments} experiments in {res.wall_s:.1f} s on {res.jobs} worker(s): '
        f'{rate:.0f} experiments/s ({rate * EXPERIMENT_S:.0f} x real time)'
    )
    return '\n'.join(L) + '\n'


# -- files ----------------------------------------------------------------------------------------
def tuner_command(res: S.StudyResult, c: int, r: int, out: Path) -> str:
    """The tuner command that repeats run ``r`` of cell ``c`` on the ROS bench (its losses
    equal the study's bit for bit: test/test_study.py)."""
    cell, sp = res.cells[c], res.spec
    args = ['ros2', 'run', 'im_tuner', 'tuner', '--algo', cell.algo]
    for k, v in cell.options:
        args += [f'--{k.replace("_", "-")}', repr(v)]
    args += [
        '--seed',
        str(int(res.run_seed[r])),
        '--budget',
        str(sp.budget),
        '--model',
        sp.model,
        '--remeasure',
        '1' if sp.remeasure else '0',
    ]
    if cell.algo in S.optim.TAKES_START:
        args += ['--params', str(out / 'starts' / f'run_{r:03d}.yaml')]
    elif sp.params_file:
        args += ['--params', sp.params_file]
    if sp.drive_config:
        args += ['--drive-config', sp.drive_config]
    return ' '.join(shlex.quote(a) for a in args)


def write_starts(res: S.StudyResult, out: Path) -> None:
    """starts/run_<r>.yaml: the tuner parameter file of SPSA run r (box + its start)."""
    if 'spsa' not in res.spec.algos:
        return
    params = res.spec.params()
    c = next(i for i, cell in enumerate(res.cells) if cell.algo == 'spsa')
    d = out / 'starts'
    d.mkdir(parents=True, exist_ok=True)
    for r in range(res.spec.runs):
        box = {
            n: {'lo': lo, 'hi': hi, 'start': float(res.start[c, r, i])}
            for i, (n, lo, hi) in enumerate(
                zip(GAIN_NAMES, params.space.lo, params.space.hi, strict=True)
            )
        }
        text = (
            f'# SPSA run {r} of the study in {out.name}: random start (run seed '
            f'{int(res.run_seed[r])})\n'
            + yaml.safe_dump(
                {'search_box': box, 'satisfactory_loss': params.satisfactory_loss}, sort_keys=False
            )
        )
        (d / f'run_{r:03d}.yaml').write_text(text)


RUN_COLUMNS = (
    'algo',
    'config',
    'run',
    'run_seed',
    'drive_seed',
    *(f'start_{n}' for n in GAIN_NAMES),
    'start_loss',
    'final_loss',
    'final_loss_raw',
    'best_eval',
    *(f'best_{n}' for n in GAIN_NAMES),
    'remeasured_loss',
    'satisfactory',
    'evals_to_satisfactory',
    'iterations_to_satisfactory',
    'aborted',
    'faults',
    'tuner_command',
)


def write_runs_csv(st: StudyStats, out: Path) -> Path:
    res = st.res
    pr = per_run(res, st.threshold)
    path = out / 'runs.csv'
    with path.open('w', newline='') as f:
        w = csv.writer(f)
        w.writerow(RUN_COLUMNS)
        for c, cell in enumerate(res.cells):
            for r in range(res.spec.runs):
                be = int(res.best_eval[c, r])
                w.writerow(
                    [
                        cell.algo,
                        cell.label,
                        r,
                        int(res.run_seed[r]),
                        int(res.drive_seed[r]),
                        *(repr(float(x)) for x in res.start[c, r]),
                        repr(float(pr['start'][c, r])),
                        repr(float(pr['final'][c, r])),
                        repr(float(res.losses[c, r, be])) if be >= 0 else 'nan',
                        be,
                        *(repr(float(x)) for x in res.best_gains[c, r]),
                        repr(float(pr['remeasured'][c, r])),
                        int(pr['satisfactory'][c, r]),
                        '' if math.isnan(pr['evals'][c, r]) else int(pr['evals'][c, r]),
                        '' if math.isnan(pr['iterations'][c, r]) else int(pr['iterations'][c, r]),
                        int(res.aborted[c, r].sum()),
                        int(res.faults[c, r].sum()),
                        tuner_command(res, c, r, out),
                    ]
                )
    return path


def write_tables_csv(st: StudyStats, out: Path) -> Path:
    path = out / 'tables.csv'
    with path.open('w', newline='') as f:
        w = csv.writer(f)
        w.writerow(
            (
                'statistic',
                'algo',
                'config',
                'row',
                'col',
                'value',
                'ci_low',
                'ci_high',
                'n',
                'paper',
                'threshold',
            )
        )
        for stat, _, _ in (*STATS, ('remeasured', '', 3)):
            for c in st.cells:
                iv = getattr(c, stat)
                key = PAPER_KEY.get(stat)
                p = c.paper(key) if key else None
                w.writerow(
                    (
                        stat,
                        c.cell.algo,
                        c.cell.label,
                        c.cell.row,
                        c.cell.col,
                        repr(iv.value),
                        repr(iv.lo),
                        repr(iv.hi),
                        iv.n,
                        '' if p is None else p,
                        st.threshold,
                    )
                )
    return path


# -- figures --------------------------------------------------------------------------------------
def fig_tables(st: StudyStats):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 9.5), layout='constrained')
    axes = fig.subplots(3, 1)
    labels = [f'{ALGO_NAME[c.cell.algo]}\n' + c.cell.label.replace(' ', '\n') for c in st.cells]
    x = np.arange(len(st.cells))
    colours = ['tab:blue' if c.cell.algo == 'spsa' else 'tab:orange' for c in st.cells]
    for ax, (stat, title, _), ylab in zip(
        axes,
        (STATS[0], STATS[1], STATS[3]),
        ('final loss (hand-tuned = 1)', 'satisfactory runs [%]', 'iterations to satisfactory'),
        strict=True,
    ):
        ivs = [getattr(c, stat) for c in st.cells]
        v = np.array([i.value for i in ivs])
        # (a percentile interval of a small sample need not contain the point)
        lo = np.array([max(i.value - i.lo, 0.0) if math.isfinite(i.lo) else 0.0 for i in ivs])
        hi = np.array([max(i.hi - i.value, 0.0) if math.isfinite(i.hi) else 0.0 for i in ivs])
        ax.bar(
            x,
            np.nan_to_num(v),
            color=colours,
            alpha=0.75,
            gid=f'ours:{stat}',
            label='simulation (mean, 95 % interval)',
        )
        ax.errorbar(x, np.nan_to_num(v), yerr=[lo, hi], fmt='none', ecolor='k', capsize=3)
        key = PAPER_KEY[stat]
        assert key is not None  # the figure's three statistics all have paper values
        pv = np.array([c.paper(key) if c.paper(key) is not None else np.nan for c in st.cells])
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
    fig = Figure(figsize=(6 * len(algos), 4.5), layout='constrained')
    axes = np.atleast_1d(fig.subplots(1, len(algos), sharey=True))
    import matplotlib

    cmap = matplotlib.colormaps['tab10']
    for ax, algo in zip(axes, algos, strict=True):
        idx = [c for c, cell in enumerate(res.cells) if cell.algo == algo]
        for k, c in enumerate(idx):
            b = best[c]
            with np.errstate(invalid='ignore'):
                med = np.median(b, axis=0)
            centre = (res.cells[c].row, res.cells[c].col) == PAPER_CELL[algo]
            ax.plot(
                evals,
                np.where(np.isfinite(med), med, np.nan),
                color=cmap(k % 10),
                lw=2.5 if centre else 1.2,
                gid=f'median:{res.cells[c].label}',
                label=res.cells[c].label + (" (paper's)" if centre else ''),
            )
            if centre:
                with np.errstate(invalid='ignore'):
                    q1, q3 = np.nanquantile(
                        np.where(np.isfinite(b), b, np.nan), [0.25, 0.75], axis=0
                    )
                ax.fill_between(evals, q1, q3, color=cmap(k % 10), alpha=0.2)
        ax.axhline(st.threshold, color='tab:green', ls='--', lw=1, label='satisfactory')
        ax.axhline(1.0, color='0.4', ls=':', lw=1, label='hand-tuned start')
        ax.set_title(f'{ALGO_NAME[algo]}: median best-so-far loss of {res.spec.runs} runs')
        ax.set_xlabel('loss evaluations (experiments of 1.125 s)')
        ax.set_ylabel('best loss so far (hand-tuned = 1)')
        ax.set_ylim(0.0, 1.6)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return fig


# -- reproduction.md ------------------------------------------------------------------------------
def _md_table(st: StudyStats, stat: str, d: int) -> list[str]:
    L = []
    for algo, rows, cols, by in _grids(st):
        L.append(f'| {ALGO_NAME[algo]} | ' + ' | '.join(cols) + ' |')
        L.append('|---' * (len(cols) + 1) + '|')
        for i, rl in enumerate(rows):
            cells = []
            for j in range(len(cols)):
                c = by[(i, j)]
                p = _paper(c, stat, d)
                cells.append(_iv(getattr(c, stat), d) + (f' (paper {p})' if p else ''))
            L.append(f'| {rl} | ' + ' | '.join(cells) + ' |')
        L.append('')
    return L


def reproduction_md(st: StudyStats, command: str, figures: dict[str, str]) -> str:
    res, sp = st.res, st.res.spec
    rate = res.experiments / res.wall_s if res.wall_s > 0 else math.nan
    L = [
        "# Reproducing the paper's configuration study (Tables I-III) in simulation",
        '',
        '<!-- generated by `ros2 run im_tuner study` (im_tuner/study_cli.py); '
        '`make reproduction` regenerates it -->',
        '',
        f'Command: `{res.command or command}`'
        + (f' (tables re-made with `{command}`)' if res.command and command != res.command else ''),
        '',
        f'{len(res.cells)} configurations x {sp.runs} runs x {sp.budget} loss evaluations '
        f'({res.experiments} experiments of 1.125 s, {res.experiments * EXPERIMENT_S / 3600:.0f} h '
        f'of bench time) on the {sp.model} voltage-fed model with the encoder, seed {sp.seed}: '
        f'the grid ran in {res.wall_s:.0f} s on {res.jobs} worker(s), {rate:.0f} experiments/s.',
        '',
        '## What is compared, and how',
        '',
        '* **Runs.** Every run is what `ros2 run im_tuner tuner` does on the simulated '
        'lock-step bench: a fresh drive at rest, one reference experiment of the start '
        'gains (not counted), the evaluations, one re-measurement of the best. Run r of '
        'every configuration has the same seed (the same drive noise and, for SPSA, the '
        "same random start: common random numbers). `runs.csv` gives each run's tuner "
        'command; a test re-runs a sample of them through the ROS nodes and gets the same '
        'losses bit for bit.',
        '* **SPSA** starts from a point drawn uniformly in the search box (the paper: '
        '"different starting points in the search space"); A = 20, alpha = gamma = 0.3 as '
        'in the paper. **neCGA** starts from its uniform distribution; eta = floor(n/2).',
        f"* **Normalised loss.** The paper's values lie between 0.70 and 0.99, which only "
        f'makes sense relative to a reference controller; its runs start from a working '
        f'controller. We divide every loss by L_ref = {res.l_ref:.5f} (standard error '
        f'{res.l_ref_sem:.5f}), the mean loss of the hand-tuned start gains over '
        f'{S.REF_EXPERIMENTS} consecutive experiments after the first one from rest (that '
        f'first one, {res.l_first:.4f}, lacks the load-removal transient every later '
        'experiment starts with). The hand-tuned controller is therefore 1.00; a value '
        'below 1 is an improvement over it.',
        '* **Final loss** of a run: its smallest measured non-aborted loss (the paper: the '
        'final controller is "the one generating the smallest loss"). This minimum over '
        'noisy measurements is biased low; the re-measured loss of the same controller is '
        'reported beside it.',
        f'* **Satisfactory** (Table II): final loss <= {st.threshold:g}, i.e. at least '
        f'{100 * (1 - st.threshold):.0f} % better than the hand-tuned start. The paper does '
        'not give its threshold; its tables suggest a level near 0.9 on this scale: a cell '
        'with an average final loss of 0.91 has 92 % satisfactory runs (with a level of 0.8, '
        'its 8 % other runs would have to average above 2), and cells averaging 0.97-0.99 '
        'still have 44-64 %. A 10 % improvement is far above the measurement noise (the '
        "hand-tuned start's loss varies by "
        f'{100 * res.l_ref_sem * math.sqrt(S.REF_EXPERIMENTS) / res.l_ref:.2f} % (standard '
        'deviation) from one experiment to the next; tuned high-gain controllers vary more, '
        'see the re-measured losses). `--from DIR --satisfactory X` re-tabulates a study at '
        'another level without new experiments.',
        '* **Table III**: evaluations (experiments) until the first non-aborted loss at or '
        'below the threshold, averaged over the satisfactory runs (as the paper), and the '
        "same in the optimiser's iterations (SPSA: 2 evaluations per iteration; neCGA: "
        'generations, 1 evaluation each plus one per elite replacement). The paper says '
        '"iterations" without saying how it counts them.',
        '* **Intervals** are 95 %: a percentile bootstrap over runs for means and '
        'differences (run indices resampled together across configurations, because they '
        'share seeds) and Wilson intervals for percentages. A verdict needs the interval of '
        'the difference to exclude zero.',
        '',
    ]
    for stat, title, d in STATS:
        L.append(f'## {title}')
        L.append('')
        L += _md_table(st, stat, d)
    L.append(
        'Re-measured loss of the final controllers (mean; the final loss is the minimum '
        'of noisy measurements, this is an independent one):'
    )
    L.append('')
    L += _md_table(st, 'remeasured', 3)
    if any(c.no_final for c in st.cells):
        L.append(
            'Runs in which every experiment was aborted (left out of Table I, not '
            'satisfactory): '
            + ', '.join(f'{c.cell.label}: {c.no_final}' for c in st.cells if c.no_final)
            + '.'
        )
        L.append('')
    for name, rel in figures.items():
        L.append(f'![{name}]({rel})')
        L.append('')
    if st.conclusions:
        L += [
            "## Which of the paper's conclusions hold in simulation",
            '',
            '| # | the paper | its evidence | simulation (95 % intervals) | verdict |',
            '|---|---|---|---|---|',
        ]
        for k, c in enumerate(st.conclusions, 1):
            L.append(f'| {k} | {c.claim} | {c.paper} | {c.ours} | **{c.verdict}** |')
        L.append('')
    us = st.us_per_iteration
    sp_idx = [i for i, c in enumerate(res.cells) if c.algo == 'spsa']
    notes: list[str] = []
    if sp_idx:
        i = sp_idx[0]  # the starts are the same in every SPSA cell
        ok = ~res.ref_aborted[i]
        med = float(np.median(res.ref_loss[i][ok] / res.l_ref)) if ok.any() else math.nan
        small = [st.cells[j].final.value for j in sp_idx if res.cells[j].row == 0]
        notes.append(
            f"* SPSA's random starts: median loss {med:.2f} among the starts that completed "
            f'their experiment; {100 * (1 - ok.mean()):.0f} % of the starts were aborted '
            '(unstable, or tripping the supervisor). With a = a0/5 the steps are small: that '
            f'row ends at an average final loss of {min(small):.2f}-{max(small):.2f} (the '
            'paper: 0.91-0.99).'
        )
        best = min(sp_idx, key=lambda j: (st.cells[j].final.value, j))
        if (res.cells[best].row, res.cells[best].col) != (1, 1):
            notes.append(
                f'* In simulation SPSA does best with {res.cells[best].label}, where the '
                "paper's bench favoured a0 = 0.0183, c0 = 0.03. A plausible reason, not "
                'tested here: the simulated loss is much less noisy than a bench measurement, '
                'and noisy gradient estimates punish large steps.'
            )
    L += [
        '## Reading it',
        '',
        *notes,
        "* The simulation is the paper's motor model with the encoder, measurement noise and "
        "a load step, not the paper's bench: unmodelled friction, cogging and sensor "
        'effects are absent, so absolute values (and the share of aborted experiments) '
        'differ. The pattern is what can be compared.',
        '* Verdicts come from the intervals above; "not significant" means 100 runs per '
        'configuration cannot tell.',
        "* Timing (conclusion on computation) is this machine's Python, not the paper's "
        f'dSPACE board ({PAPER_US_PER_ITERATION["spsa"]:.0f} and '
        f'{PAPER_US_PER_ITERATION["necga"]:.0f} us per iteration there): '
        + (
            f'{us.get("spsa", math.nan):.1f} and {us.get("necga", math.nan):.1f} us here. '
            if us
            else ''
        )
        + 'Either is negligible beside a 1.125 s experiment.',
        '',
    ]
    return '\n'.join(L) + '\n'


# -- output ---------------------------------------------------------------------------------------
def write_outputs(st: StudyStats, out: Path, command: str) -> dict[str, Path]:
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    text = tables_text(st)
    paths['tables'] = out / 'tables.txt'
    paths['tables'].write_text(text)
    paths['tables_csv'] = write_tables_csv(st, out)
    write_starts(st.res, out)
    paths['runs_csv'] = write_runs_csv(st, out)
    figs = {'tables': fig_tables(st), 'convergence': fig_convergence(st)}
    for name, fig in figs.items():
        paths[f'{name}_png'] = out / f'{name}.png'
        fig.savefig(paths[f'{name}_png'], dpi=110)
    paths['md'] = out / 'reproduction.md'
    paths['md'].write_text(reproduction_md(st, command, {k: f'{k}.png' for k in figs}))
    return paths


def _build_parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog='ros2 run im_tuner study',
        description="The paper's configuration study (Tables I-III) offline, on the "
        'numba kernels of the nodes, in a process pool '
        '(docs/reproduction.md).',
    )
    ap.add_argument('--runs', type=int, default=100, help='runs per configuration (default 100)')
    ap.add_argument(
        '--budget', type=int, default=200, help='loss evaluations per run (default 200)'
    )
    ap.add_argument(
        '--algos',
        default=','.join(S.STUDY_ALGOS),
        help='comma-separated: spsa, necga (default both)',
    )
    ap.add_argument(
        '--model',
        choices=('full', 'reduced'),
        default='full',
        help='drive model (default full: voltage-fed with the encoder)',
    )
    ap.add_argument(
        '--jobs',
        type=int_in(1, max_jobs()),
        default=None,
        help='worker processes (default: every core; at most '
        f'{max_jobs()}, 4 per core); results do not depend on it',
    )
    ap.add_argument(
        '--seed', type=int, default=S.DEFAULT_SEED, help=f'study seed (default {S.DEFAULT_SEED})'
    )
    ap.add_argument(
        '--satisfactory',
        type=float,
        default=None,
        help='satisfactory level of the normalised final loss (default '
        f'{S.DEFAULT_SATISFACTORY:g}: 10 %% better than the hand-tuned start)',
    )
    ap.add_argument(
        '--no-remeasure',
        action='store_true',
        help="skip the re-measurement of each run's final controller",
    )
    ap.add_argument(
        '--params',
        metavar='FILE',
        help='tuner parameter file (search box; default the packaged one)',
    )
    ap.add_argument(
        '--drive-config', metavar='FILE', help="drive parameter file (default the paper's motor)"
    )
    ap.add_argument(
        '--out',
        type=Path,
        metavar='DIR',
        help='output directory (default bags/study_<model>_<UTC time>)',
    )
    ap.add_argument(
        '--from',
        dest='source',
        type=Path,
        metavar='DIR',
        help='re-tabulate an existing study (no new experiments; with '
        '--satisfactory); writes into DIR unless --out',
    )
    ap.add_argument('--quiet', action='store_true', help='no progress line')
    return ap


class Progress:
    """Runs done, experiments/s and ETA: an updating line on a terminal, else a line every
    10 %."""

    def __init__(self, total_exp_per_run: int, quiet: bool, stream=sys.stderr) -> None:
        self.per_run, self.quiet, self.stream = total_exp_per_run, quiet, stream
        self.tty = stream.isatty()
        self.last_pct = -1

    def __call__(self, done: int, total: int, elapsed: float) -> None:
        if self.quiet:
            return
        pct = 100 * done // total
        if not self.tty and pct // 10 == self.last_pct // 10 and done != total:
            return
        self.last_pct = pct
        rate = done * self.per_run / elapsed if elapsed > 0 else 0.0
        eta = int(elapsed / done * (total - done)) if done else 0
        fill = 24 * done // total
        text = (
            f'study [{"#" * fill}{"." * (24 - fill)}] {done}/{total} runs  '
            f'{done * self.per_run} experiments  {rate:.0f}/s  ETA {eta // 60}:{eta % 60:02d}'
        )
        if self.tty:
            self.stream.write('\r' + text + ('\n' if done == total else ''))
        else:
            self.stream.write(text + '\n')
        self.stream.flush()


def max_jobs() -> int:
    """Most worker processes accepted: 4 per core (each is a whole Python process)."""
    return 4 * (os.cpu_count() or 1)


def _spec(cli: argparse.Namespace) -> S.StudySpec:
    algos = tuple(a.strip() for a in cli.algos.split(',') if a.strip())
    for a in algos:
        if a not in S.STUDY_ALGOS:
            raise StudyError(
                f'--algos: no study grid for {a!r} (allowed: {", ".join(S.STUDY_ALGOS)})'
            )
    if cli.jobs is not None and cli.jobs < 1:
        raise StudyError(f'--jobs must be >= 1, got {cli.jobs}')
    try:
        spec = S.StudySpec(
            runs=cli.runs,
            budget=cli.budget,
            algos=algos,
            model=cli.model,
            seed=cli.seed,
            satisfactory=float(
                S.DEFAULT_SATISFACTORY if cli.satisfactory is None else cli.satisfactory
            ),
            remeasure=not cli.no_remeasure,
            drive_config=cli.drive_config,
            params_file=cli.params,
        )
    except ValueError as exc:
        raise StudyError(f'--{exc}') from None  # the messages start with the option's name
    try:
        spec.params()
        spec.drive()
    except (TunerParamsError, ValueError) as exc:
        raise StudyError(str(exc)) from None
    return spec


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if args is None else args)
    command = ' '.join(['ros2 run im_tuner study', *(shlex.quote(a) for a in argv)])
    try:
        cli = _build_parser().parse_args(argv)
        if cli.satisfactory is not None and not (
            cli.satisfactory > 0 and math.isfinite(cli.satisfactory)
        ):
            raise StudyError(
                f'--satisfactory must be a normalised loss > 0, got {cli.satisfactory}'
            )
        if cli.source is not None:
            try:
                res = S.load(cli.source)
            except ValueError as exc:
                raise StudyError(str(exc)) from None
            out = cli.out or cli.source
        else:
            spec = _spec(cli)
            stamp = _dt.datetime.now(_dt.UTC).strftime('%Y_%m_%d-%H_%M_%S')
            out = cli.out or Path('bags') / f'study_{spec.model}_{stamp}'
        if out.exists() and not out.is_dir():
            raise StudyError(f'--out {out}: exists and is not a directory')
        if cli.source is None and out.is_dir() and (out / S.META_FILE).exists():
            raise StudyError(
                f'--out {out}: already holds a study (use --from to re-tabulate '
                'it, or another --out)'
            )
        if cli.source is None and out.is_dir() and any(out.iterdir()):
            raise StudyError(
                f'--out {out}: already exists and is not empty; choose a new directory'
            )
        if (
            cli.source is not None
            and cli.out is not None
            and cli.out.is_dir()
            and any(cli.out.iterdir())
            and cli.out.resolve() != cli.source.resolve()
        ):
            raise StudyError(
                f'--out {out}: already exists and is not empty; choose a new directory'
            )
    except (StudyError, UsageError) as exc:
        print(f'error: study: {exc}', file=sys.stderr)
        return EXIT_USAGE
    if cli.source is None:
        per_run = spec.budget + 1 + int(spec.remeasure)
        n = len(spec.cells) * spec.runs
        if not cli.quiet:
            print(
                f'study: {len(spec.cells)} configurations x {spec.runs} runs x {spec.budget} '
                f'evaluations = {n * per_run} experiments ({spec.model} model) on '
                f'{cli.jobs or S.default_jobs()} worker(s) -> {out}',
                file=sys.stderr,
            )
        try:
            res = S.run_study(spec, cli.jobs, Progress(per_run, cli.quiet))
            res.command = command
        except KeyboardInterrupt:
            print('study: interrupted; nothing written', file=sys.stderr)
            return 130
        S.save(res, out)
    st = compute(res, cli.satisfactory)
    paths = write_outputs(st, out, command)
    print(paths['tables'].read_text(), end='')
    print(
        f'study written to {out}/: '
        + ', '.join(p.name for p in paths.values())
        + (', study.npz, study.json, starts/' if cli.source is None else '')
    )
    return 0


if __name__ == '__main__':
    sys.exit(main())
