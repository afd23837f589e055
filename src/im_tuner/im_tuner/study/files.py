"""The study's files: runs.csv, tables.csv and a tuner command per run (starts/)."""

from __future__ import annotations

import csv
import math
import shlex
from pathlib import Path

import yaml

from im_controller.config import GAIN_NAMES

from .. import optim
from ..family import DEFAULT_DRIVE
from ..identify import FIGURES
from .results import StudyResult
from .spec import REFERENCE_ALGOS
from .stats import StudyStats, per_run
from .text import STATS


# -- files ----------------------------------------------------------------------------------------
def tuner_command(res: StudyResult, c: int, r: int, out: Path) -> str:
    """The tuner command that repeats run ``r`` of cell ``c`` on the ROS bench (its losses
    equal the study's bit for bit: test/test_study.py)."""
    cell, sp = res.cells[c], res.spec
    if (
        cell.algo in REFERENCE_ALGOS
        or sp.realism
        or (sp.drives and sp.drives[0] != DEFAULT_DRIVE)
        or sp.split
    ):
        # an outside reference row, a drive/profile the tuner has no option for yet, or a
        # plant that is not the told drive (the ROS bench would need a drive file of it)
        return ''
    args = ['ros2', 'run', 'im_tuner', 'tuner', '--algo', cell.algo]
    for k, v in cell.opts.items():
        args += ['--opt', f'{k}={v if isinstance(v, str) else repr(v)}']
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
    if cell.start_kind == 'random':
        args += ['--params', str(out / 'starts' / f'run_{r:03d}.yaml')]
    elif sp.params_file:
        args += ['--params', sp.params_file]
    policies = optim.POLICIES.get(cell.algo, {})
    if cell.start_kind == 'none' and 'start' in policies:
        args += ['--opt', 'start=none']
    if 'first' in policies:  # said either way: the tuner's default depends on its bench
        args += ['--opt', f'first={cell.first}']
    if sp.drive_config:
        args += ['--drive-config', sp.drive_config]
    if sp.ripple_limit != 'default':  # (the default: the tuner's own for the algorithm)
        limit = sp.limit_of(cell)
        args += ['--ripple-limit', 'off' if limit is None else repr(limit)]

    return ' '.join(shlex.quote(a) for a in args)


def write_starts(res: StudyResult, out: Path) -> None:
    """starts/run_<r>.yaml: the tuner parameter file of run r of the random-start cells
    (box + its start; every such cell's run r has the same start)."""
    rand = [i for i, cell in enumerate(res.cells) if cell.start_kind == 'random']
    if not rand:
        return
    params = res.spec.params()
    c = rand[0]
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
            f'# run {r} of the study in {out.name}: random start (run seed '
            f'{int(res.run_seed[r])})\n'
            + yaml.safe_dump(
                {'search_box': box, 'satisfactory_loss': params.satisfactory_loss}, sort_keys=False
            )
        )
        (d / f'run_{r:03d}.yaml').write_text(text)


#: The standstill ripple of isq* [A] of the start and of the gains the run leaves applied,
#: after the move and after the load: rms (what the ripple limit bounds), then peak to peak
#: (``StudyResult.ripple``, ``ripple_pp``).
RIPPLE_COLUMNS = tuple(
    f'{who}_{measure}_after_{when}'
    for measure in ('rms', 'pp')
    for who in ('start', 'applied')
    for when in ('move', 'load')
)

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
    *RIPPLE_COLUMNS,
    *(f'identified_{f}' for f in FIGURES),
    'tuner_command',
)


def _num(x: float) -> str:
    """A number of runs.csv: exact (repr), empty when not measured (nan)."""
    return '' if math.isnan(x) else repr(float(x))


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
                        *(_num(x) for x in (*res.ripple[c, r], *res.ripple_pp[c, r])),
                        *(_num(x) for x in res.identified[c, r]),
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
        extra = ('remeasured', 'fast', 'fast_reached', 'ripple_ratio', 'ripple_over')
        for stat in (*(s[0] for s in STATS), *extra, 'ripple_pp_ratio', 'aborted_per_run'):
            for c in st.cells:
                iv = getattr(c, stat)
                p = c.paper(stat)
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
