"""The standstill-ripple limit's price: per told drive and plant case,
the same study twice, with the final choice's ripple limit 1.5 and without
(``study --ripple-limit 1.5`` / ``off``), for the default (safe, first step from the
identified drive) and the paper's SPSA and neCGA at their centre configurations.

    python research/ripple_grid.py --out bags/ripple [--runs 8 --budget 60]
        [--drives im750w-j1,im7500w-j10] [--cases exact,J=x0.5,...]

Runs one ``study`` per (drive, case, limit) into OUT/<drive>/<case>/<limit>/ (a study
already done is read, not re-run), then prints one markdown table: per case and row, the
median over runs of the applied gains' standstill rms of isq* over the start's (the larger
window), the runs above 1.5, the aborted experiments per run and the mean re-measured
final loss (normalised by the plant's L_ref), without and with the limit, and the change
of that loss.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from mismatch_grid import CASES, grid_arguments

ROWS = (
    ('safe', 'first step from the identified drive', 'default (safe, identified)'),
    ('spsa', 'a=0.0183 c=0.03', 'SPSA (paper centre)'),
    ('necga', 'n=25 eta=12', 'neCGA (paper centre)'),
)
LIMITS = ('off', '1.5')


def _study(
    drive: str, case: str, limit: str, out: Path, runs: int, budget: int, algos: str
) -> float:
    cmd = [
        sys.executable, '-m', 'im_tuner.study',
        '--drives', drive, '--algos', algos, '--runs', str(runs),
        '--budget', str(budget), '--jobs', '2', '--quiet', '--out', str(out),
        '--ripple-limit', limit,
    ]  # fmt: skip
    if CASES[case]:
        cmd += ['--plant-mismatch', CASES[case]]
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    with (out.parent / f'{out.name}.log').open('w') as log:
        subprocess.run(cmd, check=True, stdout=log, env=os.environ)
    return time.perf_counter() - t0


def _read(study_dir: Path) -> dict[tuple[str, str, str], float]:
    """(statistic, algo, config) -> value of a study directory, tabulated afresh (a study
    written before a statistic changed is read the same way)."""
    from im_tuner.study.results import load
    from im_tuner.study.stats import compute

    out = {}
    for c in compute(load(study_dir)).cells:
        for k in ('remeasured', 'ripple_ratio', 'ripple_over', 'aborted_per_run'):
            out[(k, c.cell.algo, c.cell.label)] = getattr(c, k).value
    return out


def _n(x: float, fmt: str = '.2f') -> str:
    return '-' if math.isnan(x) else format(x, fmt)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    grid_arguments(ap)
    ap.add_argument('--algos', default='safe,spsa,necga', help="the study's --algos")
    a = ap.parse_args()
    print(
        '| told drive | plant | row | ripple / start (median), off -> 1.5 | runs > 1.5 '
        '| aborted / run | re-measured, off -> 1.5 | change |'
    )
    print('|---|---|---|---|---|---|---|---|')
    for drive in a.drives.split(','):
        for case in a.cases.split(','):
            v, took = {}, []
            for limit in LIMITS:
                d = a.out / drive / case.replace('=', '') / limit
                if not (d / drive / 'study.npz').exists():
                    took.append(f'{_study(drive, case, limit, d, a.runs, a.budget, a.algos):.0f}')
                v[limit] = _read(d / drive)
            when = f' ({" + ".join(took)} s)' if took else ''
            for al, cfg, lab in ROWS:
                if ('remeasured', al, cfg) not in v['off']:
                    continue  # (not in this study's --algos)
                off, on = ({k: v[lim][(k, al, cfg)] for k in ('remeasured', 'ripple_ratio',
                           'ripple_over', 'aborted_per_run')} for lim in LIMITS)  # fmt: skip
                change = 100.0 * (on['remeasured'] / off['remeasured'] - 1.0)
                # (nan: the start's ripple not measured, e.g. its reference aborted)
                n_over = [_n(x['ripple_over'] * a.runs / 100.0, '.0f') for x in (off, on)]
                print(
                    f'| {drive} | {case}{when} | {lab} | {_n(off["ripple_ratio"])} -> '
                    f'{_n(on["ripple_ratio"])} | {n_over[0]} -> {n_over[1]} of {a.runs} | '
                    f'{off["aborted_per_run"]:.1f} -> {on["aborted_per_run"]:.1f} | '
                    f'{off["remeasured"]:.3f} -> {on["remeasured"]:.3f} | {change:+.1f} % |',
                    flush=True,
                )
                when = ''


if __name__ == '__main__':
    main()
