"""The machine's floor for a 5 kHz loop: the composed loop's own wait for each period
start (``im_drive_sim.loop_clock.wait_start``: clock_nanosleep to 40 us before, then a
busy-wait), run in a compiled loop that does nothing else and never touches Python,
SCHED_FIFO 50, memory locked, the CPU latency request held, timer slack 1 ns -- what the
hypervisor and the kernel leave a real-time thread here. It is ``host_check``'s
measurement (``im_drive_sim.host.probe``), run twice: alone and beside ``--hogs`` busy
processes. The composed bench can do no better than this; what it measures beyond it is
its own (docs/real-drive.md, "What it bought on this machine").

    .venv/bin/python benchmarks/loop_floor.py [--seconds 30] [--hogs 2]

(each of the two runs lasts ``--seconds``: about 2 x 30 s with the defaults; a bad value is
one line on stderr, exit 2).

Prints the overruns (starts more than a period late), the worst lateness and the
lateness histogram (pacing.LATENESS_BINS), with and without ``--hogs`` busy processes.
"""

from __future__ import annotations

import argparse
import subprocess
import sys

import im_drive_sim  # noqa: F401 (the numeric baseline, set before numpy loads)

# isort: split
from im_drive_sim import host, rt
from im_drive_sim.cli import Parser, UsageError, finite_float, int_in, run_cli

TS_NS = 200_000


def measure(seconds: float) -> dict:
    f = host.probe(seconds, rt.RtOptions(50, -1, True))
    for line in f.realtime.get('refused', []):
        print(f'warning: {line}', file=sys.stderr)
    return {
        'periods': f.periods,
        'overruns': f.overruns,
        'overrun_pct': f.late_pct,
        'held': f.held,
        'max_lateness_us': f.max_lateness_us,
        'lateness_histogram': f.histogram,
        'tolerance': f.tolerance,
        'pm_qos_held': f.realtime['pm_qos']['held'],
    }


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line; a bad value raises ``UsageError`` (one line, exit 2 in ``main``)."""
    ap = Parser(description=__doc__.splitlines()[0])
    ap.add_argument(
        '--seconds',
        type=finite_float(0.0, 3600.0, lo_open=True, unit='s'),
        default=30.0,
        help='length of each run [s] (0 < s <= 3600)',
    )
    ap.add_argument(
        '--hogs', type=int_in(0, 64), default=2, help='busy processes beside the second run'
    )
    args = ap.parse_args(argv)
    if int(args.seconds * 1e9 / TS_NS) < 1:
        raise UsageError(f'--seconds {args.seconds:g}: shorter than one period (200 us)')
    return args


def main(argv: list[str] | None = None) -> dict:
    args = parse(argv)
    print(
        f'loop_floor: two runs of {args.seconds:g} s (0 and {args.hogs} hogs): about '
        f'{2 * args.seconds + 5:.0f} s',
        flush=True,
    )
    out = {}
    for hogs in (0, args.hogs):
        procs = [
            # at normal priority (chrt -o 0): a child inherits this thread's SCHED_FIFO,
            # and two FIFO hogs would starve the machine
            subprocess.Popen(['chrt', '-o', '0', sys.executable, '-c', 'while True: pass'])
            for _ in range(hogs)
        ]
        try:
            r = measure(args.seconds)
        finally:
            for p in procs:  # by PID
                p.kill()
                p.wait(timeout=10)
        out[f'hogs_{hogs}'] = r
        print(
            f'floor, {hogs} hogs: {r["periods"]} periods, overruns {r["overruns"]} '
            f'({r["overrun_pct"]:.3f} %), held {r["held"]}, worst lateness '
            f'{r["max_lateness_us"]:.0f} us, {r["lateness_histogram"]}; 95 % of experiments '
            f'meet --timing-tolerance {r["tolerance"]}'
        )
    return out


if __name__ == '__main__':
    sys.exit(run_cli('loop_floor', lambda: (main(sys.argv[1:]), 0)[1]))
