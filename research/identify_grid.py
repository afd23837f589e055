"""The identification goal on every packaged drive: the J identified from the
hand-tuned start's two experiments within 10 % of the plant's, on every packaged drive
and every mismatch of mismatch_grid.py (J x0.5-x2.5 alone, and J x1.5 Rr x1.3 Lm x0.85
Coulomb 2 % delay 2 together).

    python research/identify_grid.py [--drives all|NAME,...] [--cases exact,J=x0.5,...]
        [--seeds 0,1,2] [--realism bench]

Per (drive, case, seed): the tuner's own :class:`TuningRun` (the reference, then
``safe``'s evaluation 1: the start in the other direction) on the offline bench of the
plant (the told drive with ``study --plant-mismatch``'s mismatch applied,
``study.plant.apply_mismatch``), budget 1, the run seed's drive noise as a study run
has it (``run_seeds``); then ``identify`` on the start's records, exactly what the
tuner's ``--opt first=identify`` does before evaluation 2 (``first_step.IdentifiedFirstStep``).
Prints one markdown table (identified J / the plant's J - 1, and Kt, per case: the worst
over the seeds) and the worst case; exit 1 when a J misses 10 %.  Each drive file's own
realism profile unless ``--realism`` is given.  About 1 s per (drive, case, seed).
"""

from __future__ import annotations

import argparse
import sys
import time

from mismatch_grid import CASES  # the mismatch grid's cases (this directory)

from im_drive_sim.family import PACKAGED_NAMES
from im_tuner.family import drive_setup
from im_tuner.identify import identify, start_motions
from im_tuner.offline import OfflineBench
from im_tuner.optim import make_optimizer
from im_tuner.runlog.tally import MemoryRecord
from im_tuner.study.plant import apply_mismatch, parse_mismatch
from im_tuner.tuning import TuningRun, run_seeds

#: the goal: |J identified / J plant - 1| <= GOAL
GOAL = 0.10


def identified(name: str, case: str, seed: int, realism: str | None) -> tuple[float, float] | str:
    """(J / J_plant - 1, Kt / Kt_plant - 1) identified from the start's two experiments;
    'unstable' when the start aborted on the plant (no identification, no first step: the
    tuner then runs as without a model), 'none' when too few rows identified nothing."""
    setup = drive_setup(name, realism=realism)
    plant = apply_mismatch(setup.drive, parse_mismatch(CASES[case])) if CASES[case] else setup.drive
    space = setup.params.space
    opt_seed, drive_seed = run_seeds(seed)
    opt = make_optimizer('safe', space.dim, opt_seed, space.start_u)
    run = TuningRun(
        MemoryRecord(),
        space,
        opt,
        budget=1,
        satisfactory_loss=setup.params.satisfactory_loss,
        remeasure=0,
        reference=True,
    )
    run.run(OfflineBench(plant, drive_seed, setup.experiment))
    if any(getattr(r, 'aborted', False) for r in run.records):
        return 'unstable'
    idf = identify(start_motions(run.records), setup.drive.machine)
    if idf is None:
        return 'none'
    return idf.J / plant.machine.J - 1.0, idf.Kt / plant.machine.Kt - 1.0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--drives', default='all', help="'all' or packaged names, comma-separated")
    ap.add_argument('--cases', default=','.join(CASES))
    ap.add_argument('--seeds', default='0,1,2', help='run seeds, comma-separated')
    ap.add_argument(
        '--realism', default=None, help="a profile for every drive (default: the file's)"
    )
    a = ap.parse_args(argv)
    drives = list(PACKAGED_NAMES) if a.drives == 'all' else a.drives.split(',')
    cases = a.cases.split(',')
    seeds = [int(s) for s in a.seeds.split(',')]
    bad = [d for d in drives if d not in PACKAGED_NAMES] + [c for c in cases if c not in CASES]
    if bad:
        print(f'identify_grid: unknown drive or case: {", ".join(bad)}', file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    print(f'| drive | {" | ".join(cases)} |')
    print('|---|' + '---|' * len(cases))
    worst, unstable, missed = (0.0, ''), [], []
    for d in drives:
        cells = []
        for c in cases:
            got = [identified(d, c, s, a.realism) for s in seeds]
            errs = [e for e in got if not isinstance(e, str)]
            if len(errs) < len(got):  # the start aborted / nothing identified, some seed
                what = sorted({e for e in got if isinstance(e, str)})
                cells.append(f'{"/".join(what)} ({len(got) - len(errs)} of {len(got)})')
                (unstable if what == ['unstable'] else missed).append(f'{d} {c}')
                continue
            j = max(errs, key=lambda e: abs(e[0]))
            kt = max(errs, key=lambda e: abs(e[1]))
            cells.append(f'{100 * j[0]:+.1f} / {100 * kt[1]:+.1f}')
            if abs(j[0]) > abs(worst[0]):
                worst = (j[0], f'{d} {c}')
        print(f'| {d} | {" | ".join(cells)} |')
    print(
        f'\nJ / Kt identified vs the plant [%], the worst of seeds {seeds}; worst J: '
        f'{100 * worst[0]:+.1f} % ({worst[1]}); goal {100 * GOAL:g} %; start unstable '
        f'(nothing to identify, no first step): {", ".join(unstable) or "none"}; nothing '
        f'identified from a stable start: {", ".join(missed) or "none"}; '
        f'{time.perf_counter() - t0:.0f} s'
    )
    return 0 if abs(worst[0]) <= GOAL and not missed else 1


if __name__ == '__main__':
    sys.exit(main())
