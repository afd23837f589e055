"""Benchmark of the optimiser core: median ask+tell time per loss evaluation [us].

Each algorithm of ``im_tuner.optim`` with its default options at dim = 5 (the paper's five
gains; 5 x 16 bits for the binary compact GAs) is driven on a cheap quadratic loss:
``repeats`` batches of ``evals`` evaluations each after a warm-up batch, and the figure
is the median of the batch means (the loss itself, one numpy expression, is included; it
costs about 1 us).  Issue target: well below 50 us per evaluation.

    python bench/bench_optim.py [--evals 2000] [--repeats 7]

``main() -> dict`` returns ``{algo: us_per_evaluation}`` for ``bench/run_all.py``.
See docs/optimisers.md.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

try:
    from im_tuner.optim import ALGOS, make_optimizer
except ImportError:  # running from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "im_tuner"))
    from im_tuner.optim import ALGOS, make_optimizer

DIM = 5


def bench_algo(algo: str, evals: int = 2000, repeats: int = 7) -> float:
    """Median over ``repeats`` batches of the mean ask+tell time per evaluation [us]."""
    opt = make_optimizer(algo, DIM, seed=1)
    target = np.linspace(0.2, 0.8, DIM)

    def batch() -> float:
        t0 = time.perf_counter_ns()
        for _ in range(evals):
            u = opt.ask()
            d = u - target
            opt.tell(u, float(d @ d))
        return (time.perf_counter_ns() - t0) / evals / 1e3

    batch()  # warm-up (imports, caches)
    return statistics.median(batch() for _ in range(repeats))


def main(evals: int = 2000, repeats: int = 7, verbose: bool = True) -> dict[str, float]:
    """Run every algorithm; returns ``{algo: median us per evaluation}``."""
    res = {algo: bench_algo(algo, evals, repeats) for algo in ALGOS}
    if verbose:
        print(f"optimiser ask+tell, dim={DIM}, default options: {repeats} batches x "
              f"{evals} evaluations (median of batch means)")
        for algo, us in res.items():
            print(f"  {algo:6s} {us:7.2f} us/evaluation")
    return res


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--evals", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()
    main(a.evals, a.repeats)
