"""Benchmark of the optimiser core: median ask+tell time per loss evaluation [us], hot and cold.

Each algorithm of ``im_tuner.optim`` with its default options at dim = 5 (the paper's five
gains; 5 x 16 bits for the binary compact GAs) is driven on a cheap quadratic loss (one
numpy expression, about 1 us, included in the hot figure only).  Target: well below
50 us per evaluation *in the tuning run*.

* **hot**: ``repeats`` batches of ``evals`` back-to-back evaluations after a warm-up batch;
  the median of the batch means.  Everything stays in the CPU caches: the optimiser's
  arithmetic alone.
* **cold**: what the tuner sees.  There every ask and every tell comes right after a
  150 ms experiment (numba kernels, DDS) and fsync'ed file writes, so code and data have
  left the caches and each numpy call costs 5-10 us.  Here, before every ask and before
  every tell: one offline experiment (``im_tuner.offline.run_experiment_offline``
  on an ``im_drive_sim.sim.DriveSim``, signals recorded) and a line appended to a file and
  fsync'ed (``--disturb stream`` streams a 32 MB array instead of the experiment, for a
  checkout without the drive packages).  ask and tell are timed alone, as tuning.py does,
  and ``tell`` gets ``u`` rebuilt from its record like the tuner's; the figure is the
  median over ``cold_evals`` evaluations of ask + tell.  On the development machine it
  lands within about 15 % of the tuner's own figure (``opt_us`` in its checkpoint).  (An
  idle sleep between the calls would inflate it 2-3x: an idle virtual CPU loses far more
  than the tuner's busy one.)

    python benchmarks/bench_optim.py [--evals 2000] [--repeats 7] [--cold-evals 40]
                                [--disturb experiment|stream]

``main() -> dict`` (for ``benchmarks/run_all.py``) returns a flat dict of medians in us per
evaluation: ``{algo: hot_us, f'{algo}_cold': cold_us}`` for every algo of ``ALGOS``, i.e.
``{'spsa': ..., 'spsa_cold': ..., 'necga': ..., 'necga_cold': ..., 'cga': ...,
'cga_cold': ..., 'pecga': ..., 'pecga_cold': ..., 'rcga': ..., 'rcga_cold': ...}``
(without the ``_cold`` keys when called with ``cold_evals=0``).  See docs/optimisers.md
("Speed").
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

# the numeric baseline (set by im_drive_sim before numpy loads), as in the nodes; a source
# checkout without the package: the fallback below
with contextlib.suppress(ImportError):
    import im_drive_sim  # noqa: F401

# isort: split
import numpy as np

try:
    from im_tuner.optim import ALGOS, make_optimizer
except ImportError:  # running from a source checkout without installing the package
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'src' / 'im_tuner'))
    from im_tuner.optim import ALGOS, make_optimizer

DIM = 5
TARGET = np.linspace(0.2, 0.8, DIM)


def bench_algo(algo: str, evals: int = 2000, repeats: int = 7) -> float:
    """Hot: median over ``repeats`` batches of the mean ask+tell time per evaluation [us]."""
    opt = make_optimizer(algo, DIM, seed=1)

    def batch() -> float:
        t0 = time.perf_counter_ns()
        for _ in range(evals):
            u = opt.ask()
            d = u - TARGET
            opt.tell(u, float(d @ d))
        return (time.perf_counter_ns() - t0) / evals / 1e3

    batch()  # warm-up (imports, caches)
    return statistics.median(batch() for _ in range(repeats))


def make_disturbance(
    kind: str = 'experiment', sleep_s: float = 0.0
) -> tuple[Callable[[], None], Callable[[], None]]:
    """(disturb, close): ``disturb()`` evicts the caches as the tuner's loop does between
    optimiser calls (see the module docstring), then sleeps ``sleep_s`` (0: none);
    ``close()`` removes its scratch file."""
    fd, path = tempfile.mkstemp(prefix='bench_optim_', suffix='.log')
    line = b'x' * 600 + b'\n'  # about one results.jsonl record
    if kind == 'experiment':
        from im_controller.config import Gains
        from im_drive_sim.sim import DriveSim
        from im_tuner.offline import run_experiment_offline

        sim = DriveSim()
        run_experiment_offline(sim, Gains())  # compiles/loads the kernels

        def work() -> None:
            run_experiment_offline(sim, Gains(), record=True)
    elif kind == 'stream':
        big = np.ones(4 * 1024 * 1024)  # 32 MB

        def work() -> None:
            big.sum()
    else:
        raise ValueError(f'unknown disturbance {kind!r} (experiment or stream)')

    def disturb() -> None:
        work()
        os.write(fd, line)
        os.fsync(fd)
        if sleep_s > 0.0:
            time.sleep(sleep_s)

    def close() -> None:
        os.close(fd)
        os.unlink(path)

    return disturb, close


def bench_cold(
    algo: str, disturb: Callable[[], None], evals: int = 40
) -> tuple[float, float, float]:
    """Cold: medians over ``evals`` evaluations of (ask + tell, ask, tell) [us], each call
    timed alone after ``disturb()``."""
    opt = make_optimizer(algo, DIM, seed=1)
    total, ask_us, tell_us = [], [], []
    for _ in range(evals):
        disturb()
        t0 = time.perf_counter()
        u = opt.ask()
        t1 = time.perf_counter()
        record = [float(x) for x in u]  # the tuner records u and tells it back
        d = u - TARGET
        loss = float(d @ d)
        disturb()
        u_told = np.asarray(record, dtype=float)
        t2 = time.perf_counter()
        opt.tell(u_told, loss)
        t3 = time.perf_counter()
        ask_us.append(1e6 * (t1 - t0))
        tell_us.append(1e6 * (t3 - t2))
        total.append(ask_us[-1] + tell_us[-1])
    return (statistics.median(total), statistics.median(ask_us), statistics.median(tell_us))


def main(
    evals: int = 2000,
    repeats: int = 7,
    verbose: bool = True,
    cold_evals: int = 40,
    disturb: str = 'experiment',
) -> dict[str, float]:
    """Run every algorithm hot, then cold; returns ``{algo: hot_us, f'{algo}_cold':
    cold_us}`` (medians, us per evaluation; no ``_cold`` keys if ``cold_evals`` is 0)."""
    hot = {algo: bench_algo(algo, evals, repeats) for algo in ALGOS}
    cold: dict[str, tuple[float, float, float]] = {}
    if cold_evals > 0:
        if disturb == 'experiment':
            try:
                import im_controller.runner  # noqa: F401
                import im_drive_sim.sim  # noqa: F401
            except ImportError:
                disturb = 'stream'
        fn, close = make_disturbance(disturb)
        try:
            cold = {algo: bench_cold(algo, fn, cold_evals) for algo in ALGOS}
        finally:
            close()
    if verbose:
        print(
            f'optimiser ask+tell, dim={DIM}, default options, us per evaluation (target: '
            f'well below 50 cold)\n  hot: median of {repeats} batch means x {evals} '
            f'evaluations back to back'
        )
        if cold:
            print(
                f'  cold: median of {cold_evals} evaluations, caches evicted before every '
                f'call ({disturb} + fsync), as in the tuning run'
            )
        for algo, us in hot.items():
            line = f'  {algo:6s} hot {us:6.2f}'
            if algo in cold:
                c, a, t = cold[algo]
                line += f'   cold {c:6.1f}  (ask {a:5.1f}, tell {t:5.1f})'
            print(line)
    res: dict[str, float] = {}
    for algo in ALGOS:
        res[algo] = hot[algo]
        if algo in cold:
            res[f'{algo}_cold'] = cold[algo][0]
    return res


if __name__ == '__main__':
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--evals', type=int, default=2000, help='hot: evaluations per batch')
    ap.add_argument('--repeats', type=int, default=7, help='hot: batches')
    ap.add_argument(
        '--cold-evals', type=int, default=40, help='cold: evaluations (0: skip the cold figures)'
    )
    ap.add_argument(
        '--disturb',
        choices=('experiment', 'stream'),
        default='experiment',
        help='cold: what evicts the caches between calls',
    )
    a = ap.parse_args()
    main(a.evals, a.repeats, cold_evals=a.cold_evals, disturb=a.disturb)
