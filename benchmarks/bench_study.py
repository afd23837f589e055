"""The offline configuration study: the paper's whole grid, timed as a command.

* ``ros2 run im_tuner study`` with the full model and with the reduced model: 12
  configurations x 100 runs x 200 evaluations (+ one reference and one re-measurement
  per run), on every core -- wall time of the whole command (start-up, L_ref, pool,
  tables, figures) and experiments per second;
* the same per-worker rate on one worker (``--jobs 1``, a 10-run grid), for the scaling
  ratio: how much of every core the pool uses;
* the run loop's cost (a study run is the tuner's ``TuningRun`` on the offline bench):
  ``study.run_one`` against a bare ask/measure/tell loop on the same bench (the
  yardstick, below), in this process, alternating, median ratio of 5 pairs. Target:
  within 10 %.

Run: ``.venv/bin/python benchmarks/bench_study.py [--runs N]`` (or ``make bench``).  Targets:
full grid <= 300 s on a 2-core machine, reduced <= 120 s.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')


def run(out: Path, *args: str) -> tuple[float, int]:
    """Wall time [s] of the whole command and the experiments it ran."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [ROS2, 'run', 'im_tuner', 'study', '--quiet', '--out', str(out), *args],
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f'study failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}')
    meta = json.loads((out / 'study.json').read_text())
    return wall, int(meta['experiments'])


def _bare_run(spec, cell_index: int, r: int) -> float:
    """The yardstick: what a study run computes, as a bare loop (reference, budget
    evaluations, one re-measurement of the best) on the same offline bench; wall [s]."""
    import math

    from im_controller.config import Gains
    from im_tuner.offline import OfflineBench
    from im_tuner.study.runs import prepare_run

    t0 = time.perf_counter()
    space, opt, drive_seed = prepare_run(spec, cell_index, r, spec.params())
    bench = OfflineBench(spec.drive(), drive_seed)
    bench.measure(Gains(*space.start))
    best, best_loss = None, math.inf
    for _ in range(spec.budget):
        u = opt.ask()
        g = space.to_gains(u)
        m = bench.measure(g)
        opt.tell(u, m.loss)
        if not m.aborted and m.loss < best_loss:
            best, best_loss = g, m.loss
    if best is not None:
        bench.measure(best)
    return time.perf_counter() - t0


def loop_overhead(pairs: int = 5) -> float:
    """Median wall ratio study.run_one / bare loop over ``pairs`` alternating pairs (one
    neCGA and one SPSA run of 200 evaluations each)."""
    import statistics

    from im_tuner.study.runs import StudySpec, run_one

    spec = StudySpec(runs=1, budget=200)
    # the paper's defaults: SPSA (a0, c0) and neCGA n = 25, the middle cell of each grid
    cells = [
        i
        for i, c in enumerate(spec.cells)
        if (c.row == 1 and c.col == 1) or c.label.startswith('n=25 ')
    ]
    run_one(spec, cells[0], 0)  # kernels loaded, caches warm
    ratios = []
    for k in range(pairs):
        t0 = time.perf_counter()
        for c in cells:
            run_one(spec, c, k)
        a = time.perf_counter() - t0
        b = sum(_bare_run(spec, c, k) for c in cells)
        ratios.append(a / b)
    return statistics.median(ratios)


def main(runs: int = 100) -> dict[str, float]:
    figures: dict[str, float] = {}
    cores = len(os.sched_getaffinity(0))
    with tempfile.TemporaryDirectory(prefix='bench_study_') as tmp:
        for model in ('full', 'reduced'):
            wall, n = run(Path(tmp) / model, '--model', model, '--runs', str(runs))
            # scale to the paper's 100 runs when a shorter grid was asked for
            figures[f'study_{model}_grid_s'] = wall * 100 / runs
            figures[f'study_{model}_exp_per_s'] = n / wall
            print(
                f'{model:8s} grid ({runs} runs/config, {cores} workers): {n} experiments in '
                f'{wall:.1f} s = {n / wall:.0f} experiments/s',
                flush=True,
            )
        wall1, n1 = run(Path(tmp) / 'one', '--model', 'full', '--runs', '10', '--jobs', '1')
        figures['study_full_1job_exp_per_s'] = n1 / wall1
        figures['study_scaling'] = figures['study_full_exp_per_s'] / (n1 / wall1)
        print(
            f'full     one worker (10 runs/config): {n1 / wall1:.0f} experiments/s; '
            f'{cores} workers give {figures["study_scaling"]:.2f} x',
            flush=True,
        )
    figures['study_loop_overhead_ratio'] = loop_overhead()
    print(
        'run loop: TuningRun on the offline bench / bare ask-measure-tell loop = '
        f'{figures["study_loop_overhead_ratio"]:.3f} (median of 5 pairs; target <= 1.10)',
        flush=True,
    )
    return figures


if __name__ == '__main__':
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--runs', type=int, default=100, help='runs per configuration (default 100)')
    for k, v in main(ap.parse_args().runs).items():
        print(f'{k}: {v:.3f}')
