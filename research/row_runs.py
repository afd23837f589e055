"""One row of the study on one drive, run by run: each run's re-measured loss (not
normalised), aborted experiments and the applied gains' standstill ripple over the start's
(the larger window), the evaluations to 0.9 of the run's reference experiment, and the
mean with its standard error. Runs are seeded by their index,
so runs ``FIRST``..``RUNS-1`` continue a row measured before.

    python research/row_runs.py im750w-j1 - safe 'first step from the identified' 30
    python research/row_runs.py im750w-j1 - cmaes sigma0 30
    python research/row_runs.py im7500w-j10 'J=x0.5' safe 'first step from the drive' 30 10

Arguments: a packaged drive, a ``--plant-mismatch`` text or ``-``, the algorithm, the start
of the row's label, the number of runs, and optionally the first run (0). Budget 200,
realism ``bench``, as the mismatch grid.
"""

import im_drive_sim  # noqa: F401, I001  (the numeric baseline, before numpy is imported)

import sys
import time

import numpy as np

from im_tuner.study import cli as C
from im_tuner.study.runs import run_one


def main(argv: list[str]) -> None:
    drive, mismatch, algo, label, runs = argv[0], argv[1], argv[2], argv[3], int(argv[4])
    first = int(argv[5]) if len(argv) > 5 else 0
    args = ['--drives', drive, '--algos', algo, '--runs', str(runs), '--budget', '200']
    args += ['--realism', 'bench']
    if mismatch != '-':
        args += ['--plant-mismatch', mismatch]
    spec = C._spec(C._build_parser().parse_args(args)).for_drive(drive)
    cell = next(i for i, c in enumerate(spec.cells) if c.algo == algo and c.label.startswith(label))
    t0 = time.time()
    res = [run_one(spec, cell, r) for r in range(first, runs)]
    x = np.array([r.remeasured for r in res])
    ripple = [max(r.ripple[2] / r.ripple[0], r.ripple[3] / r.ripple[1]) for r in res]
    print(
        f'{drive} {mismatch} {algo} [{spec.cells[cell].label}] runs {first}-{runs - 1}: '
        f'mean {x.mean():.4f} sd {x.std(ddof=1):.4f} se {x.std(ddof=1) / np.sqrt(len(x)):.4f}, '
        f'{time.time() - t0:.0f} s'
    )
    print('re-measured ' + ' '.join(f'{v:.4f}' for v in x))
    print('aborted ' + ' '.join(str(int(r.aborted.sum())) for r in res))
    print('ripple ' + ' '.join(f'{v:.2f}' for v in ripple))
    to = [_to_09(r) for r in res]
    print(f'evaluations to 0.9 of the reference ({np.mean(to):.2f}) ' + ' '.join(map(str, to)))


def _to_09(r: object) -> int:
    """The first evaluation (from 1) whose loss is within 0.9 of the run's reference
    experiment's, not aborted (budget + 1: none)."""
    ok = (r.losses <= 0.9 * r.ref_loss) & ~r.aborted
    return int(np.argmax(ok)) + 1 if ok.any() else len(r.losses) + 1


if __name__ == '__main__':
    main(sys.argv[1:])
