"""The study over several drives: a summary per method (one configuration, matched by
algorithm and label across the drives) over the drives, and whether the tuner's default
meets its goal (``GOAL``) on each drive; docs/reproduction-family.md shows both.  Pure
(numpy-free arithmetic on the per-drive :class:`~.stats.StudyStats`): every drive's losses
are normalised by its own L_ref, so the drives' values can be averaged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from .drives import FamilyResult
from .spec import DEFAULT_ROW
from .stats import FAST_LEVEL, CellStats, StudyStats, compute

#: The goal for the default: evaluations to the satisfactory level (mean), to
#: FAST_LEVEL (median) and the share reaching it [%], aborted per run, and the re-measured
#: loss's allowed excess over the drive's best row (relative).
GOAL = {
    'evals': 3.0,
    'fast': 25.0,
    'fast_reached': 99.0,
    'aborted_per_run': 1.0,
    'remeasured': 0.02,
}
#: (CellStats attribute, digits, the worst drive is the highest (+1) or the lowest (-1)).
SUMMARY_STATS: tuple[tuple[str, int, int], ...] = (
    ('remeasured', 3, +1),
    ('evals', 1, +1),
    ('fast', 1, +1),
    ('fast_reached', 0, -1),
    ('aborted_per_run', 1, +1),
)


@dataclass
class MethodSummary:
    """One method over the drives: per statistic (mean over drives, worst value, the
    worst drive's name); nan where no drive has a value. ``left_out``: per statistic, the
    drives without a value, each with why ('im7500w-j10: all 5 runs aborted'; 'n=0': no
    run reached it): never dropped from the mean without a word."""

    algo: str
    label: str
    start_kind: str
    mean: dict[str, float]
    worst: dict[str, float]
    worst_drive: dict[str, str]
    left_out: dict[str, list[str]] = field(default_factory=dict)


@dataclass
class GoalCheck:
    """Whether the default's row on one drive meets the goal, and what misses."""

    drive: str
    method: str  #: the default's row ('safe defaults')
    meets: bool
    misses: list[str]


@dataclass
class FamilyStats:
    """A study over drives, tabulated: each drive's stats, the summary, the goal checks."""

    fam: FamilyResult
    threshold: float
    drives: list[tuple[str, StudyStats]]
    methods: list[MethodSummary]
    checks: list[GoalCheck]


def compute_family(fam: FamilyResult, threshold: float | None = None) -> FamilyStats:
    """Every drive's tables (``stats.compute``) and the summary over the drives."""
    drives = [(n, compute(r, threshold)) for n, r in zip(fam.names, fam.results, strict=True)]
    checks = [g for g in (goal_check(n, st) for n, st in drives) if g is not None]
    return FamilyStats(fam, drives[0][1].threshold, drives, summarize(drives), checks)


def summarize(drives: list[tuple[str, StudyStats]]) -> list[MethodSummary]:
    """The summary per method (in the first drive's row order) over ``drives``
    ((name, stats) each)."""
    if not drives:
        return []
    out = []
    for c0 in drives[0][1].cells:
        key = (c0.cell.algo, c0.cell.label)
        rows = [(name, _find(st, key)) for name, st in drives]
        mean: dict[str, float] = {}
        worst: dict[str, float] = {}
        worst_drive: dict[str, str] = {}
        left_out: dict[str, list[str]] = {}
        for stat, _d, sign in SUMMARY_STATS:
            vals = [
                (name, getattr(cs, stat).value)
                for name, cs in rows
                if cs is not None and math.isfinite(getattr(cs, stat).value)
            ]
            left_out[stat] = [
                f'{name}: ' + (f'all {cs.runs} runs aborted' if cs.no_final == cs.runs else 'n=0')
                for name, cs in rows
                if cs is not None and not math.isfinite(getattr(cs, stat).value)
            ]
            if not vals:
                mean[stat], worst[stat], worst_drive[stat] = math.nan, math.nan, ''
                continue
            mean[stat] = sum(v for _n, v in vals) / len(vals)
            name, v = max(vals, key=lambda nv: sign * nv[1])
            worst[stat], worst_drive[stat] = v, name
        out.append(
            MethodSummary(
                c0.cell.algo, c0.cell.label, c0.cell.start_kind, mean, worst, worst_drive, left_out
            )
        )
    return out


def _find(st: StudyStats, key: tuple[str, str]) -> CellStats | None:
    for c in st.cells:
        if (c.cell.algo, c.cell.label) == key:
            return c
    return None


def goal_check(name: str, st: StudyStats) -> GoalCheck | None:
    """Whether the default's row of drive ``name`` meets the goal (None: no such row)."""
    cs = _find(st, DEFAULT_ROW)  # the tuner's default on a drive it knows
    if cs is None:
        return None
    misses: list[str] = []
    thr = st.threshold
    if not cs.evals.value <= GOAL['evals']:
        misses.append(f'mean evaluations to <= {thr:g} {cs.evals.value:.1f} > {GOAL["evals"]:g}')
    if not math.isfinite(cs.fast.value):
        misses.append(f'no run reaches {FAST_LEVEL:g}')
    elif cs.fast.value > GOAL['fast']:
        misses.append(
            f'median evaluations to <= {FAST_LEVEL:g} {cs.fast.value:.1f} > {GOAL["fast"]:g}'
        )
    if not cs.fast_reached.value >= GOAL['fast_reached']:
        misses.append(
            f'{cs.fast_reached.value:.0f} % of runs reach {FAST_LEVEL:g} '
            f'< {GOAL["fast_reached"]:g} %'
        )
    if not cs.aborted_per_run.value <= GOAL['aborted_per_run']:
        misses.append(
            f'{cs.aborted_per_run.value:.2f} aborted per run > {GOAL["aborted_per_run"]:g}'
        )
    limit = st.res.spec.limit_of(cs.cell)
    rows = within_limit_rows(st, limit)
    b = min(rows, key=lambda c: rows[c][0], default=None)
    if b is not None and not (cs.remeasured.value <= (1.0 + GOAL['remeasured']) * rows[b][0]):
        best, (value, n) = st.cells[b], rows[b]
        within = '' if limit is None else f' within the ripple limit {limit:g}'
        runs = '' if n == st.res.spec.runs else f', its {n} runs of {st.res.spec.runs} within it'
        misses.append(
            f're-measured {cs.remeasured.value:.3f} > {100 * GOAL["remeasured"]:g} % above '
            f'the best row{within} ({best.cell.algo} {best.cell.label}: {value:.3f}{runs})'
        )
    return GoalCheck(name, f'{cs.cell.algo} {cs.cell.label}', not misses, misses)


def within_limit_rows(st: StudyStats, limit: float | None) -> dict[int, tuple[float, int]]:
    """Per row (its index in ``st.cells``), its mean re-measured loss over the runs whose
    applied gains keep within the ripple limit ``limit`` (the larger window's rms over
    the start's, ``runs.csv``), and how many runs that is; rows with none left out.
    ``limit`` None: every run of every row (the rows' own means).  The default keeps its
    gains within its limit: a row whose choices do not is no better for a user who asks
    for it."""
    from .stats import per_run, ripple_ratio  # (numpy: the study's arrays)

    out: dict[int, tuple[float, int]] = {}
    rem = per_run(st.res, st.threshold)['remeasured']
    ratio = ripple_ratio(st.res)
    for c, cs in enumerate(st.cells):
        if limit is None:
            if math.isfinite(cs.remeasured.value):
                out[c] = (cs.remeasured.value, st.res.spec.runs)
            continue
        pairs = zip(rem[c], ratio[c], strict=True)
        vals = [float(v) for v, q in pairs if q <= limit and math.isfinite(v)]
        if vals:
            out[c] = (sum(vals) / len(vals), len(vals))
    return out
