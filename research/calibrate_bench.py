"""The ``bench`` realism profile's calibration: one command,
``python research/calibrate_bench.py`` (``make calibrate-bench``), measures and prints the
fit and writes it as docs/calibration.md.

What it fits: one factor s that scales every noise-like bench magnitude together
(``im_drive_sim.params.BENCH_NOISE_KEYS``: current-sensor noise, encoder edge jitter,
the random load, the load step's amplitude and instant) from its sourced estimate
(``BENCH_ESTIMATES``, docs/drive-model.md "Bench effects"); the systematic effects keep
their sourced magnitudes. For the ``ideal`` profile and for ``bench`` at each s:

(a) the spread of repeated measurements: the coefficient of variation of the hand-tuned
    start's loss over ``--spread`` consecutive experiments after the first from rest
    (the drive file's seed), and the wall time of one experiment (the study's
    experiments/s);
(b) a small study with the study's own runs (``runs.run_one``, normalised by
    ``runs.reference_loss`` of the same drive): the paper's centre cells, SPSA a=0.0183
    c=0.03 and neCGA n=25 eta=12, ``--runs`` runs of ``--budget`` evaluations, Table I
    (mean final loss) and Table II (% of runs satisfactory at 0.9) against the paper's.

The fit: the s whose two centre cells are closest to the paper's, by the distance
D = sum over the cells of (dTable I / 0.05)^2 + (dTable II / 10 %)^2 (0.05 and 10 points:
about the sampling error of a 30-run mean and percentage). The paper publishes no spread
of repeated measurements: (a) is reported, not fitted.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from im_drive_sim.cli import EXIT_USAGE
from im_tuner.study.spec import StudySpec, default_jobs

__all__ = ['CENTRE', 'PAPER_CENTRE', 'Row', 'calibrate', 'main', 'markdown']

#: The paper's centre cells (labels of ``spec.grid``) and their Table I / Table II values.
CENTRE: tuple[str, ...] = ('a=0.0183 c=0.03', 'n=25 eta=12')
PAPER_CENTRE: dict[str, tuple[float, float]] = {
    'a=0.0183 c=0.03': (0.81, 90.0),
    'n=25 eta=12': (0.70, 92.0),
}
#: The distance's scales: Table I [normalised loss], Table II [percentage points].
SCALE_FINAL, SCALE_PCT = 0.05, 10.0
THRESHOLD = 0.9
#: The largest noise scale the sources support (docs/drive-model.md 7a): at s = 4 the
#: current noise is 0.04 A (10x the ADC's floor), the jitter 4 us, the random load 2 % of
#: rated torque, the load step 8 % std and up to 4 ms late (a 2 ms fieldbus cycle); beyond
#: it no source holds. The fit chooses among s <= this; larger s are shown, not chosen.
MAX_SCALE = 4.0


@dataclass
class Row:
    """One profile's results: ``scale`` None is ``ideal``."""

    scale: float | None
    cv: float  #: spread of repeated measurements (std/mean of the start's loss)
    loss: float  #: mean of those measurements (raw)
    exp_ms: float  #: wall time of one experiment [ms], over the study's runs
    l_ref: float
    final: dict[str, float]  #: Table I per centre cell
    sat: dict[str, float]  #: Table II [%] per centre cell
    aborted: dict[str, float]  #: % of evaluations aborted per centre cell

    @property
    def name(self) -> str:
        return 'ideal' if self.scale is None else f'bench s={self.scale:g}'

    @property
    def distance(self) -> float:
        return sum(
            ((self.final[c] - PAPER_CENTRE[c][0]) / SCALE_FINAL) ** 2
            + ((self.sat[c] - PAPER_CENTRE[c][1]) / SCALE_PCT) ** 2
            for c in CENTRE
        )


def drive_for(scale: float | None) -> Any:
    """The packaged drive (full model): ``ideal``, or ``bench`` at noise scale ``scale``."""
    from im_drive_sim.drive_file import load_config
    from im_drive_sim.params import bench_profile

    if scale is None:
        return load_config(overrides={'realism': 'ideal'})
    return load_config(overrides={'realism': 'bench', **bench_profile(scale)})


def spread(drive: Any, n: int) -> tuple[float, float, float]:
    """(CV, mean loss, ms per experiment) of the hand-tuned start over ``n`` consecutive
    experiments after the first from rest (drive seed of the file)."""
    from im_controller.config import Gains
    from im_tuner.offline import OfflineBench

    bench = OfflineBench(drive, drive.seed)
    g = Gains()
    bench.measure(g)
    t0 = time.perf_counter()
    x = np.array([bench.measure(g).loss for _ in range(n)])
    ms = 1e3 * (time.perf_counter() - t0) / n
    return float(x.std(ddof=1) / x.mean()), float(x.mean()), ms


