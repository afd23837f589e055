"""The study's tables as text (tables.txt, also printed)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from . import spec as S
from .plant import plant_line, plants_line
from .stats import EXPERIMENT_S, FAST_LEVEL, CellStats, StudyStats, _fmt_iv

if TYPE_CHECKING:
    from .summary import FamilyStats

ALGO_NAME = {
    'spsa': 'SPSA',
    'necga': 'neCGA',
    'cga': 'cGA',
    'pecga': 'peCGA',
    'rcga': 'rcGA',
    'cmaes': 'CMA-ES',
    'tpe': 'TPE',
    'safe': 'safe',
    'bobyqa': 'Py-BOBYQA',
}
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


def no_intervals_note(runs: int) -> str:
    """Why a study of too few runs shows its means without intervals."""
    return (
        f'{runs} run per configuration: means without intervals (a bootstrap interval '
        f'needs >= {S.MIN_RUNS_FOR_INTERVALS} runs); percentages with Wilson intervals'
    )


# -- text -----------------------------------------------------------------------------------------
def _paper(c: CellStats, stat: str, d: int, form: str = '{}') -> str:
    """The paper's value of ``stat`` in ``c``'s cell, put in ``form`` ('': none)."""
    v = c.paper(stat)
    return '' if v is None else form.format(f'{v:.2f}' if d == 3 else f'{v:.0f}')


def _grids(st: StudyStats) -> list[tuple[str, list[str], list[tuple[str, list[CellStats]]]]]:
    """Tables I-III's grids: (algo, column labels, [(row label, the row's cells)]) per
    algorithm of the paper (SPSA: a down, c across; neCGA: n across)."""
    out = []
    for algo in st.res.spec.algos:
        if algo not in S.PAPER_ALGOS or not st.res.spec.full_grid:
            continue
        cs = [c for c in st.cells if c.cell.algo == algo]
        top = [c.cell.label.split() for c in cs if c.cell.row == 0]
        if algo == 'spsa':
            cols = [words[1] for words in top]
            labels = [c.cell.label.split()[0] for c in cs if c.cell.col == 0]
        else:
            cols, labels = [words[0] for words in top], ['eta=n/2']
        rows = [(rl, [c for c in cs if c.cell.row == i]) for i, rl in enumerate(labels)]
        out.append((algo, cols, rows))
    return out


#: How the comparison names a cell's start kind.
START_TEXT = {'random': 'random start', 'hand': 'hand-tuned start', 'none': 'no start'}
#: The comparison beyond the paper: (header, CellStats attribute, digits).
COMPARISON = (
    ('final (min measured)', 'final', 3),
    ('re-measured', 'remeasured', 3),
    ('evaluations to <= {thr:g}, mean', 'evals', 1),
    ('to <= {fast:g}, median', 'fast', 1),
    ('runs reaching {fast:g} [%]', 'fast_reached', 0),
    ('aborted per run', 'aborted_per_run', 1),
    ('ripple / start, median', 'ripple_ratio', 2),
    ('peak-to-peak / start', 'ripple_pp_ratio', 2),
)


def comparison_rows(st: StudyStats) -> tuple[list[str], list[list[str]]]:
    """The comparison of every configuration: header and one row per cell,
    each value with its 95 % interval."""
    head = ['method (configuration, start)'] + [
        h.format(thr=st.threshold, fast=FAST_LEVEL) for h, _a, _d in COMPARISON
    ]
    rows = []
    for c in st.cells:
        label = _method(c.cell.algo, c.cell.label, c.cell.start_kind)
        none = c.no_final == c.runs  # no final controller in any run: say so, not '-'
        rows.append(
            [label]
            + [
                f'all {c.runs} runs aborted (n=0)'
                if none and a in ('final', 'remeasured')
                else _fmt_iv(getattr(c, a), d, '-')
                for _h, a, d in COMPARISON
            ]
        )
    return head, rows


def _aligned(head: list[str], rows: list[list[str]]) -> list[str]:
    w = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]
    return [
        '  ' + '  '.join(f'{x:<{w[i]}}' for i, x in enumerate(r)).rstrip() for r in [head, *rows]
    ]


def comparison_text(st: StudyStats) -> str:
    head, rows = comparison_rows(st)
    L = ['Beyond the paper: every configuration, 95 % intervals (normalised loss)']
    L += _aligned(head, rows)
    return '\n'.join(L) + '\n'


def _method(algo: str, label: str, start_kind: str) -> str:
    """A row's name: algorithm, configuration and start ('sigma0=0.3 random start' says
    it already)."""
    start = START_TEXT[start_kind]
    text = f'{ALGO_NAME.get(algo, algo)} {label}'
    return text if start in label else f'{text} ({start})'


def summary_rows(fs: FamilyStats) -> tuple[list[str], list[list[str]]]:
    """The summary over drives: per method, each statistic's mean over the drives and
    its worst drive."""
    from .summary import SUMMARY_STATS

    names = {a: h for h, a, _d in COMPARISON}
    head = ['method (configuration, start)'] + [
        names[a].format(thr=fs.threshold, fast=FAST_LEVEL) + ': mean over drives (worst)'
        for a, _d, _s in SUMMARY_STATS
    ]
    rows = []
    for m in fs.methods:
        row = [_method(m.algo, m.label, m.start_kind)]
        for a, d, _s in SUMMARY_STATS:
            v, w = m.mean[a], m.worst[a]
            cell = '-' if not math.isfinite(v) else f'{v:.{d}f} ({w:.{d}f} {m.worst_drive[a]})'
            out = m.left_out.get(a)
            if out:  # a drive without a value is named, not averaged away silently
                cell += ('; ' if math.isfinite(v) else ' ') + 'left out: ' + ', '.join(out)
            row.append(cell)
        rows.append(row)
    return head, rows


def goal_lines(fs: FamilyStats) -> list[str]:
    """One line per drive: whether the default meets its goal there (``summary.GOAL``)."""
    return [
        f'{g.drive}: the default ({g.method}) '
        + ('meets the goal' if g.meets else 'misses the goal: ' + '; '.join(g.misses))
        for g in fs.checks
    ]


def family_text(fs: FamilyStats) -> str:
    """Each drive's comparison, then the summary over the drives and the goal lines."""
    sp = fs.fam.spec
    L = [
        f'Study over {len(fs.drives)} drive(s), realism {sp.realism or "of each drive file"}: '
        f'{len(fs.drives[0][1].cells)} configurations x {sp.runs} runs x {sp.budget} '
        f'evaluations per drive, {sp.model} model, seed {sp.seed}; loss normalised per drive '
        'by its hand-tuned start',
        *filter(None, [plants_line([(n, st.res.spec) for n, st in fs.drives])]),
        *([no_intervals_note(sp.runs)] if sp.runs < S.MIN_RUNS_FOR_INTERVALS else []),
        '',
    ]
    for name, st in fs.drives:
        res = st.res
        L.append(
            f'Drive {name}: L_ref = {res.l_ref:.5f} (+- {res.l_ref_sem:.5f}); '
            f'{res.experiments} experiments in {res.wall_s:.1f} s'
        )
        pl = plant_line(res.spec, res.l_ref, res.l_ref_told)
        if pl:
            L.append(pl)
        L.append(comparison_text(st))
    head, rows = summary_rows(fs)
    L.append('Summary over the drives (normalised loss: each drive by its own hand-tuned start)')
    L += _aligned(head, rows)
    L.append('')
    L.append('The default against its goal:')
    L += ['  ' + g for g in goal_lines(fs)] or ['  (the default is not in this study)']
    return '\n'.join(L) + '\n'


