"""The exact-file goal: the default's re-measured loss against the long-CMA-ES bound.

    python research/cmaes_bound.py --out bags/bound [--drives im750w-j1,im7500w-j10]
        [--seeds 0,1] [--evaluations 1000] [--points 8] [--repeats 10] [--runs 8]
        [--budgets 50,200] [--realism ideal|bench]

The bound: a CMA-ES run of ``--evaluations`` experiments (the
study's row ``sigma0=0.1``, the tuner's own ``TuningRun`` on the offline bench of the
drive file as written, each seed of ``--seeds`` with the study's run seeds, once from a
uniform random point of the box as the study's row starts and once from the hand-tuned
start, ``--x0``: from random points CMA-ES does not find im7500w-j10's good region in
1000 evaluations, so the random starts alone are no bound there), then its
``--points`` best distinct evaluated points each measured ``--repeats`` more times on a
fresh bench of the same drive (the drive file's seed, the points interleaved); the point
of the smallest of those means over every seed is then measured ``CONFIRM`` = 30 more
times as the default's choices are (``choice_scatter.choice_losses``): the least of 8-64
means is biased low by the picking, and the bound is the fresh mean, in units of L_ref
(the study's: the hand-tuned start's mean loss over 100 experiments,
``study.runs.reference_loss``).

The default: ``ros2 run im_tuner study --drives D --algos safe --runs R --budget B``
(the recommended safe row is the default, first step from the identified drive, ripple
limit 1.5; blind safe and safe from the file's model come with it) per budget of
``--budgets`` into OUT/<drive>/b<B>/ (a study already there is read, not re-run): its mean
re-measured loss (tables.csv ``remeasured``: one experiment of each run's choice), and the
same runs repeated in this process as the tuner runs them (``--remeasure``: its default
3 best re-measured, the best re-measured chosen) with each choice measured ``--repeats``
times (:func:`expected_loss`): the choices' expected loss, what the goal compares with the
bound (within 4 % at 50 evaluations, 2 % at 200).  One re-measurement scatters by 3-5 %
per run here, so 8 runs' mean of it by about 1.5 %: the size of the goal.  Prints one
markdown table; exit 1 when the goal is missed.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import im_drive_sim  # noqa: F401 (the numeric baseline, set before numpy loads)

# isort: split
import numpy as np
from choice_scatter import choice_losses, repeated_runs, start_and_choice  # (this directory)
from mismatch_grid import _read as read_tables  # (this directory)

from im_tuner.family import drive_setup
from im_tuner.offline import OfflineBench
from im_tuner.optim import make_optimizer
from im_tuner.runlog.records import Evaluation
from im_tuner.runlog.tally import MemoryRecord
from im_tuner.study.runs import reference_loss
from im_tuner.study.spec import StudySpec
from im_tuner.tuning import TuningRun, run_seeds

#: the goal: the default's expected loss over the bound, per budget
GOAL = {50: 1.04, 200: 1.02}
#: the study's default row
DEFAULT_LABEL = 'first step from the identified drive'


#: where each seed's CMA-ES starts (``--x0``)
X0S = ('random', 'start')

#: fresh experiments of the bound's point (its expected loss, not the least of the means)
CONFIRM = 30


def bound(
    name: str,
    seeds: list[int],
    evaluations: int,
    points: int,
    repeats: int,
    realism: str | None,
    x0s: tuple[str, ...] = X0S,
) -> dict:
    """The long-CMA-ES bound on drive ``name`` (module docstring), with what it took:
    one CMA-ES per seed and per start of ``x0s`` (``random``: the study's row, a uniform
    random point of the box; ``start``: the hand-tuned start)."""
    setup = drive_setup(name, realism=realism)
    space = setup.params.space
    start = space.to_gains(space.start_u)
    l_ref = reference_loss(setup.drive, experiment=setup.experiment, start=start)[0]
    best: dict[tuple, float] = {}
    found_by: dict[tuple, str] = {}  # which run found a point
    t0 = time.perf_counter()
    for seed, x0 in ((s, x) for x in x0s for s in seeds):
        opt_seed, drive_seed = run_seeds(seed)
        at = space.start_u if x0 == 'start' else None
        opt = make_optimizer('cmaes', space.dim, opt_seed, sigma0=0.1, start=at)
        run = TuningRun(
            MemoryRecord(),
            space,
            opt,
            budget=evaluations,
            satisfactory_loss=setup.params.satisfactory_loss,
            remeasure=0,
            reference=True,
        )
        run.run(OfflineBench(setup.drive, drive_seed, setup.experiment))
        ok = sorted(
            (r.loss, tuple(sorted(r.gains.items())))
            for r in run.records
            if isinstance(r, Evaluation) and r.status == 'ok' and not r.aborted
        )
        mine: dict[tuple, float] = {}
        for loss, g in ok:
            mine.setdefault(g, loss)
            if len(mine) == points:
                break
        for g, loss in mine.items():
            if loss < best.get(g, np.inf):
                best[g], found_by[g] = loss, f'seed {seed} from {x0}'
    bench = OfflineBench(setup.drive, setup.drive.seed, setup.experiment)
    bench.measure(start)  # the first experiment from rest (not a measure)
    gains = {g: type(start)(**dict(g)) for g in best}
    losses: dict[tuple, list[float]] = {g: [] for g in best}
    for _ in range(repeats):
        for g in best:
            m = bench.measure(gains[g])
            losses[g].append(np.inf if m.aborted else m.loss)
    means = {g: float(np.mean(v)) for g, v in losses.items()}
    g_best = min(means, key=means.__getitem__)
    # the least of 8-64 means is biased low (it was picked by them): its expected loss
    # from fresh experiments, as the default's choices are measured (choice_losses)
    fresh = float(
        np.mean(choice_losses(setup.drive, setup.experiment, start, gains[g_best], CONFIRM))
    )
    return {
        'l_ref': l_ref,
        'bound': fresh / l_ref,
        'picked_by': means[g_best] / l_ref,
        'measured_best': best[g_best] / l_ref,
        'gains': dict(g_best),
        'found_by': found_by[g_best],
        'seconds': time.perf_counter() - t0,
    }


def default_loss(name: str, budget: int, runs: int, out: Path, realism: str | None) -> float:
    """The default's mean re-measured loss [L_ref] at ``budget`` (a study per budget)."""
    tables = out / name / 'tables.csv'
    if not tables.exists():
        cmd = [
            str(Path(sys.prefix) / 'bin' / 'ros2'), 'run', 'im_tuner', 'study',
            '--drives', name, '--algos', 'safe', '--runs', str(runs), '--budget', str(budget),
            '--jobs', '2', '--quiet', '--out', str(out),
        ]  # fmt: skip
        if realism is not None:
            cmd += ['--realism', realism]
        out.mkdir(parents=True, exist_ok=True)
        with (out.parent / f'{out.name}.log').open('w') as log:
            subprocess.run(cmd, check=True, stdout=log)
    got = read_tables(tables).get(('remeasured', 'safe', DEFAULT_LABEL))
    if got is None:
        raise SystemExit(f'{tables}: no remeasured row of the default')
    return got


