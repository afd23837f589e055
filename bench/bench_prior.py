"""safe's first step from the drive model: its cost, and the goals of issue 29 on a plant
that differs from the model.

    python bench/bench_prior.py MODEL.yaml [PLANT.yaml] [--runs N] [--budget B]

MODEL.yaml is the drive file the tuner knows (its nominal model gives the prior); the runs
measure on PLANT.yaml (default: MODEL.yaml), e.g. a copy with another J and Rr, to see
what a wrong model costs.  Prints the prior's cost (first call and cached), then for
safe's defaults and the 'first step from the drive model' row, over the same run seeds
as the study (seed 2005): mean evaluations to 0.9 L_ref, median evaluations to 0.5 and
the share of runs that reach it, aborted experiments per run, re-measured final loss
(all normalised by the plant's own L_ref).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from im_drive_sim.params import load_config
from im_tuner.prior import model_prior
from im_tuner.study.runs import StudySpec, reference_loss, run_one


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('model')
    ap.add_argument('plant', nargs='?')
    ap.add_argument('--runs', type=int, default=30)
    ap.add_argument('--budget', type=int, default=200)
    cli = ap.parse_args(argv)
    spec = StudySpec(runs=cli.runs, budget=cli.budget, algos=('safe',), drive_config=cli.model)
    plant = load_config(cli.plant or cli.model, overrides={'model': spec.model})
    params = spec.params()
    t0 = time.perf_counter()
    prior = model_prior(spec.drive(), params.space)
    t1 = time.perf_counter()
    model_prior(spec.drive(), params.space)
    t2 = time.perf_counter()
    print(f'prior: {prior}')
    print(f'prior cost: first {t1 - t0:.2f} s (numba kernels loaded), cached {t2 - t1:.4f} s')
    l_ref = reference_loss(plant)[0]
    print(f'plant {cli.plant or cli.model}: L_ref {l_ref:.6g}')
    for c, cell in enumerate(spec.cells):
        if cell.label not in ('defaults', 'first step from the drive model'):
            continue
        e09, e05, ab, rem = [], [], [], []
        for r in range(cli.runs):
            res = run_one(spec, c, r, plant, params)
            ln = np.where(res.aborted, np.inf, res.losses / l_ref)
            best = np.minimum.accumulate(ln)
            for out, level in ((e09, 0.9), (e05, 0.5)):
                hit = np.flatnonzero(best <= level)
                out.append(hit[0] + 1.0 if hit.size else np.nan)
            ab.append(res.aborted.sum())
            rem.append(res.remeasured / l_ref)
        e09a, e05a = np.array(e09), np.array(e05)
        print(
            f'{cell.label:32s} to 0.9: mean {np.nanmean(e09a):.2f} ({np.mean(~np.isnan(e09a)):.0%})'
            f'  to 0.5: median {np.nanmedian(e05a):.1f} ({np.mean(~np.isnan(e05a)):.0%})'
            f'  aborted/run {np.mean(ab):.2f}  re-measured {np.nanmean(rem):.4f}'
        )
    return 0


if __name__ == '__main__':
    sys.exit(main())
