"""The report's speed: start-up, and a whole report of a ~25 MB bag.

* start-up: ``ros2 run im_tuner report --help`` and a refusal (``report
  /nonexistent``: one line, exit 2), each the real command in a child process, median
  of ``--repeats`` runs. Target: under 1 s (the command line is checked before numpy,
  numba or matplotlib are imported);
* a whole report, ``ros2 run im_tuner report RUN --out DIR`` (bag read, summary, CSV,
  the four figures: two of them drawn in a second process while the bag is read), on a
  run made here first with the real tuner (``--algo necga --seed 1``, in-process
  simulated bench, recording on; ``--budget 11`` first, and if its bag is not within
  20 % of ``--mb`` (25 MB, about 250 000 messages) once more with the budget scaled to
  it); median of ``--repeats`` runs, each into a new directory. Target: under 3 s on a
  2-core machine.

The load average is printed before and after: on a shared machine the figures are
inflated; compare them with the load in mind.

Run: ``.venv/bin/python benchmarks/bench_report.py [--mb 25] [--repeats 5]`` (part of
``make bench``).  ``main() -> dict`` returns the figures for run_all.py.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault('ROS_DOMAIN_ID', str(150 + os.getpid() % 50))
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    return env


def timed(args: list[str], expect: int = 0) -> float:
    """Wall time [s] of ``ros2 run im_tuner <args>``, which must exit ``expect``."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [ROS2, 'run', 'im_tuner', *args], capture_output=True, text=True, env=_env()
    )
    wall = time.perf_counter() - t0
    if proc.returncode != expect:
        raise RuntimeError(f'{" ".join(args)}: exit {proc.returncode}: {proc.stderr[-2000:]}')
    return wall


def make_run(run: Path, budget: int, seed: int) -> float:
    """A tuning run with a bag to report on; returns the bag's size [MB]."""
    timed(
        [
            'tuner',
            '--algo',
            'necga',
            '--budget',
            str(budget),
            '--seed',
            str(seed),
            '--out',
            str(run),
            '--quiet',
        ]
    )
    return sum(f.stat().st_size for f in run.glob('bag_*/*.mcap')) / 1e6


def make_bag(tmp: Path, mb: float, budget: int, seed: int) -> tuple[Path, float, int]:
    """A run whose bag is within 20 % of ``mb`` [MB]: tried with ``budget``, then once
    more with the budget scaled by the size per experiment (the run has budget + 4
    experiments: the reference and 3 re-measurements). Returns (run, MB, budget)."""
    run = tmp / f'run_{budget}'
    size = make_run(run, budget, seed)
    if abs(size - mb) > 0.2 * mb:
        budget = max(1, round(mb * (budget + 4) / size) - 4)
        run = tmp / f'run_{budget}'
        size = make_run(run, budget, seed)
    return run, size, budget


def _load() -> str:
    return ' '.join(f'{x:.2f}' for x in os.getloadavg())


def main(mb: float = 25.0, budget: int = 11, repeats: int = 5, seed: int = 1) -> dict[str, float]:
    print(f'load average (1, 5, 15 min) before: {_load()}', flush=True)
    help_s = statistics.median(timed(['report', '--help']) for _ in range(repeats))
    refuse_s = statistics.median(
        timed(['report', '/nonexistent/run'], expect=2) for _ in range(repeats)
    )
    print(
        f'start-up, median of {repeats}: report --help {help_s:.2f} s, a refusal '
        f'{refuse_s:.2f} s (target < 1 s)',
        flush=True,
    )
    tmp = Path(tempfile.mkdtemp(prefix='bench_report_'))
    try:
        run, size, budget = make_bag(tmp, mb, budget, seed)
        total = [
            timed(['report', str(run), '--out', str(tmp / f'report{i}')]) for i in range(repeats)
        ]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    total_s = statistics.median(total)
    print(
        f'report of a {size:.0f} MB bag (tuner --algo necga --budget {budget}), median of '
        f'{repeats}: {total_s:.2f} s (runs {", ".join(f"{t:.2f}" for t in total)}; '
        'target < 3 s)',
        flush=True,
    )
    print(f'load average after: {_load()}', flush=True)
    return {
        'report_help_s': help_s,
        'report_refusal_s': refuse_s,
        'report_25mb_s': total_s,
        'report_25mb_bag_mb': size,
    }


if __name__ == '__main__':
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--mb', type=float, default=25.0, help='bag size to report on [MB]')
    ap.add_argument('--budget', type=int, default=11, help='first guess of the budget')
    ap.add_argument('--repeats', type=int, default=5)
    ap.add_argument('--seed', type=int, default=1)
    a = ap.parse_args()
    main(a.mb, a.budget, a.repeats, a.seed)
