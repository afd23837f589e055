"""The study's default row (safe, first step from the identified drive) with changed safe
options, outside the study's grid: the mean re-measured loss of its runs, not normalised
(compare rows of the same drive and plant: the same seeds, the same L_ref).

    python research/default_row_options.py im750w-j1 - '{"remeasure_every": 5}'
    python research/default_row_options.py im7500w-j10 'J=x0.5' -

Arguments: a packaged drive, a ``--plant-mismatch`` text or ``-``, a JSON object of safe
options or ``-`` (the defaults), and optionally the number of runs (10). An upper-case key
sets that class constant of ``SAFE`` instead (``'{"IDENTIFIED_SIGMA": 0.03}'``).
"""

import im_drive_sim  # noqa: F401, I001  (the numeric baseline, before numpy is imported)

import json
import sys
import time

import numpy as np

from im_tuner.optim.safe import SAFE
from im_tuner.study import cli as C
from im_tuner.study import spec as S
from im_tuner.study.runs import run_one

DEFAULT = 'first step from the identified drive'


def main(argv: list[str]) -> None:
    drive, mismatch, options = argv[:3]
    runs = int(argv[3]) if len(argv) > 3 else 10
    given = json.loads(options) if options != '-' else {}
    for key in [k for k in given if k.isupper()]:
        setattr(SAFE, key, given.pop(key))
    extra = tuple(given.items())
    grid = [
        (label, (('first', 'identify'), *extra) if label == DEFAULT else opts)
        for label, opts in S.EXTRA_GRIDS['safe']
    ]
    S.EXTRA_GRIDS['safe'] = tuple(grid)
    args = [
        '--drives',
        drive,
        '--algos',
        'safe',
        '--runs',
        str(runs),
        '--budget',
        '200',
        '--realism',
        'bench',
    ]
    if mismatch != '-':
        args += ['--plant-mismatch', mismatch]
    spec = C._spec(C._build_parser().parse_args(args)).for_drive(drive)
    cell = next(i for i, c in enumerate(spec.cells) if c.label == DEFAULT)
    t0 = time.time()
    results = [run_one(spec, cell, r) for r in range(runs)]
    rem = np.mean([r.remeasured for r in results])
    aborted = sum(int(r.aborted.sum()) for r in results)
    print(
        f'{drive} {mismatch} {options}: re-measured {rem:.4f} (mean of {runs} runs, '
        f'not normalised), {aborted} aborted, {time.time() - t0:.0f} s'
    )


if __name__ == '__main__':
    main(sys.argv[1:])