def tables_text(st: StudyStats) -> str:
    res = st.res
    sp = res.spec
    L = [
        f'Offline configuration study: {len(res.cells)} configurations x {sp.runs} runs x '
        f'{sp.budget} evaluations, {sp.model} model, seed {sp.seed}',
        f'loss normalised by L_ref = {res.l_ref:.5f} (+- {res.l_ref_sem:.5f}), the hand-tuned '
        f'start over {S.REF_EXPERIMENTS} experiments; satisfactory: final loss <= '
        f'{st.threshold:g}',
        *filter(None, [plant_line(sp, res.l_ref, res.l_ref_told)]),
        'cells: ours mean [95 % interval] | paper',
        *([no_intervals_note(sp.runs)] if sp.runs < S.MIN_RUNS_FOR_INTERVALS else []),
        '',
    ]
    for stat, title, d in STATS if sp.paper_tables else ():
        L.append(title)
        for algo, cols, rows in _grids(st):
            L.append(f'  {ALGO_NAME[algo]:<12}' + ''.join(f'{c:<31}' for c in cols))
            for rl, cs in rows:
                cells = ''.join(
                    f'{_fmt_iv(getattr(c, stat), d, "-") + _paper(c, stat, d, " | {}"):<31}'
                    for c in cs
                )
                L.append(f'  {rl:<12}{cells}'.rstrip())
        L.append('')
    L.append(comparison_text(st))
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
