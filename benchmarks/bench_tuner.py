"""The default tuning run, timed: ``ros2 run im_tuner tuner --algo <algo>`` end to end.

Each run is the real command (a child process, in-process simulated bench, recorder on,
budget 200, 3 re-measurements, the reference), in a fresh run directory. From its
``summary.json`` and the process wall clock it reports:

* wall time of the whole command (start-up, numba cache load, discovery, tuning, closing
  the bag) and of the tuning loop alone;
* simulated experiment time (the sum of every experiment's sim time);
* their ratio, the real-time factor (target >= 5, recording included), on the whole
  command's wall time -- the stricter figure -- and on the loop;
* the optimiser's ask+tell time per evaluation: the median over the run's evaluations,
  measured around the real calls between experiments (target < 50 us);
* the report of that run, ``ros2 run im_tuner report RUN --out DIR`` (reads the ~345 MB
  bag, writes the four figures and the CSV): whole-command wall time, median of 3.

Run: ``.venv/bin/python benchmarks/bench_tuner.py [--algos necga spsa] [--budget 200]``
(part of ``make bench``).  ``main() -> dict`` returns the figures for run_all.py.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')


def run_once(algo: str, budget: int, seed: int) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix='bench_tuner_'))
    env = dict(os.environ)
    env.setdefault('ROS_DOMAIN_ID', str(150 + os.getpid() % 50))
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    try:
        t0 = time.perf_counter()
        proc = subprocess.run(
            [
                ROS2,
                'run',
                'im_tuner',
                'tuner',
                '--algo',
                algo,
                '--budget',
                str(budget),
                '--seed',
                str(seed),
                '--out',
                str(tmp / 'run'),
                '--quiet',
            ],
            capture_output=True,
            text=True,
            env=env,
        )
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise RuntimeError(f'tuner failed ({proc.returncode}): {proc.stderr[-2000:]}')
        s = json.loads((tmp / 'run' / 'summary.json').read_text())
        bag = sum(f.stat().st_size for f in (tmp / 'run').glob('bag_*/*.mcap'))
        report = []
        for i in range(3):
            t0 = time.perf_counter()
            rep = subprocess.run(
                [
                    ROS2,
                    'run',
                    'im_tuner',
                    'report',
                    str(tmp / 'run'),
                    '--out',
                    str(tmp / f'report{i}'),
                ],
                capture_output=True,
                text=True,
                env=env,
            )
            report.append(time.perf_counter() - t0)
            if rep.returncode != 0:
                raise RuntimeError(f'report failed ({rep.returncode}): {rep.stderr[-2000:]}')
        return {
            'wall_s': wall,
            'loop_wall_s': s['loop_wall_s'],
            'sim_s': s['sim_s'],
            'rtf': s['sim_s'] / wall,
            'rtf_loop': s['real_time_factor'],
            'opt_us': s['optimizer_us_per_eval'],
            'best': s['best']['loss'],
            'start': s['reference']['loss'],
            'experiments': s['experiments'],
            'bag_mb': bag / 1e6,
            'report_s': statistics.median(report),
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main(algos: tuple[str, ...] = ('necga', 'spsa'), budget: int = 200, seed: int = 1) -> dict:
    figures = {}
    for algo in algos:
        r = run_once(algo, budget, seed)
        print(
            f'{algo:>6} budget {budget}: wall {r["wall_s"]:.1f} s (tuning loop '
            f'{r["loop_wall_s"]:.1f} s), simulated experiments {r["sim_s"]:.1f} s '
            f'({r["experiments"]}), real-time factor {r["rtf"]:.2f} (loop {r["rtf_loop"]:.2f}), '
            f'ask+tell {r["opt_us"]:.1f} us/eval, best loss {r["best"]:.4f} (start '
            f'{r["start"]:.4f}), bag {r["bag_mb"]:.0f} MB; report of the run '
            f'{r["report_s"]:.2f} s',
            flush=True,
        )
        figures[f'tuner_{algo}_rtf'] = r['rtf']
        figures[f'tuner_{algo}_ask_tell_us'] = r['opt_us']
        figures[f'tuner_{algo}_wall_s'] = r['wall_s']
        figures[f'tuner_{algo}_sim_s'] = r['sim_s']
        figures[f'report_{algo}_s'] = r['report_s']
    return figures


if __name__ == '__main__':
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--algos', nargs='+', default=['necga', 'spsa'])
    ap.add_argument('--budget', type=int, default=200)
    ap.add_argument('--seed', type=int, default=1)
    a = ap.parse_args()
    main(tuple(a.algos), a.budget, a.seed)
