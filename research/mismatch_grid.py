"""The mismatch grid: the default (safe, first step from the identified
drive) beside safe from the drive file's model, blind safe, CMA-ES and Py-BOBYQA, on
plants that are not the told drive (``study --plant-mismatch``), per told drive.

    python research/mismatch_grid.py --out bags/mismatch [--runs 8 --budget 60]
        [--drives im750w-j1,im7500w-j10] [--cases exact,J=x0.5,...]

Runs one ``ros2 run im_tuner study`` per (drive, case) into OUT/<drive>/<case>/ (a case
already done is read, not re-run), then prints one markdown table: per case and row, the
mean evaluations to 0.9 of the plant's L_ref, aborted experiments per run and the mean
re-measured final loss (the study's tables.csv: ``evals``, ``aborted_per_run``,
``remeasured``), the best re-measured row of the case in bold.
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
import time
from pathlib import Path

#: the mismatches: J alone x0.5-x2.5, and all together
CASES: dict[str, str] = {
    'exact': '',
    'J=x0.5': 'J=x0.5',
    'J=x1.5': 'J=x1.5',
    'J=x2': 'J=x2',
    'J=x2.5': 'J=x2.5',
    'all': 'J=x1.5 Rr=x1.3 Lm=x0.85 coulomb=2% delay=2',
}
ROWS = (
    ('safe', 'first step from the identified drive', 'default (safe, identified)'),
    ('safe', 'first step from the drive model', "safe, the file's model"),
    ('safe', 'defaults', 'blind safe'),
    ('cmaes', 'sigma0=0.1', 'CMA-ES sigma0 0.1'),
    ('bobyqa', 'rhobeg=0.08', 'Py-BOBYQA'),
)


def _study(drive: str, case: str, out: Path, runs: int, budget: int) -> float:
    cmd = [
        str(Path(sys.prefix) / 'bin' / 'ros2'), 'run', 'im_tuner', 'study',
        '--drives', drive, '--algos', 'safe,cmaes,bobyqa', '--runs', str(runs),
        '--budget', str(budget), '--jobs', '2', '--quiet', '--out', str(out),
    ]  # fmt: skip
    if CASES[case]:
        cmd += ['--plant-mismatch', CASES[case]]
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    with (out.parent / f'{out.name}.log').open('w') as log:  # (the study's tables on stdout)
        subprocess.run(cmd, check=True, stdout=log)
    return time.perf_counter() - t0


def _read(path: Path) -> dict[tuple[str, str, str], float]:
    with path.open() as f:
        return {
            (r['statistic'], r['algo'], r['config']): float(r['value'])
            for r in csv.DictReader(f)
            if r['statistic'] in ('evals', 'aborted_per_run', 'remeasured')
        }


def grid_arguments(ap: argparse.ArgumentParser) -> None:
    """The grid's options (this script's and ripple_grid.py's)."""
    ap.add_argument('--out', type=Path, required=True)
    ap.add_argument('--runs', type=int, default=8)
    ap.add_argument('--budget', type=int, default=60)
    ap.add_argument('--drives', default='im750w-j1,im7500w-j10')
    ap.add_argument('--cases', default=','.join(CASES))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    grid_arguments(ap)
    a = ap.parse_args()
    print('| told drive | plant | row | to 0.9, mean | aborted / run | re-measured |')
    print('|---|---|---|---|---|---|')
    for drive in a.drives.split(','):
        for case in a.cases.split(','):
            d = a.out / drive / case.replace('=', '')
            tables = d / drive / 'tables.csv'
            took = ''
            if not tables.exists():
                took = f' ({_study(drive, case, d, a.runs, a.budget):.0f} s)'
            v = _read(tables)
            rem = {lab: v.get(('remeasured', al, cfg)) for al, cfg, lab in ROWS}
            best = min(x for x in rem.values() if x is not None)
            for al, cfg, lab in ROWS:
                r = rem[lab]
                rtext = '-' if r is None else (f'**{r:.3f}**' if r == best else f'{r:.3f}')
                print(
                    f'| {drive} | {case}{took} | {lab} | {v[("evals", al, cfg)]:.2f} | '
                    f'{v[("aborted_per_run", al, cfg)]:.2f} | {rtext} |',
                    flush=True,
                )
                took = ''


if __name__ == '__main__':
    main()
