"""What N held periods do to a loss: the measurement behind the default
``timing_tolerance`` (``python research/held.py``, docs/real-drive.md
"Timing tolerance").

A drive that cannot pause holds its last command over every period its loop starts too
late for; the controller never sees the states of those periods. Here the same happens
on the pure core, exactly as in the real-time loop: the plant steps with the command
held, the controller's kernel gets the next state it would have seen
(``ExperimentRunner.step``), and the experiment counts the periods ``held``.

For each drive profile (``ideal``, ``bench``), gains (the hand-tuned start; the faster
gains of docs/real-drive.md) and number N of held periods -- placed at seeded random instants
of the 1.125 s move, one at a time (a slightly late loop) or all in one burst (one
stall of N periods, the worst case) -- it runs the same experiment (the same noise seed)
with and without them and reports the paired change of the loss, |dL|/L (median, 95th
percentile, worst over the seeds), beside the spread of the loss over the seeds with no
held period (the bench's own noise, the coefficient of variation). The default tolerance
is the largest N whose 95th-percentile change on ``ideal`` (the held periods' own effect)
stays below the ``bench`` noise (:func:`default_tolerance`).

Written by hand: a loop of the pure core's public steps (``DriveSim.step_into``,
``ExperimentRunner.step``); no library injects late periods into a drive model.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from im_controller.config import Gains
from im_controller.layout import Q_N, Q_SETTLE_N, STATUS_DONE
from im_controller.runner import ExperimentRunner, config_for_drive
from im_drive_sim.drive_file import load_config
from im_drive_sim.params import DriveConfig
from im_drive_sim.sim import DriveSim

__all__ = ['HeldRow', 'loss_with_held', 'main', 'measure']

#: gains measured: the hand-tuned start, and the faster gains of docs/real-drive.md's example
GAINS: dict[str, Gains] = {
    'start': Gains(),
    'fast': Gains(k_pw=0.9, k_iw=60.0, k_pos=45.0, tau_sm=0.003, tau_eq=0.004),
}
COUNTS = (1, 2, 5, 10, 20, 50)
SHAPES = ('spread', 'burst')


def drive_for(profile: str) -> DriveConfig:
    return load_config(overrides={'realism': profile})


def loss_with_held(
    drive: DriveConfig, gains: Gains, seed: int, held_at: Sequence[tuple[int, int]]
) -> tuple[float, int]:
    """The loss of one experiment from rest (noise seed ``seed``) with ``held_at``: (i, m)
    = after the controller's i-th answer of the experiment (its settle included), m
    periods go by with that command held, unseen. Returns (loss, held periods counted)."""
    sim = DriveSim(drive, seed=seed)
    sim.reset(omega=0.0, fluxed=True)
    runner = ExperimentRunner(config_for_drive(None, sim), gains)
    runner.reset(sim.theta_meas)
    runner.start(0)
    state = np.zeros(14)
    sim.read_into(state)
    misses = dict(held_at)
    i = 0
    while True:
        isq, load, st = runner.step(state)
        if st >= STATUS_DONE:
            break
        sim.step_into(isq, load, state)
        for _ in range(misses.get(i, 0)):
            sim.step_into(isq, load, state)
        i += 1
    res = runner.result()
    assert res is not None
    return res.loss, res.held


def _instants(rng: np.random.Generator, settle: int, n: int, count: int, shape: str) -> list:
    """Where the held periods go: inside the move (step settle .. settle + n)."""
    if shape == 'burst':
        return [(int(rng.integers(settle, settle + n - count)), count)]
    picks = rng.choice(np.arange(settle, settle + n - 1), size=count, replace=False)
    return [(int(p), 1) for p in sorted(picks)]


@dataclass
class HeldRow:
    profile: str
    gains: str
    shape: str
    count: int
    median: float  #: |dL|/L, paired with the same seed without held periods
    p95: float
    worst: float
    counted: int  #: held periods the experiment counted (the same for every seed)


def _one(args: tuple[str, str, int, str, int]) -> tuple[str, str, str, int, int, float, int]:
    profile, gname, count, shape, seed = args
    drive = drive_for(profile)
    sim = DriveSim(drive, seed=seed)
    runner = ExperimentRunner(config_for_drive(None, sim), GAINS[gname])
    settle, n = int(runner.Q[Q_SETTLE_N]), int(runner.Q[Q_N])
    rng = np.random.default_rng([seed, count, SHAPES.index(shape)])
    held_at = _instants(rng, settle, n, count, shape) if count else []
    loss, held = loss_with_held(drive, GAINS[gname], seed, held_at)
    return profile, gname, shape, count, seed, loss, held


def measure(
    profiles: Sequence[str], seeds: int, counts: Sequence[int] = COUNTS, workers: int = 2
) -> tuple[list[HeldRow], dict[tuple[str, str], float]]:
    """The rows (module docstring) and, per (profile, gains), the noise: the coefficient
    of variation of the loss over the seeds with no held period."""
    jobs = [
        (p, g, c, s, seed)
        for p in profiles
        for g in GAINS
        for c in (0, *counts)
        for s in (SHAPES if c else SHAPES[:1])
        for seed in range(seeds)
    ]
    with ProcessPoolExecutor(workers) as pool:
        out = list(pool.map(_one, jobs, chunksize=4))
    base = {(p, g, seed): loss for p, g, _, c, seed, loss, _ in out if c == 0}
    noise = {}
    for p in profiles:
        for g in GAINS:
            x = np.array([base[(p, g, s)] for s in range(seeds)])
            noise[(p, g)] = float(x.std(ddof=1) / x.mean())
    rows = []
    for p in profiles:
        for g in GAINS:
            for c in counts:
                for shape in SHAPES:
                    sel = [o for o in out if o[:4] == (p, g, shape, c)]
                    d = np.array([abs(o[5] / base[(p, g, o[4])] - 1.0) for o in sel])
                    stats = (float(np.median(d)), float(np.quantile(d, 0.95)), float(d.max()))
                    rows.append(HeldRow(p, g, shape, c, *stats, int(sel[0][6])))
    return rows, noise


def default_tolerance(rows: Sequence[HeldRow], noise: dict[tuple[str, str], float]) -> int:
    """The largest N whose effect -- the 95th-percentile |dL|/L on the ``ideal`` profile,
    where nothing but the held periods changes the loss -- stays below the ``bench``
    noise (the spread of repeated experiments), for every gains and both shapes. (On
    ``bench`` a held period also shifts the noise stream, so the paired change there is
    mostly noise itself.)"""
    ok = 0
    for c in sorted({r.count for r in rows}):
        sel = [r for r in rows if r.profile == 'ideal' and r.count == c]
        if sel and all(r.p95 < noise[('bench', r.gains)] for r in sel):
            ok = c
        else:
            break
    return ok


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog='python research/held.py',
        description='What N held periods do to a loss (the default timing_tolerance).',
    )
    ap.add_argument('--seeds', type=int, default=20, help='noise seeds per cell (default 20)')
    ap.add_argument('--workers', type=int, default=2)
    ap.add_argument('--profiles', default='ideal,bench')
    a = ap.parse_args(argv)
    if a.seeds < 3 or a.workers < 1:
        ap.error('--seeds >= 3 and --workers >= 1')
    profiles = a.profiles.split(',')
    rows, noise = measure(profiles, a.seeds, workers=a.workers)
    print('| profile | gains | held periods | placed | counted | median dL/L | p95 | worst |')
    print('|---|---|---|---|---|---|---|---|')
    for r in rows:
        print(
            f'| {r.profile} | {r.gains} | {r.count} | {r.shape} | {r.counted} | '
            f'{100 * r.median:.3f} % | {100 * r.p95:.3f} % | {100 * r.worst:.3f} % |'
        )
    print()
    for (p, g), cv in noise.items():
        print(f'noise ({p}, {g}): the loss varies by {100 * cv:.2f} % (CV over {a.seeds} seeds)')
    if {'ideal', 'bench'} <= set(profiles):
        print(f'default tolerance: {default_tolerance(rows, noise)} held periods')
    return 0


if __name__ == '__main__':
    sys.exit(main())
