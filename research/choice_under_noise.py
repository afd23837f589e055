"""Which gains should a run leave applied, when one experiment's loss scatters?

For runs of the study's default row (safe, first step from the identified drive) on a
told drive and a plant, after each run: the gains the run chose (``final_choice``), the
gains with the best mean of two or more measurements within the ripple limit, and safe's
incumbent, each measured 12 more times on the run's own bench (its state as the run left
it); the means are over the run's reference loss.  Also how many of the run's
experiments were louder than the limit in their own experiment.

    python research/choice_under_noise.py --drive im750w-j1 [--mismatch 'J=x0.5'] [--runs 10]
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import im_drive_sim  # noqa: F401 (the numeric baseline, set before numpy loads)

# isort: split
import numpy as np

from im_controller.config import Gains
from im_tuner import tuning as T
from im_tuner.runlog import ripple as RP
from im_tuner.runlog.records import Evaluation
from im_tuner.study import runs as R
from im_tuner.study.plant import parse_mismatch
from im_tuner.study.spec import StudySpec

AGAIN = 12


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--drive', default='im750w-j1')
    ap.add_argument('--mismatch', default='')
    ap.add_argument('--runs', type=int, default=10)
    a = ap.parse_args()
    spec = StudySpec(
        runs=a.runs, budget=200, algos=('safe',), drives=(a.drive,), full_grid=False,
        mismatch=parse_mismatch(a.mismatch) if a.mismatch else (), realism='bench',
    )  # fmt: skip
    cell = next(i for i, c in enumerate(spec.cells) if c.first == 'identify')
    kept: list[tuple[T.TuningRun, object]] = []
    run = T.TuningRun.run

    def keep(self: T.TuningRun, bench: object) -> str:
        kept.append((self, bench))
        return run(self, bench)

    T.TuningRun.run = keep  # type: ignore[method-assign]
    print('| run | re-measured | loud experiments | chosen | best mean (n) | incumbent |')
    print('|---|---|---|---|---|---|')
    rows = []
    for r in range(a.runs):
        res = R.run_one(spec, cell, r)
        tr, bench = kept[-1]
        recs, ref = tr.records, res.ref_loss
        bound = RP.ripple_bound(recs, tr.ripple_limit)
        ev = [x for x in recs if isinstance(x, Evaluation) and x.status == 'ok']
        loud = sum(1 for x in ev if (o := RP._over(x.ripple, bound)) is not None and o > 1)
        by: dict[tuple, list[float]] = defaultdict(list)
        for x in ev:
            by[tuple(sorted(x.gains.items()))].append(x.loss / ref)
        multi = [k for k, v in by.items() if len(v) > 1 and RP.within_limit(recs, dict(k), bound)]
        best = min(multi, key=lambda k: np.mean(by[k]))

        row = tuple(
            float(np.mean([bench.measure(g).loss / ref for _ in range(AGAIN)]))
            for g in (
                Gains(**tr.final_choice()['gains']),
                Gains(**dict(best)),
                tr.space.to_gains(tr.opt.x),
            )
        )
        rows.append(row)
        print(
            f'| {r} | {res.remeasured / ref:.3f} | {loud} of {len(ev)} | {row[0]:.3f} '
            f'| {row[1]:.3f} ({len(by[best])}) | {row[2]:.3f} |',
            flush=True,
        )
    m = np.mean(rows, axis=0)
    print(f'| mean | | | {m[0]:.4f} | {m[1]:.4f} | {m[2]:.4f} |')


if __name__ == '__main__':
    main()
