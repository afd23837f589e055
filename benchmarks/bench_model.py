"""Benchmark of the IM drive model kernels: median ns per 200 us model step.

Runs ``kernels.run_batch`` (a numba loop, no per-step Python) over a batch of steps for
the full model (vector control + RK4 plant) and the reduced model, after a warm-up that
also triggers compilation; repeats and prints median/min/max ns per step.

    python benchmarks/bench_model.py [--steps 100000] [--repeats 7]

``main() -> dict`` returns the figures for ``benchmarks/run_all.py``.  See docs/drive-model.md.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import time
from pathlib import Path

# the numeric baseline (set by im_drive_sim before numpy loads), as in the nodes; a source
# checkout without the package: the fallback below
with contextlib.suppress(ImportError):
    import im_drive_sim  # noqa: F401

# isort: split
import numpy as np

try:
    from im_drive_sim import kernels as K, model_layout as L
    from im_drive_sim.drive_file import load_config
    from im_drive_sim.sim import DriveSim
except ImportError:  # running from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'src' / 'im_drive_sim'))
    from im_drive_sim import kernels as K, model_layout as L
    from im_drive_sim.drive_file import load_config
    from im_drive_sim.sim import DriveSim


def _inputs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A representative command: square-wave isq* (+-3 A, 50 ms) and a 1.75 N m load step."""
    k = np.arange(n)
    isq = np.where((k // 250) % 2 == 0, 3.0, -3.0)
    tl = np.where((k // 2500) % 2 == 0, 0.0, 1.75)
    return isq.astype(np.float64), tl.astype(np.float64)


def bench_model(model: str, steps: int = 100_000, repeats: int = 7) -> dict[str, float]:
    """Median/min/max ns per step of ``run_batch`` for ``model`` ('full' | 'reduced')."""
    sim = DriveSim(load_config(overrides={'model': model}))
    isq, tl = _inputs(steps)
    dummy = np.empty((1, L.N_RUN_FIELDS))
    noise = np.zeros((steps + 1, L.NOISE_COLS))  # noise-free: one block covers the batch
    # Warm-up (compilation or cache load, caches, branch predictors).
    sim.reset()
    K.run_batch(sim.S, sim.P, noise, isq, tl, dummy, 0, min(steps, 10_000), False)
    per_step = []
    for _ in range(repeats):
        sim.reset()
        sim.S[L.S_NPOS] = 0.0
        t0 = time.perf_counter_ns()
        K.run_batch(sim.S, sim.P, noise, isq, tl, dummy, 0, steps, False)
        per_step.append((time.perf_counter_ns() - t0) / steps)
    if not np.all(np.isfinite(sim.S)):
        raise RuntimeError(f'{model} model state became non-finite in the benchmark')
    return {
        'median_ns': statistics.median(per_step),
        'min_ns': min(per_step),
        'max_ns': max(per_step),
        'steps': float(steps),
        'repeats': float(repeats),
    }


def main(steps: int = 100_000, repeats: int = 7, verbose: bool = True) -> dict:
    """Run both benchmarks; returns ``{'full': {...}, 'reduced': {...}}`` (ns per step)."""
    res = {m: bench_model(m, steps, repeats) for m in ('full', 'reduced')}
    if verbose:
        print(f'model step benchmark: {steps} steps x {repeats} repeats (run_batch, numba)')
        for m, r in res.items():
            print(
                f'  {m:8s} median {r["median_ns"]:7.1f} ns/step   '
                f'min {r["min_ns"]:7.1f}   max {r["max_ns"]:7.1f}'
            )
    return res


if __name__ == '__main__':
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--steps', type=int, default=100_000)
    ap.add_argument('--repeats', type=int, default=7)
    a = ap.parse_args()
    main(a.steps, a.repeats)