def _run(task: tuple[StudySpec, int, int, float | None]) -> tuple[float | None, int, Any]:
    """One study run (a pool task): (scale, cell, (the run's final raw loss, aborted
    count, its experiments' wall time [s], its experiments: evaluations, reference and
    re-measurement))."""
    from im_tuner.study.runs import run_one

    spec, c, r, scale = task
    res = run_one(spec, c, r, drive_for(scale))
    ok = ~res.aborted
    final = float(res.losses[ok].min()) if ok.any() else math.nan
    n_exp = res.losses.size + 1 + (0 if math.isnan(res.remeasured) else 1)
    return scale, c, (final, int(res.aborted.sum()), res.exp_s, n_exp)


def _results(tasks: list, jobs: int) -> Iterator[tuple[float | None, int, Any]]:
    """``_run`` of every task, in order: in this process (jobs 1) or on a pool."""
    if jobs == 1:
        yield from map(_run, tasks)
        return
    ctx = multiprocessing.get_context('forkserver')
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx) as pool:
        yield from pool.map(_run, tasks, chunksize=4)


def calibrate(
    scales: tuple[float, ...], runs: int, budget: int, n_spread: int, jobs: int, seed: int
) -> tuple[list[Row], float]:
    """The rows of ``ideal`` and of ``bench`` at each scale (module docstring), and the
    spread of ``bench`` with its noise-like effects off (s = 0: the systematic ones alone)."""
    from im_tuner.study.runs import reference_loss

    spec = StudySpec(runs=runs, budget=budget, seed=seed)
    labels = [cell.label for cell in spec.cells]
    cells = [labels.index(lab) for lab in CENTRE]
    profiles: list[float | None] = [None, *scales]
    rows: dict[float | None, Row] = {}
    for s in profiles:
        drive = drive_for(s)
        cv, loss, _ms = spread(drive, n_spread)
        l_ref = reference_loss(drive)[0]
        rows[s] = Row(s, cv, loss, math.nan, l_ref, {}, {}, {})
        print(f'{rows[s].name}: spread CV {100 * cv:.2f} %', flush=True)
    tasks = [(spec, c, r, s) for s in profiles for c in cells for r in range(runs)]
    finals: dict[tuple[float | None, int], list[tuple[float, int, float, int]]] = {}
    t0 = time.perf_counter()
    for i, (s, c, out) in enumerate(_results(tasks, jobs), 1):
        finals.setdefault((s, c), []).append(out)
        if i % runs == 0:
            el = time.perf_counter() - t0
            print(f'  {i}/{len(tasks)} runs, {el:.0f} s', file=sys.stderr, flush=True)
    print(f'{len(tasks)} runs in {time.perf_counter() - t0:.0f} s', flush=True)
    for s in profiles:
        row = rows[s]
        for lab, c in zip(CENTRE, cells, strict=True):
            f = np.array([x[0] for x in finals[(s, c)]]) / row.l_ref
            ok = f[~np.isnan(f)]  # a run with every experiment aborted has no final
            row.final[lab] = float(ok.mean()) if ok.size else math.nan
            row.sat[lab] = 100.0 * float(np.mean(np.nan_to_num(f, nan=np.inf) <= THRESHOLD))
            row.aborted[lab] = 100.0 * sum(x[1] for x in finals[(s, c)]) / (runs * budget)
        done = [x for c in cells for x in finals[(s, c)]]
        row.exp_ms = 1e3 * sum(x[2] for x in done) / sum(x[3] for x in done)
    cv0 = spread(drive_for(0.0), n_spread)[0]
    print(f'bench s=0 (systematic effects only): spread CV {100 * cv0:.2f} %', flush=True)
    return [rows[s] for s in profiles], cv0


