"""The offline configuration study (issue 7): the paper's whole grid, timed as a command.

* ``ros2 run im_tuner study`` with the full model and with the reduced model: 12
  configurations x 100 runs x 200 evaluations (+ one reference and one re-measurement
  per run), on every core -- wall time of the whole command (start-up, L_ref, pool,
  tables, figures) and experiments per second;
* the same per-worker rate on one worker (``--jobs 1``, a 10-run grid), for the scaling
  ratio: how much of every core the pool uses.

Run: ``.venv/bin/python bench/bench_study.py [--runs N]`` (or ``make bench``).  Targets
(issue 7): full grid <= 300 s on a 2-core machine, reduced <= 120 s.
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
    return figures


if __name__ == '__main__':
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--runs', type=int, default=100, help='runs per configuration (default 100)')
    for k, v in main(ap.parse_args().runs).items():
        print(f'{k}: {v:.3f}')
