"""The real bench at 5 kHz, timed: real-time tuning runs, recording on.

Each run is the real command, ``ros2 run im_tuner tuner --bench B --budget N`` (a child
process, recorder on, a fresh run directory), on these benches and drive modes:

* ``realtime``: the composed bench -- drive simulator and controller in the tuner's
  process, one wall-clock loop (im_tuner.bench.realtime);
* ``realtime-hardware-like``, ``realtime-example-drive``: the composed bench with a drive
  that cannot pause (the simulator's ``hardware_like`` mode; the example drive): a late
  period is periods held with the old current (``missed``), the experiments with any are
  flagged ``timing`` (what a real drive would see on this machine);
* ``realtime-processes``: drive, controller and recorder as separate processes (how a
  drive in its own process runs); experiments a controller answered late are flagged
  ``timing`` and re-run (--retries 1 here: the figure is the timing, not the search);
* the load scenario: the composed loop runs SCHED_FIFO 50 by default (as
  ros2_control_node), so ``realtime`` is the quiet reference; ``realtime-sched-other``
  the same under the normal policy (``--thread-priority 0``); ``realtime-rt`` with the
  memory locked too (``--thread-priority 50 --lock-memory``); ``realtime-hogs`` next to
  two CPU hogs (busy processes at normal priority, ended by PID) under the normal policy,
  ``realtime-hogs-rt`` with ``--thread-priority 50 --lock-memory``;
  ``realtime-frozen-reader`` next to a reliable KEEP_ALL reader of every drive and
  controller topic (frozen_reader.py) frozen with SIGSTOP from its 100th state to the
  run's end. For every composed mode: the tuner's memory growth from its first result
  to its end (``rss_growth_mb``), the messages the loop's outbox could not deliver (to
  DDS readers, and to the bag), the period-start lateness p99; overruns and period work
  also as ratios to the quiet ``realtime`` run.

From each run's ``summary.json`` (the drive's own counters, and the composed loop's
per-period timings) and ``results.jsonl``:

* held and late periods, in % of all the drive's periods (target <= 0.1 % on the composed
  bench), overruns (periods that started more than a period late) and watchdog trips;
* per-period work of the composed loop, p50/p99/max [us] against the 200 us budget, and
  the controller's answer latency (state taken -> command out) p50/p99 [us];
* experiments that ran exactly 5625 drive periods, and those flagged timing.

Medians over ``--runs`` runs (3). Run: ``.venv/bin/python benchmarks/bench_realtime.py
[--budget 20] [--runs 3]`` (part of ``make bench``). ``main() -> dict`` returns the
figures for run_all.py.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import select
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# the live view's frozen client is the tests' (test/live_client.py)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'test'))
from live_client import FrozenClient

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
#: name -> (tuner --bench, extra tuner arguments, figure tag). The drive modes of the
#: composed bench: the simulator that pauses while the loop is late (its model time
#: waits), the simulator in its hardware-like mode and the example drive (they cannot
#: pause: a late period start follows periods held with the old current, counted
#: ``missed`` and held, so experiments with any are flagged timing and re-run).
MODES: dict[str, tuple[str, list[str], str]] = {
    'realtime': ('realtime', [], 'rt_composed'),
    'realtime-hardware-like': (
        'realtime',
        ['--retries', '1', '--ros-args', '-p', 'hardware_like:=true'],
        'rt_hwlike',
    ),
    'realtime-example-drive': (
        'realtime',
        ['--retries', '1', '--drive', 'example', '--fault-policy', 'reset'],
        'rt_example',
    ),
    'realtime-processes': ('realtime-processes', ['--retries', '1'], 'rt_processes'),
    # the composed loop runs SCHED_FIFO 50 by default (as ros2_control_node): the quiet
    # `realtime` row; `--thread-priority 0` is the normal policy
    'realtime-sched-other': ('realtime', ['--thread-priority', '0'], 'rt_other'),
    'realtime-rt': ('realtime', ['--thread-priority', '50', '--lock-memory'], 'rt_fifo'),
    'realtime-hogs': ('realtime', ['--thread-priority', '0'], 'rt_hogs'),
    'realtime-hogs-rt': ('realtime', ['--thread-priority', '50', '--lock-memory'], 'rt_hogs_fifo'),
    'realtime-frozen-reader': ('realtime', [], 'rt_frozen'),
    # a plant on the wall clock (the example drive) next to two CPU hogs, the loop with
    # --thread-priority 50 --lock-memory: what a real drive gets on a loaded machine
    'realtime-example-drive-hogs-rt': (
        'realtime',
        [
            *('--retries', '1', '--drive', 'example', '--fault-policy', 'reset'),
            *('--thread-priority', '50', '--lock-memory'),
        ],
        'rt_example_hogs_fifo',
    ),
}
FROZEN_READER = str(Path(__file__).with_name('frozen_reader.py'))
#: the topics a live client waits for before it subscribes (the 5 kHz ones and the loss)
LIVE_TOPICS = ('/drive/state', '/drive/command', '/controller/internals', '/controller/loss')
BENCHES = tuple(MODES)
#: the load scenario: CPU hogs (busy Python processes, normal priority) beside the run
HOGS = {'realtime-hogs': 2, 'realtime-hogs-rt': 2, 'realtime-example-drive-hogs-rt': 2}


def start_hogs(n: int) -> list[subprocess.Popen]:
    return [
        subprocess.Popen([sys.executable, '-c', 'while True: pass'], stdin=subprocess.DEVNULL)
        for _ in range(n)
    ]


def stop_hogs(hogs: list[subprocess.Popen]) -> None:
    for h in hogs:  # by PID
        h.kill()
        h.wait(timeout=10)


def _rss_kib(pid: int) -> int:
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _run_tuner(
    cmd: list[str], env: dict, frozen: bool, run: Path, live_port: int = 0
) -> tuple[int, str, float]:
    """Run the tuner; with ``frozen``, next to a reader frozen (SIGSTOP) from its 100th
    state on; with ``live_port``, next to a live-view client (test/live_client.py's
    FrozenClient) connected to the tuner's ``--live`` server, subscribed to every channel
    and never reading. Returns (exit code, stderr, the tuner's RSS growth [MB] from its
    first result (``run``/results.jsonl, the reference experiment: start-up done) to its
    end: in every mode, so the frozen run's growth compares with the quiet run's)."""
    reader = client = None
    if frozen:
        reader = subprocess.Popen(
            [sys.executable, FROZEN_READER],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            env=env,
        )
    growth = 0.0
    with tempfile.TemporaryFile('w+') as err:
        tuner = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, text=True, env=env)
        try:
            if live_port:
                client = FrozenClient(live_port, set(LIVE_TOPICS), 120.0)
            if reader is not None:
                assert reader.stdout is not None
                ready, _, _ = select.select([reader.stdout], [], [], 120.0)
                if ready and reader.stdout.readline().strip() == 'ready':
                    os.kill(reader.pid, signal.SIGSTOP)
            rss0 = peak = 0
            while tuner.poll() is None:
                rss = _rss_kib(tuner.pid)
                if not rss0 and (run / 'results.jsonl').exists():
                    rss0 = peak = rss
                peak = max(peak, rss)
                time.sleep(0.2)  # sampling the memory while the run goes on
            growth = (peak - rss0) / 1024.0 if rss0 else 0.0
            tuner.wait(timeout=1800)
        finally:
            if client is not None:
                client.close()
            for p in (tuner, reader):  # by PID
                if p is not None and p.poll() is None:
                    p.kill()
            if reader is not None:
                reader.wait(timeout=30)
        err.seek(0)
        return tuner.returncode, err.read(), growth


def free_port() -> int:
    """A TCP port nothing listens on now (the kernel's choice)."""
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def run_once(mode: str, budget: int, seed: int, live: bool = False) -> dict:
    """One tuning run of ``mode``; with ``live``, with ``--live`` and a frozen live client."""
    bench, extra, _tag = MODES[mode]
    tmp = Path(tempfile.mkdtemp(prefix='bench_rt_'))
    env = dict(os.environ)
    env.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 50))
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    hogs = start_hogs(HOGS.get(mode, 0))
    try:
        cmd = [ROS2, 'run', 'im_tuner', 'tuner', '--bench', bench, '--budget', str(budget)]
        cmd += ['--seed', str(seed), '--remeasure', '0', '--quiet', '--out', str(tmp / 'run')]
        port = free_port() if live else 0
        if port:
            cmd += ['--live', str(port)]
        cmd += extra  # the tuner's options, then any --ros-args (always last in MODES)
        code, stderr, growth = _run_tuner(
            cmd, env, mode == 'realtime-frozen-reader', tmp / 'run', port
        )
        summary_path = tmp / 'run' / 'summary.json'
        if not summary_path.exists():
            raise RuntimeError(f'{bench}: no summary (exit {code}): {stderr[-800:]}')
        s = json.loads(summary_path.read_text())
        recs = [json.loads(x) for x in (tmp / 'run' / 'results.jsonl').read_text().splitlines()]
        d = s['sessions'][-1]['drive'] or {}
        steps = max(int(d.get('steps', 0)), 1)
        out = {
            'exit': code,
            'rss_growth_mb': growth,
            # the drive counts per period fresh or held (a late command's period is held
            # there: fresh + held = steps); per command, late
            'held_late_pct': 100.0 * d.get('held', 0) / steps,
            'late_commands': d.get('late', 0),
            # the experiments' own periods, held or late (the controller's count)
            'exp_held_late_pct': 100.0
            * sum(r['periods']['held'] + r['periods']['late'] for r in recs if r.get('periods'))
            / max(1, sum(r['steps'] for r in recs if r.get('periods'))),
            'overruns': d.get('overruns'),
            # a drive that cannot pause: the whole periods its late starts skipped
            'missed_pct': 100.0 * d.get('missed', 0) / steps,
            'overrun_pct': 100.0 * d.get('overruns', 0) / steps,
            'watchdog_trips': d.get('watchdog_trips'),
            'periods': steps,
            'experiments': len(recs),
            'completed': sum(r['status'] == 'ok' for r in recs),
            'exact_5625': sum(
                r['status'] == 'ok'
                and r.get('steps') == 5625
                and r.get('t_end_ns', 0) - r.get('t_start_ns', 0) == 1_125_000_000
                for r in recs
            ),
            'timing_flagged': sum(r['status'] == 'timing' for r in recs),
        }
        out['live'] = s['sessions'][-1].get('live') or {}
        loop = d.get('loop')
        if loop:
            out['work'] = loop['period_work_us']
            out['answer'] = loop['controller_answer_us']
            out['max_lateness_us'] = loop['max_lateness_us']
            out['lateness_histogram'] = loop.get('lateness_histogram') or {}
            out['lateness_p99_us'] = (loop.get('lateness_us') or {}).get('p99', math.nan)
            # messages the outbox could not deliver (to DDS readers, to the bag)
            out['outbox_lost'] = loop.get('outbox_lost', 0)
            out['bag_lost'] = sum(
                c.get('lost_recorder', 0) for c in (loop.get('outbox') or {}).values()
            )
            sched = loop.get('realtime') or {}
            out['policy'] = f'{sched.get("policy", "?")} {sched.get("priority", "")}'.strip()
        return out
    finally:
        stop_hogs(hogs)
        shutil.rmtree(tmp, ignore_errors=True)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--budget', type=int, default=20)
    ap.add_argument('--runs', type=int, default=3)
    ap.add_argument('--benches', nargs='+', default=list(BENCHES), choices=BENCHES)
    args = ap.parse_args(argv if argv is not None else [])
    figures: dict[str, float] = {}
    for bench in args.benches:
        runs = [run_once(bench, args.budget, seed) for seed in range(1, args.runs + 1)]
        tag = MODES[bench][2]

        def med(key: str, runs: list[dict] = runs) -> float:
            return float(statistics.median(float(r[key]) for r in runs))

        print(
            f'{bench:<20} periods held or late: {med("held_late_pct"):.3f} % of all the '
            f"drive's periods, {med('exp_held_late_pct'):.3f} % of the experiments'; late "
            f'commands {med("late_commands"):.0f}; overruns '
            f'{med("overruns"):.0f} ({med("overrun_pct"):.2f} %), missed periods '
            f'{med("missed_pct"):.2f} %, watchdog trips '
            f'{med("watchdog_trips"):.0f}; completed experiments exactly 5625 periods '
            f'{med("exact_5625"):.0f} of {med("completed"):.0f} (of {med("experiments"):.0f}'
            f' run; the others aborted or off timing), flagged timing '
            f'{med("timing_flagged"):.0f}; exits {[r["exit"] for r in runs]}',
            flush=True,
        )
        figures[f'{tag}_held_late_pct'] = med('held_late_pct')
        figures[f'{tag}_exp_held_late_pct'] = med('exp_held_late_pct')
        figures[f'{tag}_overrun_pct'] = med('overrun_pct')
        figures[f'{tag}_missed_pct'] = med('missed_pct')
        figures[f'{tag}_watchdog_trips'] = med('watchdog_trips')
        figures[f'{tag}_timing_flagged'] = med('timing_flagged')
        if all('work' in r for r in runs):
            for what in ('work', 'answer'):
                for q in ('p50', 'p99', 'max'):
                    figures[f'{tag}_{what}_{q}_us'] = float(
                        statistics.median(r[what][q] for r in runs)
                    )
            print(
                f'{"":<20} per-period work p50/p99/max '
                f'{figures[f"{tag}_work_p50_us"]:.0f} / {figures[f"{tag}_work_p99_us"]:.0f} / '
                f'{figures[f"{tag}_work_max_us"]:.0f} us (budget 200); controller answer '
                f'p50/p99 {figures[f"{tag}_answer_p50_us"]:.0f} / '
                f'{figures[f"{tag}_answer_p99_us"]:.0f} us; worst lateness '
                f'{med("max_lateness_us"):.0f} us; loop {runs[0].get("policy")}',
                flush=True,
            )
            figures[f'{tag}_max_lateness_us'] = med('max_lateness_us')
            hist = runs[0]['lateness_histogram']
            if hist:
                total = max(1, sum(hist.values()))
                print(
                    f'{"":<20} period starts by lateness (run 1): '
                    + ', '.join(f'{k} {100.0 * v / total:.2f} %' for k, v in hist.items()),
                    flush=True,
                )
            for key in ('rss_growth_mb', 'lateness_p99_us', 'outbox_lost', 'bag_lost'):
                figures[f'{tag}_{key}'] = med(key)
            print(
                f'{"":<20} period-start lateness p99 {med("lateness_p99_us"):.0f} us; the '
                f"tuner's memory grew {med('rss_growth_mb'):.1f} MB from its first result to "
                f'its end'
                + (' (the reader frozen meanwhile)' if bench == 'realtime-frozen-reader' else '')
                + f'; messages not delivered: {med("outbox_lost"):.0f} (to the bag: '
                f'{med("bag_lost"):.0f})',
                flush=True,
            )
            quiet = 'rt_composed'
            if tag != quiet and f'{quiet}_work_p99_us' in figures:
                for key in ('overrun_pct', 'work_p99_us'):
                    q = figures[f'{quiet}_{key}']
                    figures[f'{tag}_{key}_ratio'] = figures[f'{tag}_{key}'] / q if q else math.inf
                print(
                    f'{"":<20} to the quiet run: overruns '
                    f'x{figures[f"{tag}_overrun_pct_ratio"]:.2f}, work p99 '
                    f'x{figures[f"{tag}_work_p99_us_ratio"]:.2f}',
                    flush=True,
                )
    return figures


if __name__ == '__main__':
    main(sys.argv[1:])