def markdown(
    rows: list[Row],
    cv0: float,
    runs: int,
    budget: int,
    n_spread: int,
    command: str,
    max_scale: float = MAX_SCALE,
) -> str:
    """docs/calibration.md: the target, the rows (``ideal`` first), the fit (the best s <=
    ``max_scale``) and what remains different; ``cv0`` the spread of ``bench`` at s = 0."""
    bench = [r for r in rows if r.scale is not None]
    allowed = [r for r in bench if (r.scale or 0.0) <= max_scale] or bench
    best = min(allowed, key=lambda r: r.distance)
    free = min(bench, key=lambda r: r.distance)
    spsa, ga = CENTRE
    head = (
        '| profile | spread CV of the start [%] | experiments/s | '
        f'SPSA {spsa}: Table I | Table II [%] | aborted [%] | '
        f'neCGA {ga}: Table I | Table II [%] | aborted [%] | distance D |\n'
        '|---|---|---|---|---|---|---|---|---|---|\n'
    )
    paper = (
        f'| **paper** | not published | 0.6 (the real bench) | {PAPER_CENTRE[spsa][0]:.2f} | '
        f'{PAPER_CENTRE[spsa][1]:.0f} | < 1 (all cells) | {PAPER_CENTRE[ga][0]:.2f} | '
        f'{PAPER_CENTRE[ga][1]:.0f} | < 1 | 0 |\n'
    )
    body = ''.join(
        f'| {r.name}{_mark(r, best, max_scale)} | {100 * r.cv:.2f} | {1e3 / r.exp_ms:.0f} | '
        f'{r.final[spsa]:.2f} | {r.sat[spsa]:.0f} | {r.aborted[spsa]:.1f} | '
        f'{r.final[ga]:.2f} | {r.sat[ga]:.0f} | {r.aborted[ga]:.1f} | {r.distance:.1f} |\n'
        for r in rows
    )
    ideal = rows[0]
    slow = sum(r.exp_ms for r in bench) / len(bench) / ideal.exp_ms
    return (
        '# Calibration of the `bench` realism profile\n\n'
        f'Generated by `{command}` (`make calibrate-bench`; `research/calibrate_bench.py`). '
        'Do not edit: re-run it.\n\n'
        "**Target.** The paper's centre cells, SPSA a=0.0183 c=0.03 (Table I 0.81, Table II "
        '90 %) and neCGA n=25 eta=12 (0.70, 92 %); the paper publishes no spread of repeated '
        'measurements, so the spread (the coefficient of variation of the hand-tuned '
        f"start's loss over {n_spread} consecutive experiments after the first) is reported, "
        'not fitted.\n\n'
        '**The fit.** One factor s scales every noise-like bench magnitude together '
        '(`im_drive_sim.params.BENCH_NOISE_KEYS`: current-sensor noise, encoder edge '
        "jitter, random load, the load step's amplitude and instant) from its sourced "
        'estimate (docs/drive-model.md 7a); the systematic effects (offsets, friction, '
        "ripple, dead time, Rr drift) keep theirs. For each s: the study's own runs "
        f'(`runs.run_one`, packaged drive, full model) of the two cells, {runs} runs x '
        f"{budget} evaluations, losses normalised by the same drive's L_ref (100 "
        'experiments). Chosen: the smallest D = sum over the cells of '
        f'(dTable I/{SCALE_FINAL:g})^2 + (dTable II/{SCALE_PCT:g} points)^2 among the s '
        f'the sources support (s <= {max_scale:g}: `calibrate.MAX_SCALE`, beyond it a '
        'magnitude exceeds every source of docs/drive-model.md 7a).\n\n'
        + head
        + paper
        + body
        + f'\n**Chosen: s = {best.scale:g}** (`params.BENCH_NOISE_SCALE`; the `bench` '
        f'profile is `bench_profile({best.scale:g})`). D = {best.distance:.1f} against '
        f'{ideal.distance:.1f} for `ideal`. One experiment (1.625 s of bench time) takes '
        f'{ideal.exp_ms:.1f} ms on `ideal` and {slow:.1f}x that on `bench` (its noise '
        "blocks, friction, ripple and dead-time terms): the mean over the study's runs, "
        'wall time in parallel workers on a shared 2-core machine, indicative.\n\n'
        '**What remains different.** ' + _remaining(best, ideal, cv0, free) + '\n'
    )


def _mark(r: Row, best: Row, max_scale: float) -> str:
    if r is best:
        return ' (chosen)'
    return ' (beyond the sources)' if (r.scale or 0.0) > max_scale else ''


