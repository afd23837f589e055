"""safe's first step from the drive model: its cost, and the default's goals, on a plant
that may differ from the model, or on the packaged family of drives.

    python research/bench_prior.py MODEL.yaml [PLANT.yaml] [--runs N] [--budget B]
    python research/bench_prior.py --drives NAME,...|all [--realism bench] [--runs N]

MODEL.yaml is the drive file the tuner knows (its nominal model gives the prior); the runs
measure on PLANT.yaml (default: MODEL.yaml), e.g. a copy with another J and Rr, to see
what a wrong model costs (the default experiment and the packaged tuner parameters).
``--drives`` takes packaged drives (``im_tuner.family.drive_setup``: each drive's own
experiment, box and start; the profile ``--realism``), the model being the drive's own.
Prints the prior's cost, then for safe's defaults and the first step from the model,
over the study's run seeds (seed 2005; the study's TuningRun on the offline bench): mean
evaluations to 0.9 L_ref, median evaluations to 0.5 and the share of runs that reach it,
aborted experiments per run, re-measured final loss (normalised by the plant's own
L_ref: the start's mean loss over 100 experiments after the first from rest).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import im_drive_sim  # noqa: F401 (the numeric baseline, set before numpy loads)

# isort: split
import numpy as np

from im_drive_sim.drive_file import load_config
from im_tuner import optim
from im_tuner.offline import OfflineBench
from im_tuner.prior import model_prior
from im_tuner.runlog import Evaluation, MemoryRecord, Remeasurement
from im_tuner.space import TunerParams, load_params
from im_tuner.study.runs import run_seed
from im_tuner.study.spec import DEFAULT_SEED, REF_EXPERIMENTS
from im_tuner.tuning import DEFAULT_RETRIES, TuningRun, run_seeds


def _bench(plant, seed: int, experiment: Any) -> OfflineBench:
    """The offline bench (with the drive's experiment: OfflineBench takes one since the
    family, im_tuner.family)."""
    if experiment is None:
        return OfflineBench(plant, seed)
    return OfflineBench(plant, seed, experiment)  # type: ignore[call-arg]


def _runs(label: str, first, plant, experiment, params: TunerParams, l_ref: float, cli) -> None:
    space = params.space
    e09, e05, ab, rem = [], [], [], []
    for r in range(cli.runs):
        opt_ss, drive_seed = run_seeds(run_seed(DEFAULT_SEED, r))
        opt = optim.make_optimizer('safe', space.dim, opt_ss, space.start_u, first=first)
        tuning = TuningRun(
            MemoryRecord(),
            space,
            opt,
            budget=cli.budget,
            satisfactory_loss=params.satisfactory_loss,
            remeasure=1,
            retries=DEFAULT_RETRIES,
            reference=True,
        )
        assert tuning.run(_bench(plant, drive_seed, experiment)) == 'done'
        ev = [x for x in tuning.records if isinstance(x, Evaluation)]
        best = np.minimum.accumulate([np.inf if x.aborted else x.loss / l_ref for x in ev])
        for out, level in ((e09, 0.9), (e05, 0.5)):
            hit = np.flatnonzero(best <= level)
            out.append(hit[0] + 1.0 if hit.size else np.nan)
        ab.append(sum(x.aborted for x in ev))
        rm = [x for x in tuning.records if isinstance(x, Remeasurement)]
        rem.append(rm[0].loss / l_ref if rm else np.nan)
    e09a, e05a = np.array(e09), np.array(e05)
    reached = ~np.isnan(e05a)
    med = np.median(e05a[reached]) if reached.any() else np.nan
    print(
        f'  {label:32s} to 0.9: mean {np.nanmean(e09a):.2f} ({np.mean(~np.isnan(e09a)):.0%})'
        f'  to 0.5: median {med:.1f} ({np.mean(reached):.0%})'
        f'  aborted/run {np.mean(ab):.2f}  re-measured {np.nanmean(rem):.4f}',
        flush=True,
    )


def _measure(name: str, model, plant, experiment: Any, params: TunerParams, cli) -> None:
    t0 = time.perf_counter()
    prior = model_prior(model, params.space, experiment)
    t1 = time.perf_counter()
    model_prior(model, params.space, experiment)
    t2 = time.perf_counter()
    bench = _bench(plant, plant.seed, experiment)
    start = params.space.to_gains(params.space.start_u)
    bench.measure(start)  # the first from rest
    l_ref = float(np.mean([bench.measure(start).loss for _ in range(REF_EXPERIMENTS)]))
    print(f'{name}: L_ref {l_ref:.6g}; prior {prior}')
    print(f'  prior cost: {t1 - t0:.2f} s, cached {t2 - t1:.4f} s', flush=True)
    _runs('defaults', None, plant, experiment, params, l_ref, cli)
    if prior is not None:
        _runs('first step from the drive model', prior.u, plant, experiment, params, l_ref, cli)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or '').splitlines()[0])
    ap.add_argument('model', nargs='?')
    ap.add_argument('plant', nargs='?')
    ap.add_argument('--drives', help="packaged drives (comma-separated, or 'all')")
    ap.add_argument('--realism', default='bench', choices=('ideal', 'bench'))
    ap.add_argument('--runs', type=int, default=30)
    ap.add_argument('--budget', type=int, default=200)
    cli = ap.parse_args(argv)
    if (cli.drives is None) == (cli.model is None):
        ap.error('give MODEL.yaml [PLANT.yaml] or --drives')
    if cli.drives is None:
        model = load_config(cli.model)
        plant = load_config(cli.plant or cli.model)
        _measure(cli.plant or cli.model, model, plant, None, load_params(None), cli)
        return 0
    from im_tuner.family import DRIVE_NAMES, drive_setup  # (the packaged family)

    for name in DRIVE_NAMES if cli.drives == 'all' else cli.drives.split(','):
        s = drive_setup(name, realism=cli.realism)
        _measure(name, s.drive, s.drive, s.experiment, s.params, cli)
    return 0


if __name__ == '__main__':
    sys.exit(main())
