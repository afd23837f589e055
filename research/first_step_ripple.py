"""Is the first step's predicted ripple what the plant measures? (im_tuner.prior, step 4)

For run R of the study's default row (safe, first step from the identified drive) on a
told drive and a plant: the first step with the ripple limit 1.5 (``identified_prior``),
its predicted standstill rms over the start's (``Prior.ripple_ratio``), and what the
plant measures in twelve experiments of it (every other one after the start's, so that
they begin from different rest positions): its loss and mean and largest rms over the
start's (mean of four), per window; the error is the prediction over the louder
window's measured mean, less 1.

    python research/first_step_ripple.py --drives paper_750w,im3700w [--mismatch 'J=x2']
        [--realism bench] [--runs 0,1,2]
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import im_drive_sim  # noqa: F401 (the numeric baseline, set before numpy loads)

# isort: split
import numpy as np

from im_tuner import first_step as FS, prior as P
from im_tuner.offline import OfflineBench
from im_tuner.study import runs as R
from im_tuner.study.plant import parse_mismatch
from im_tuner.study.spec import StudySpec


def _identified(spec: StudySpec, run: int) -> tuple[Any, ...] | None:
    """(told drive, space, experiment, identification) of run ``run`` of the default row."""
    cell = next(i for i, c in enumerate(spec.cells) if c.first == 'identify')
    calls: list[Any] = []
    orig = FS.identified_prior
    FS.identified_prior = lambda *args: calls.append(args)
    try:
        R.run_one(spec, cell, run)  # the run's start: its two experiments identify the drive
    finally:
        FS.identified_prior = orig
    return tuple(calls[0][:4]) if calls else None  # (none: the start aborted, nothing identified)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--drives', default='im750w-j1')
    ap.add_argument('--mismatch', default='')
    ap.add_argument('--realism', default='bench')
    ap.add_argument('--runs', default='0')
    a = ap.parse_args()
    runs = [int(x) for x in a.runs.split(',')]
    print(
        '| drive | run | predicted | plant, mean (move, load) | largest | plant loss / start '
        '| error | offline experiments, s |'
    )
    print('|---|---|---|---|---|---|---|---|')
    for drive in a.drives.split(','):
        spec = StudySpec(
            runs=max(runs) + 1, budget=3, algos=('safe',), drives=(drive,), full_grid=False,
            mismatch=parse_mismatch(a.mismatch) if a.mismatch else (), realism=a.realism,
        )  # fmt: skip
        plant, _params, experiment = spec.loaded()
        for run in runs:
            got = _identified(spec, run)
            if got is None:
                print(f'| {drive} | {run} | the start aborts: nothing identified | | | | | |')
                continue
            d, space, exp, idf = got
            t0 = time.perf_counter()
            pr = P.identified_prior(d, space, exp, idf, 1.5)
            dt = time.perf_counter() - t0
            if pr is None or pr.ripple_ratio is None:
                print(f'| {drive} | {run} | no first step | | | | | {dt:.1f} |', flush=True)
                continue
            pl = OfflineBench(plant, run, experiment)
            g0, g1 = space.to_gains(space.start_u), space.to_gains(np.array(pr.u))
            pl.measure(g0)  # from rest
            m0 = [pl.measure(g0) for _ in range(4)]
            ms = []
            for i in range(12):
                if i % 2 == 0:
                    pl.measure(g0)
                ms.append(pl.measure(g1))
            r0 = np.mean([(m.ripple[0], m.ripple[2]) for m in m0], axis=0)
            r = np.array([(m.ripple[0], m.ripple[2]) for m in ms]) / r0
            loss = np.mean([m.loss for m in ms]) / np.mean([m.loss for m in m0])
            err = pr.ripple_ratio / r.mean(axis=0).max() - 1.0
            print(
                f'| {drive} | {run} | {pr.ripple_ratio:.2f} | {r[:, 0].mean():.2f}, '
                f'{r[:, 1].mean():.2f} | {r[:, 0].max():.2f}, {r[:, 1].max():.2f} '
                f'| {loss:.3f} | {err:+.0%} | {pr.experiments}, {dt:.1f} |',
                flush=True,
            )


if __name__ == '__main__':
    main()