def _remaining(best: Row, ideal: Row, cv0: float, free: Row) -> str:
    from im_drive_sim.params import bench_profile

    spsa, ga = CENTRE
    parts = []
    for lab, name in ((spsa, 'SPSA'), (ga, 'neCGA')):
        pf, ps = PAPER_CENTRE[lab]
        parts.append(
            f'{name} centre: Table I {best.final[lab]:.2f} (paper {pf:.2f}, ideal '
            f'{ideal.final[lab]:.2f}), Table II {best.sat[lab]:.0f} % (paper {ps:.0f} %, '
            f'ideal {ideal.sat[lab]:.0f} %).'
        )
    parts.append(
        f"The spread of the start's loss is {100 * best.cv:.2f} % on `bench` against "
        f'{100 * ideal.cv:.2f} % on `ideal` and {100 * cv0:.2f} % with the noise-like '
        'effects off (s = 0): the systematic effects (friction, ripple, offsets, dead time '
        "make each experiment's loss depend on the state the previous one left) set most "
        'of it, and s does not scale them. A small study (its runs are few) carries a '
        'sampling error of about 0.03-0.05 in Table I and 5-10 points in Table II; the other '
        "cells of the paper's grid are not fitted (`make reproduction` shows them)."
    )
    prof = bench_profile(best.scale or 0.0)
    parts.append(
        f'At s = {best.scale:g} the noise-like magnitudes are: current noise '
        f'{prof["sensors.current_noise_std"]:g} A, encoder jitter '
        f'{1e6 * prof["sensors.encoder_jitter"]:g} us, random load '
        f'{prof["disturbance.load_noise_std"]:g} N m, load step amplitude std '
        f'{100 * prof["disturbance.load_step_amplitude_std"]:g} %, load step delay up to '
        f'{1e3 * prof["disturbance.load_step_delay_max"]:g} ms.'
    )
    if free is not best:
        parts.append(
            f'Without the bound the fit goes on to s = {free.scale:g} (D = '
            f"{free.distance:.1f}): the paper's centre cells ask for more noise than the "
            'sources support, and the gap left at the chosen s is what the supported '
            "effects cannot close (the paper's bench has effects this model lacks)."
        )
    return ' '.join(parts)


#: offline experiments per second of one worker (full model, ``bench`` profile): the rate
#: docs/calibration.md measured (63 ideal, 55-60 bench), rounded down for a loaded machine
RATE_PER_WORKER = 50.0
#: experiments of the reference loss L_ref per profile (``runs.reference_loss``)
_REF_EXPERIMENTS = 100


def estimate(scales: tuple[float, ...], runs: int, budget: int, n_spread: int, jobs: int) -> str:
    """One line said at the start: the experiments :func:`calibrate` will run and about how
    long they take on ``jobs`` workers (at ``RATE_PER_WORKER`` each)."""
    profiles = 1 + len(scales)  # ideal, then bench at each scale
    runs_total = profiles * len(CENTRE) * runs * budget
    side = (profiles + 1) * (n_spread + 1) + profiles * _REF_EXPERIMENTS  # spreads, L_ref
    seconds = runs_total / (RATE_PER_WORKER * jobs) + side / RATE_PER_WORKER
    return (
        f'calibrate: {runs_total + side} experiments ({profiles} profiles x {len(CENTRE)} '
        f'cells x {runs} runs x {budget} evaluations, plus spreads and L_ref): about '
        f'{max(1, round(seconds / 60))} min on {jobs} worker(s)'
    )


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one line, exit 2 (the project's rule)
        print(f'calibrate: {message}', file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


def _scales(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(x) for x in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError(f'not a list of numbers: {text!r}') from None
    if not vals or not all(math.isfinite(v) and 0.0 < v <= 16.0 for v in vals):
        raise argparse.ArgumentTypeError(f'scales must be numbers in (0, 16], got {text!r}')
    return vals


def _positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f'must be an integer >= 1, got {text!r}')
    return v


def main(argv: list[str] | None = None) -> int:
    p = _Parser(prog='python research/calibrate_bench.py', description=__doc__.split('\n')[0])
    p.add_argument('--scales', type=_scales, default=(1.0, 2.0, 4.0, 8.0))
    p.add_argument('--runs', type=_positive, default=30)
    p.add_argument('--budget', type=_positive, default=200)
    p.add_argument('--spread', type=_positive, default=30, help='experiments for the CV')
    p.add_argument('--jobs', type=_positive, default=default_jobs())
    p.add_argument('--seed', type=int, default=2005)
    p.add_argument('--out', type=Path, default=None, help='write the markdown here')
    a = p.parse_args(argv)
    if a.out is not None and not a.out.parent.is_dir():
        p.error(f'--out: no directory {a.out.parent}')
    if a.seed < 0:
        p.error(f'--seed must be >= 0, got {a.seed}')
    print(estimate(a.scales, a.runs, a.budget, a.spread, a.jobs), file=sys.stderr, flush=True)
    rows, cv0 = calibrate(a.scales, a.runs, a.budget, a.spread, a.jobs, a.seed)
    args = ' '.join(sys.argv[1:]) if argv is None else ' '.join(argv)
    text = markdown(
        rows, cv0, a.runs, a.budget, a.spread, f'python research/calibrate_bench.py {args}'
    )
    print(text)
    if a.out is not None:
        a.out.write_text(text, encoding='utf-8')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