def expected_loss(
    name: str, budget: int, runs: int, repeats: int, realism: str | None, remeasure: int
) -> float:
    """The default's expected loss [L_ref] at ``budget``: each of the study's ``runs`` runs
    of the default row repeated in this process (the same seeds: the same records, the
    same choice), its final choice measured ``repeats`` times on a fresh bench of the
    drive (one experiment of the start before every third, so they start from other rest
    positions), the mean over the repeats and runs (research/choice_scatter.py's
    protocol).  ``remeasure``: the K best distinct evaluations re-measured at the run's end
    (the tuner's ``--remeasure``, default 3; the study's runs re-measure 1)."""
    spec = StudySpec(
        runs=runs, budget=budget, algos=('safe',), drives=(name,), full_grid=False,
        realism=realism,
    )  # fmt: skip
    drive, _params, experiment = spec.loaded()
    setup = drive_setup(name, realism=realism)
    space = setup.params.space
    l_ref = reference_loss(drive, experiment=experiment, start=space.to_gains(space.start_u))[0]
    means = []
    for _res, run in repeated_runs(spec, DEFAULT_LABEL, remeasure):
        start, choice, _ref_loss = start_and_choice(run)
        ls = choice_losses(drive, experiment, start, choice, repeats)
        means.append(float(np.mean(ls)) / l_ref)
    return float(np.mean(means))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--out', type=Path, required=True)
    ap.add_argument('--drives', default='im750w-j1,im7500w-j10')
    ap.add_argument('--seeds', default='0,1')
    ap.add_argument('--evaluations', type=int, default=1000)
    ap.add_argument('--points', type=int, default=8)
    ap.add_argument('--repeats', type=int, default=10)
    ap.add_argument('--runs', type=int, default=8)
    ap.add_argument('--budgets', default='50,200')
    ap.add_argument(
        '--remeasure',
        type=int,
        default=3,
        help="the runs' re-measured best (the tuner's default 3)",
    )
    ap.add_argument('--realism', default=None, help="the drives' profile (default: the file's)")
    ap.add_argument(
        '--x0',
        default=','.join(X0S),
        help="where each seed's CMA-ES starts: random (the study's row), start (the "
        'hand-tuned start), or both',
    )
    a = ap.parse_args(argv)
    x0s = tuple(a.x0.split(','))
    if not set(x0s) <= set(X0S):
        ap.error(f'--x0 {a.x0}: each of {", ".join(X0S)}')
    seeds = [int(s) for s in a.seeds.split(',')]
    budgets = [int(b) for b in a.budgets.split(',') if b]
    cols = ' | '.join(f'default at {b}: re-measured once | expected | / bound' for b in budgets)
    print(f'| drive | bound (L_ref) | picked by | its best measured | {cols} |')
    print('|---|---|---|---|' + '---|---|---|' * len(budgets))
    missed = []
    for d in a.drives.split(','):
        b = bound(d, seeds, a.evaluations, a.points, a.repeats, a.realism, x0s)
        cells = []
        for budget in budgets:
            once = default_loss(d, budget, a.runs, a.out / d / f'b{budget}', a.realism)
            x = expected_loss(d, budget, a.runs, a.repeats, a.realism, a.remeasure)
            cells += [f'{once:.3f}', f'{x:.3f}', f'{x / b["bound"]:.3f}']
            if budget in GOAL and x / b['bound'] > GOAL[budget]:
                missed.append(f'{d} at {budget}: {100 * (x / b["bound"] - 1):+.1f} %')
        head = f'| {d} | {b["bound"]:.3f} | {b["picked_by"]:.3f} | {b["measured_best"]:.3f} | '
        print(head + ' | '.join(cells) + ' |')
        took = f'the bound in {b["seconds"]:.0f} s at {b["gains"]}, found by {b["found_by"]}'
        print(f'<!-- {d}: L_ref {b["l_ref"]:.6g}, {took} -->')
    print(f'\ngoal: within 4 % at 50, 2 % at 200; missed: {"; ".join(missed) or "none"}')
    return 1 if missed else 0


if __name__ == '__main__':
    sys.exit(main())
