"""Where the composed loop's p99 and worst lateness come from: the loop in the tuner's
process against the same loop alone in a process of its own (a measurement prototype,
docs/real-drive.md, "What it bought on this machine").

A: ``tuner --bench realtime --no-record --lock-memory`` (SCHED_FIFO 50 by default).
B: this script with ``--host`` builds the same ``RealtimeBench`` (drive and controller
composed, SCHED_FIFO 50, memory locked) and serves it until SIGTERM; ``tuner --bench
none --no-record`` tunes it over DDS from another process. Run back to back, A then B,
``--pairs`` times; ``--hogs N`` busy processes beside both. Prints each loop's overruns,
per-period work p50 / p99 / max and worst lateness (the host also its drive and
controller parts).

    .venv/bin/python research/loop_own_process.py --budget 10 --pairs 3 [--hogs 2]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
FIELDS = ('periods', 'overruns', 'max_lateness_us', 'period_work_us', 'lateness_us')
PARTS = ('drive_period_us', 'controller_answer_us')


def host() -> None:
    import rclpy

    from im_drive_sim import rt
    from im_tuner.bench.realtime import RealtimeBench

    rclpy.init()
    stop: list[int] = []
    signal.signal(signal.SIGTERM, lambda *_a: stop.append(1))
    bench = RealtimeBench(rt_options=rt.RtOptions(50, -1, True))
    print('ready', flush=True)
    bench.spin_until(lambda: bool(stop))
    bench.stop_loop()
    t = bench.timing()
    print(json.dumps({k: t[k] for k in FIELDS + PARTS}), flush=True)
    bench.destroy()
    rclpy.shutdown()


def line(tag: str, d: dict) -> str:
    w = d['period_work_us']
    parts = ''.join(f', {k} {d[k]["p50"]} / {d[k]["p99"]}' for k in PARTS if d.get(k) is not None)
    return (
        f'{tag}: overruns {d["overruns"]} of {d["periods"]} '
        f'({100 * d["overruns"] / d["periods"]:.3f} %), work p50 / p99 / max '
        f'{w["p50"]} / {w["p99"]} / {w["max"]} us, worst lateness '
        f'{d["max_lateness_us"] / 1000:.1f} ms{parts}'
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--host', action='store_true', help=argparse.SUPPRESS)
    ap.add_argument('--budget', type=int, default=10)
    ap.add_argument('--pairs', type=int, default=3)
    ap.add_argument('--hogs', type=int, default=0)
    args = ap.parse_args()
    if args.host:
        host()
        return
    env = {**os.environ, 'ROS_DOMAIN_ID': os.environ.get('ROS_DOMAIN_ID', '91')}
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    hogs = [subprocess.Popen([sys.executable, '-c', 'while True: pass']) for _ in range(args.hogs)]
    tuner = [ROS2, 'run', 'im_tuner', 'tuner', '--budget', str(args.budget), '--no-record']
    try:
        for seed in range(1, args.pairs + 1):
            with tempfile.TemporaryDirectory() as tmp:
                a = Path(tmp) / 'a'
                subprocess.run(
                    [
                        *tuner,
                        '--bench',
                        'realtime',
                        '--lock-memory',
                        '--seed',
                        str(seed),
                        '--quiet',
                        '--out',
                        str(a),
                    ],
                    env=env,
                    capture_output=True,
                    check=True,
                )
                d = json.loads((a / 'summary.json').read_text())['sessions'][0]['drive']['loop']
                print(line(f'pair {seed} A, in the tuner', d), flush=True)
                h = subprocess.Popen(
                    [sys.executable, __file__, '--host'],
                    env=env,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.DEVNULL,
                    text=True,
                )
                assert h.stdout is not None and h.stdout.readline().strip() == 'ready'
                subprocess.run(
                    [
                        *tuner,
                        '--bench',
                        'none',
                        '--seed',
                        str(seed),
                        '--quiet',
                        '--out',
                        str(Path(tmp) / 'b'),
                    ],
                    env=env,
                    capture_output=True,
                    check=True,
                )
                h.send_signal(signal.SIGTERM)  # by PID
                out, _ = h.communicate(timeout=60)
                print(line(f'pair {seed} B, own process', json.loads(out.splitlines()[-1])))
    finally:
        for p in hogs:
            p.kill()
            p.wait()


if __name__ == '__main__':
    main()
