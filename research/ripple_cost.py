"""What the standstill-ripple limit costs the default, run by run.

The family study's default row (``safe``, first step from the identified drive) on each
drive's own ``bench`` plant, with the tuner's default ripple limit and with the limit off:
the same runs (a run's seeds depend only on its index, ``study.runs.run_seed``, so runs
``--first`` .. ``--first + --runs - 1`` are those of ``study --runs N`` for any N above
them), measured by the study's own ``study.runs.run_one``.  Per drive: the mean
re-measured loss over L_ref (the study's column: with the limit, the loss of the gains
the run leaves applied, ``study.runs.applied_loss``), the change with the limit, its
paired 95 % bootstrap interval (``scipy.stats.bootstrap``, BCa, on the runs' pairs:
the ratio of the two means minus 1), the largest single run's change, and how many
choices are above 1.5x the start's standstill rms; L_ref is the study's
(``study.runs.reference_loss``).  Why not ``study`` itself: it runs
every row of ``--algos safe`` (three), this one row, twice as fast with the limit off.

    python research/ripple_cost.py --drives im750w-j1,im7500w-j10 --runs 25 --first 25
        [--jobs 2] [--budget 200] [--json OUT]

The nine drives at 50 runs: 23 min on 2 cores (2026-11-29).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any

import im_drive_sim  # noqa: F401 (the numeric baseline, set before numpy loads)

# isort: split
import numpy as np
from scipy import stats

from im_controller.config import Gains
from im_drive_sim.family import DRIVE_NAMES
from im_tuner.study import runs as R
from im_tuner.study.spec import DEFAULT_ROW, StudySpec

#: the choice counted as loud: its rms over the start's above this in a window
LOUD = 1.5


def _spec(drive: str, budget: int, runs: int, limit: bool) -> StudySpec:
    return StudySpec(
        runs=runs,
        budget=budget,
        algos=('safe',),
        drives=(drive,),
        realism='bench',
        full_grid=False,
        ripple_limit='default' if limit else None,
    ).for_drive(drive)


def _one(task: tuple[str, int, int, int, bool]) -> tuple[str, bool, int, float, float]:
    """(drive, limited, run, re-measured loss, the choice's largest rms over the start's)
    of one run."""
    drive, budget, runs, r, limit = task
    spec = _spec(drive, budget, runs, limit)
    cell = next(i for i, c in enumerate(spec.cells) if (c.algo, c.label) == DEFAULT_ROW)
    res = R.run_one(spec, cell, r, *spec.loaded())
    s_move, s_load, a_move, a_load = res.ripple
    loud = max(a_move / s_move, a_load / s_load)
    return drive, limit, r, res.remeasured, loud


def _ratio(off: np.ndarray, on: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.mean(on, axis=axis) / np.mean(off, axis=axis) - 1.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--drives', default=','.join(DRIVE_NAMES))
    ap.add_argument('--runs', type=int, default=25)
    ap.add_argument('--first', type=int, default=0, help='the first run index')
    ap.add_argument('--budget', type=int, default=200)
    ap.add_argument('--jobs', type=int, default=2)
    ap.add_argument('--json', help='write every run pair here')
    a = ap.parse_args()
    drives = [d.strip() for d in a.drives.split(',') if d.strip()]
    total = a.first + a.runs
    tasks = [
        (d, a.budget, total, r, lim)
        for d in drives
        for lim in (False, True)
        for r in range(a.first, total)
    ]
    done = []
    with ProcessPoolExecutor(a.jobs) as pool:
        for k, res in enumerate(as_completed([pool.submit(_one, t) for t in tasks])):
            done.append(res.result())
            if (k + 1) % 10 == 0 or k + 1 == len(tasks):
                print(f'ripple_cost: {k + 1}/{len(tasks)} runs', file=sys.stderr, flush=True)
    l_ref = {}  # the study's L_ref: the start's mean loss on the plant (study.runs)
    for d in drives:
        spec = _spec(d, a.budget, total, True)
        drive, params, experiment = spec.loaded()
        start = Gains(*params.space.start)
        l_ref[d] = R.reference_loss(drive, experiment=experiment, start=start)[0]
    by: dict[tuple[str, bool], dict[int, tuple[float, float]]] = {}
    for d, lim, r, loss, loud in done:
        by.setdefault((d, lim), {})[r] = (loss / l_ref[d], loud)
    print(
        f'runs {a.first}-{total - 1}, {a.budget} evaluations, bench, seed {StudySpec.seed}\n'
        '| drive (bench) | re-measured: off -> limit | change | 95 % interval '
        '| largest run change | choices > 1.5x: off -> limit |\n|---|---|---|---|---|---|'
    )
    out: dict[str, Any] = {}
    for d in drives:
        runs = sorted(by[(d, False)])
        off = np.array([by[(d, False)][r][0] for r in runs])
        on = np.array([by[(d, True)][r][0] for r in runs])
        lo = hi = math.nan  # (one run: no interval)
        if np.array_equal(off, on):
            lo = hi = 0.0  # (the limit changed no run: nothing to resample)
        elif len(runs) > 1:
            ci = stats.bootstrap(
                (off, on), _ratio, paired=True, vectorized=True, n_resamples=20000,
                random_state=1, method='BCa',
            ).confidence_interval  # fmt: skip
            lo, hi = float(ci.low), float(ci.high)
        loud = [sum(by[(d, lim)][r][1] > LOUD for r in runs) for lim in (False, True)]
        ch = 100 * float(_ratio(off, on))
        print(
            f'| {d} | {off.mean():.3f} -> {on.mean():.3f} | {ch:+.1f} % | '
            f'[{100 * lo:+.1f}, {100 * hi:+.1f}] % | '
            f'{100 * float(np.max(on / off - 1)):+.0f} % | {loud[0]} -> {loud[1]} |'
        )
        out[d] = {
            'runs': runs,
            'off': off.tolist(),
            'limited': on.tolist(),
            'change': ch / 100,
            'ci95': [lo, hi],
        }
    if a.json:
        with open(a.json, 'w') as f:
            json.dump(out, f, indent=1)


if __name__ == '__main__':
    main()
