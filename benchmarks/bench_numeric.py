"""What the numeric baseline costs: the optimisers' ask + tell with numpy's and
OpenBLAS's dispatch held at x86-64-v3 (``im_drive_sim.numeric``, the default) against
native dispatch (``IM_NUMERIC_BASELINE=off``: AVX-512 where the CPU has it).

Each sample is a child process (the dispatch is fixed when numpy loads), the two settings
interleaved A, B, A, B... so that the machine's drift falls on both; in each child, every
algorithm whose state goes through numpy's SIMD loops or OpenBLAS (cmaes, tpe, safe) runs
``evals`` ask/tell steps on a cheap deterministic loss after a warm-up; the child's figure
is the median step [us].  Printed: the median over samples per setting and their ratio.

    python benchmarks/bench_numeric.py [--samples 5] [--evals 200]

``main() -> dict`` (for run_all): ``{f'numeric_{algo}_held_us', f'numeric_{algo}_off_us',
f'numeric_{algo}_ratio'}``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

ALGOS = ('cmaes', 'tpe', 'safe')

CHILD = r"""
import json, math, sys, time
import im_drive_sim
from im_drive_sim import numeric
import numpy as np
from im_tuner.optim import make_optimizer
evals = int(sys.argv[1])
out = {'state': numeric.status()['state']}
for algo in sys.argv[2:]:
    n = evals if algo != 'tpe' else max(20, evals // 5)  # tpe: ~20 ms an ask
    opt = make_optimizer(algo, 5, 7, start=np.full(5, 0.3))
    times = []
    for step in range(n + 10):
        t0 = time.perf_counter()
        u = opt.ask()
        y = float(np.sum((u - 0.4) ** 2)) + 0.01 * math.sin(9.0 * float(u[0]))
        opt.tell_measurement(u, y, False)
        if step >= 10:
            times.append(time.perf_counter() - t0)
    times.sort()
    out[algo] = times[len(times) // 2] * 1e6
print(json.dumps(out))
"""


def _sample(setting: str, evals: int) -> dict:
    env = dict(os.environ)
    for k in ('NPY_DISABLE_CPU_FEATURES', 'OPENBLAS_CORETYPE', 'OPENBLAS_NUM_THREADS'):
        env.pop(k, None)  # this process's baseline must not reach the native child
    env['IM_NUMERIC_BASELINE'] = 'x86-64-v3' if setting == 'held' else 'off'
    p = subprocess.run(
        [sys.executable, '-c', CHILD, str(evals), *ALGOS],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(p.stdout)


def main(samples: int = 5, evals: int = 200) -> dict:
    got: dict[str, list[dict]] = {'held': [], 'off': []}
    for _ in range(samples):
        for setting in ('held', 'off'):
            got[setting].append(_sample(setting, evals))
    out: dict = {}
    for algo in ALGOS:
        held = statistics.median(s[algo] for s in got['held'])
        off = statistics.median(s[algo] for s in got['off'])
        out[f'numeric_{algo}_held_us'] = held
        out[f'numeric_{algo}_off_us'] = off
        out[f'numeric_{algo}_ratio'] = held / off
    out['numeric_states'] = f'{got["held"][0]["state"]}/{got["off"][0]["state"]}'
    return out


if __name__ == '__main__':
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--samples', type=int, default=5)
    ap.add_argument('--evals', type=int, default=200)
    a = ap.parse_args()
    r = main(a.samples, a.evals)
    print(f'baseline states (held/off): {r["numeric_states"]}')
    print(f'{"algo":8s} {"held [us]":>10s} {"off [us]":>10s} {"held/off":>9s}')
    for algo in ALGOS:
        print(
            f'{algo:8s} {r[f"numeric_{algo}_held_us"]:10.1f} {r[f"numeric_{algo}_off_us"]:10.1f} '
            f'{r[f"numeric_{algo}_ratio"]:9.3f}'
        )
