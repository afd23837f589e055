"""The live view's cost on the real-time bench: tuning runs with ``--live`` and a frozen
client beside the same runs without, side by side, beside the host's floor.

    .venv/bin/python benchmarks/bench_live.py [--pairs 4] [--budget 6] [--floor-seconds 10]

Each pair is, in turn: the host's floor for a 5 kHz loop (``host_check``'s measurement,
benchmarks/loop_floor.py, ``--floor-seconds``), then ``tuner --bench realtime --budget N``
without ``--live`` and the same run with ``--live PORT`` and a Foxglove WebSocket client
connected for the whole run, subscribed to every channel and never reading its socket
(test/live_client.py's ``FrozenClient``, a 4 kB receive buffer): the worst client the
server can have. The two runs swap places from one pair to the next (plain-live,
live-plain, ...), so that a host growing louder or quieter over the minutes weighs on
both alike.

Prints, per run, the drive's overruns (period starts more than a period late), held and
late periods, the per-period work p99, the experiments flagged timing and the messages the
bag lost; then the overruns of all live runs over those of all plain runs (target <= 1.2,
docs/foxglove.md) with a 90 % bootstrap interval over the pairs (how much two runs of one
command differ on this host), the floor's overruns in the same minutes, and the live
messages dropped for the frozen client. (A real-time run's losses and message counts are
not the same from one run to the next even without ``--live``: the host's timing differs;
the lock-step bench's are, and test/test_live.py asserts them equal with a frozen client.)
``main() -> dict`` returns the figures for run_all.py.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_realtime
import loop_floor
import numpy as np


def _ratio(a: float, b: float) -> float:
    """a / b, 1 where both are 0 (no overrun either way), inf where only b is."""
    if b == 0:
        return 1.0 if a == 0 else float('inf')
    return a / b


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--pairs', type=int, default=4)
    ap.add_argument('--budget', type=int, default=6)
    ap.add_argument('--floor-seconds', type=float, default=10.0)
    args = ap.parse_args(argv if argv is not None else [])
    runs: dict[bool, list[dict]] = {False: [], True: []}
    floors: list[dict] = []
    for i in range(args.pairs):
        floors.append(f := loop_floor.measure(args.floor_seconds))
        print(
            f'pair {i + 1} floor: overruns {f["overruns"]} ({f["overrun_pct"]:.3f} %) of '
            f'{f["periods"]} periods, worst lateness {f["max_lateness_us"]:.0f} us',
            flush=True,
        )
        order = (False, True) if i % 2 == 0 else (True, False)
        for live in order:
            r = bench_realtime.run_once('realtime', args.budget, 1 + i, live=live)
            runs[live].append(r)
            print(
                f'pair {i + 1} {"live " if live else "plain"}: overruns {r["overruns"]} '
                f'({r["overrun_pct"]:.3f} %), held or late {r["held_late_pct"]:.3f} %, work p99 '
                f'{r["work"]["p99"]:.0f} us, flagged timing {r["timing_flagged"]}, bag lost '
                f'{r["bag_lost"]}, exit {r["exit"]}'
                + (
                    f'; live sent {r["live"].get("sent")} dropped {r["live"].get("dropped")}'
                    if live
                    else ''
                ),
                flush=True,
            )

    def total(live: bool, key: str) -> float:
        return float(sum(r[key] for r in runs[live]))

    periods = {live: total(live, 'periods') for live in (False, True)}
    fig = {
        'live_overruns': total(True, 'overruns'),
        'live_plain_overruns': total(False, 'overruns'),
        'live_overrun_pct': 100.0 * total(True, 'overruns') / periods[True],
        'live_plain_overrun_pct': 100.0 * total(False, 'overruns') / periods[False],
        'live_floor_overrun_pct': 100.0
        * sum(f['overruns'] for f in floors)
        / sum(f['periods'] for f in floors),
        'live_work_p99_us': statistics.median(r['work']['p99'] for r in runs[True]),
        'live_plain_work_p99_us': statistics.median(r['work']['p99'] for r in runs[False]),
        'live_dropped': statistics.median(r['live'].get('dropped', 0) for r in runs[True]),
        'live_bag_lost': total(True, 'bag_lost'),
        'live_timing_flagged': total(True, 'timing_flagged'),
        'live_plain_timing_flagged': total(False, 'timing_flagged'),
    }
    fig['live_overrun_ratio'] = _ratio(fig['live_overrun_pct'], fig['live_plain_overrun_pct'])
    # how far the ratio moves with the pairs drawn: a 90 % bootstrap interval over the pairs
    # (seeded), the host's own scatter between two runs of the same command
    over = np.array([[r['overruns'] for r in runs[live]] for live in (False, True)], float)
    per = np.array([[r['periods'] for r in runs[live]] for live in (False, True)], float)
    draws = np.random.default_rng(0).integers(0, args.pairs, (10_000, args.pairs))
    boot = [
        _ratio(over[1, d].sum() / per[1, d].sum(), over[0, d].sum() / per[0, d].sum())
        for d in draws
    ]
    fig['live_overrun_ratio_lo'], fig['live_overrun_ratio_hi'] = np.quantile(boot, [0.05, 0.95])
    print(
        f'live view, {args.pairs} pairs of --budget {args.budget} real-time runs: overruns '
        f'{fig["live_overruns"]:.0f} ({fig["live_overrun_pct"]:.3f} %) with --live and a frozen '
        f'client, {fig["live_plain_overruns"]:.0f} ({fig["live_plain_overrun_pct"]:.3f} %) '
        f'without: x{fig["live_overrun_ratio"]:.2f} [{fig["live_overrun_ratio_lo"]:.2f}, '
        f'{fig["live_overrun_ratio_hi"]:.2f}] (target <= 1.2); the floor in the same '
        f'minutes {fig["live_floor_overrun_pct"]:.3f} %; work p99 '
        f'{fig["live_work_p99_us"]:.0f} / {fig["live_plain_work_p99_us"]:.0f} us; live '
        f'messages dropped for the frozen client {fig["live_dropped"]:.0f} (median); '
        f'experiments flagged timing {fig["live_timing_flagged"]:.0f} / '
        f'{fig["live_plain_timing_flagged"]:.0f}; bag messages lost with --live '
        f'{fig["live_bag_lost"]:.0f}',
        flush=True,
    )
    return fig


if __name__ == '__main__':
    main(sys.argv[1:])
