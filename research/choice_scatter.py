"""How much of a study's re-measured loss is the one experiment it re-measures?

The study's ``re-measured`` column is one experiment of each run's final choice.  On the
offline bench a controller's loss depends on where the shaft rests when the experiment
starts (an encoder count, the direction), so that one experiment scatters.  Here, for
the default row (safe, first step from the identified drive) and Py-BOBYQA on a told
drive and a mismatched plant, each run of the study is repeated (the same seeds: the same
records) and its final choice measured ``--repeats`` more times on a fresh bench of the
plant, one experiment with the start's gains before every third (so they start from other
rest positions).  Printed per run and row: the study's re-measured loss and the repeats'
mean, standard deviation, least and largest, all over the run's reference loss.

    python research/choice_scatter.py --drive im7500w-j10 --mismatch J=x0.5 [--runs 8]
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from typing import Any

import im_drive_sim  # noqa: F401 (the numeric baseline, set before numpy loads)

# isort: split
import numpy as np

from im_controller.config import Gains
from im_tuner.offline import OfflineBench
from im_tuner.runlog import Reference
from im_tuner.study import runs as R
from im_tuner.study.plant import parse_mismatch
from im_tuner.study.spec import StudySpec

ROWS = (
    ('first step from the identified drive', 'default (safe, identified)'),
    ('rhobeg=0.08', 'Py-BOBYQA'),
)


def repeated_runs(
    spec: StudySpec, label: str, remeasure: int | None = None
) -> Iterator[tuple[Any, Any]]:
    """The study's runs of row ``label`` repeated in this process (the same seeds: the
    same records and choice): (the run's result, its ``TuningRun``) per run.
    ``remeasure``: the K best re-measured at each run's end (None: the study's own)."""
    kept: list[Any] = []

    class Kept(R.TuningRun):  # the study's own run, its records kept
        def __init__(self, *args: Any, **kw: Any) -> None:
            if remeasure is not None:
                kw = {**kw, 'remeasure': remeasure}
            super().__init__(*args, **kw)
            kept.append(self)

    R.TuningRun = Kept  # type: ignore[misc]
    cell = next(i for i, c in enumerate(spec.cells) if c.label == label)
    for r in range(spec.runs):
        res = R.run_one(spec, cell, r)
        yield res, kept[-1]


def start_and_choice(run: Any) -> tuple[Gains, Gains, float]:
    """A finished run's start gains, final choice and reference loss."""
    ref = next(x for x in run.records if isinstance(x, Reference))
    return Gains(**ref.gains), Gains(**run.final_choice()['gains']), ref.loss


def choice_losses(
    drive: Any, experiment: Any, start: Gains, choice: Gains, repeats: int
) -> list[float]:
    """``choice`` measured ``repeats`` times on a fresh bench of ``drive`` (seed 1), one
    experiment of ``start`` before every third (so from other rest positions)."""
    bench = OfflineBench(drive, 1, experiment)
    bench.measure(start)  # (from rest)
    ls = []
    for i in range(repeats):
        if i % 3 == 0:
            bench.measure(start)
        ls.append(bench.measure(choice).loss)
    return ls


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--drive', default='im7500w-j10')
    ap.add_argument('--mismatch', default='J=x0.5')
    ap.add_argument('--runs', type=int, default=8)
    ap.add_argument('--budget', type=int, default=60)
    ap.add_argument('--repeats', type=int, default=12)
    a = ap.parse_args()
    spec = StudySpec(
        runs=a.runs,
        budget=a.budget,
        algos=('safe', 'bobyqa'),
        drives=(a.drive,),
        full_grid=False,
        mismatch=parse_mismatch(a.mismatch),
    )
    plant, _params, experiment = spec.loaded()
    print('| row | run | re-measured | repeats: mean | sd | least | largest |')
    print('|---|---|---|---|---|---|---|')
    for label, name in ROWS:
        means, rems = [], []
        for r, (res, run) in enumerate(repeated_runs(spec, label)):
            start, choice, ref_loss = start_and_choice(run)
            ls = [x / ref_loss for x in choice_losses(plant, experiment, start, choice, a.repeats)]
            means.append(float(np.mean(ls)))
            rems.append(res.remeasured / ref_loss)
            print(
                f'| {name} | {r} | {rems[-1]:.4f} | {means[-1]:.4f} | {np.std(ls):.4f} '
                f'| {min(ls):.4f} | {max(ls):.4f} |',
                flush=True,
            )
        print(f'| {name} | mean | {np.mean(rems):.4f} | {np.mean(means):.4f} | | | |')


if __name__ == '__main__':
    main()
