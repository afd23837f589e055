"""``ros2 run im_drive_sim host_check [--seconds N] [--json]``: can this host run a 5 kHz
drive loop, and at which timing tolerance? Run it first, on the machine that will run
the loop (docs/real-drive.md, "Check the host first").

It runs the composed loop's own wait for N seconds (:mod:`.host`) and prints what it
measured and the verdict (``--json``: one JSON object on stdout); exit 0 with a verdict
either way.
"""

from __future__ import annotations

import argparse
import json
import sys

from . import host, rt
from .cli import Parser, finite_float, int_in, run_cli

PROG = 'host_check'


def parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog='ros2 run im_drive_sim host_check',
        description=(__doc__ or '').split('\n\n')[0].split(': ', 1)[1],
        epilog='docs/real-drive.md, "Check the host first"',
    )
    ap.add_argument(
        '--seconds',
        type=finite_float(0.5, 3600.0, unit='s'),
        default=10.0,
        metavar='S',
        help='how long to run the loop [s] (0.5-3600, default 10; an experiment is 1.125 s)',
    )
    ap.add_argument(
        '--timing-tolerance',
        type=int_in(0, 1_000_000),
        default=10,
        metavar='N',
        help="the tolerance to judge [held periods per experiment] (default 10, the tuner's)",
    )
    ap.add_argument(
        '--spin-us',
        type=finite_float(0.0, 200.0, unit='us'),
        default=host.SPIN_US,
        metavar='US',
        help=f'busy-wait before each period start [us] (0: sleep only; 200: spin only; '
        f"default {host.SPIN_US:g}, the composed loop's)",
    )
    ap.add_argument('--json', action='store_true', help='one JSON object on stdout')
    rt.add_arguments(ap, 'the loop', default_priority=rt.DEFAULT_PRIORITY)
    return ap


def describe(f: host.HostFloor) -> list[str]:
    """The human report of one measurement (the lines ``host_check`` prints)."""
    r = f.realtime
    lines = [
        f"host_check: {f.seconds:.1f} s of the 5 kHz loop's wait ({r.get('policy')} "
        f'priority {r.get("priority")}, CPUs {r.get("affinity")}, CPU latency request held '
        f'{r.get("pm_qos", {}).get("held")}, memory locked {r.get("memory_locked")}, '
        f'spin {f.spin_us:g} us)',
        f'periods {f.periods}: late {f.overruns} ({f.late_pct:.3f} %, {f.late_per_s:.1f}/s), '
        f'held {f.held} ({f.held_pct:.3f} %), worst start {f.max_lateness_us:.0f} us late',
        'lateness: ' + ', '.join(f'{k} {v}' for k, v in f.histogram.items()),
        'bursts of held periods: '
        + ', '.join(f'{k}: {v}' for k, v in f.bursts.items())
        + f'; longest {f.longest_burst}',
    ]
    h = f.held_per_experiment
    guess = ' (from the rate: measure longer than 1.125 s)' if h['from'] == 'rate' else ''
    lines.append(
        f'held periods per 1.125 s experiment: p50 {h["p50"]:.0f}, p95 {h["p95"]:.0f}, '
        f'max {h["max"]:.0f}{guess}'
    )
    change = host.loss_change_words(f.tolerance, noise=True)
    if f.meets:
        lines.append(
            f'verdict: {100 * f.share_meeting:.0f} % of experiments meet --timing-tolerance '
            f'{f.tolerance_checked}; 95 % meet {f.tolerance} ({change})'
        )
    else:
        lines.append(
            f'verdict: this host cannot meet --timing-tolerance {f.tolerance_checked} '
            f'({100 * f.share_meeting:.0f} % of experiments would): 95 % meet '
            f'{f.tolerance} ({change}); tune with `tuner --bench realtime --timing-tolerance '
            'auto`, or quieten the host and check again with --seconds 60 (docs/real-drive.md, '
            '"Check the host first")'
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(sys.argv[1:] if argv is None else argv)
    opts = rt.RtOptions.from_cli(args, rt.DEFAULT_PRIORITY)
    if not args.json:
        print(f'host_check: running the loop for {args.seconds:g} s ...', flush=True)
    floor = host.probe(args.seconds, opts, args.timing_tolerance, args.spin_us)
    for line in floor.realtime.get('refused', []):
        print(f'warning: {line}', file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(floor.as_dict()))
    else:
        print('\n'.join(describe(floor)), flush=True)
    return 0


def entry() -> int:
    """The executable (``ros2 run``: :mod:`im_drive_sim.launch`)."""
    return run_cli(PROG, main)


if __name__ == '__main__':
    from .cli import executable

    executable(PROG, entry)
