"""A user's drive at the simulator's timing: each form of a power stage on the
composed bench, beside the machine's floor measured in the same minute.

    .venv/bin/python benchmarks/bench_user_drive.py [--budget 10] [--runs 1] [--stops 10]

Drives: ``sim`` (the simulator, compiled), ``example`` (the stand-in plant as a compiled
class), ``library`` (a C library that lives on the wall clock, ``test/wallclock_drive.c``,
built here with the system compiler) and ``python`` (the stand-in as a Python hardware
class: its periods run as Python). Each runs ``tuner --bench realtime --budget N`` with
``--thread-priority 50 --lock-memory`` and the default timing tolerance, quiet and beside
two CPU hogs (busy processes at normal priority, ended by PID); before each run
``loop_floor.measure`` (the loop's wait alone, compiled, the same options) measures what
the machine gives a real-time thread in that load, for 10 s.

Printed per drive and load: whether the run finished, the overruns against the floor
(target: within 2x the floor + 0.05 %), the period work p50/p99 (target: p99 within 2x
the simulator's), held periods (all, and in the counted experiments), experiments
flagged timing; for ``example`` the losses against the same experiments replayed in
lock-step on the same plant with every period fresh (``offline.replay_stand_in``).
``--timing-tolerance auto`` (or N): the tuner's, instead of its default; the line then says the
tolerance each run chose and its own host check's late share (``host_check``'s, run before the
first experiment), beside the floor's. ``--stops N``: the library run stopped N times each
by SIGINT and SIGTERM mid-experiment at each ``--hogs`` load, its last write zero current
(``IM_TEST_DRIVE_LOG``), and the time from the signal to that write (``--drives`` with no
name: the stops only).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(REPO / 'test'))

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
RT = ['--thread-priority', '50', '--lock-memory']
DRIVES = ('sim', 'example', 'library', 'python')
FLOOR_S = 10.0


def build_library(tmp: Path) -> Path:
    cc = shutil.which('cc') or shutil.which('gcc')
    if cc is None:
        raise SystemExit('bench_user_drive: no C compiler (cc) for the library drive')
    out = tmp / 'libwallclock.so'
    inc = REPO / 'src' / 'im_drive_sim' / 'include'
    src = REPO / 'test' / 'wallclock_drive.c'
    subprocess.run(
        [cc, '-O2', '-shared', '-fPIC', f'-I{inc}', '-o', str(out), str(src), '-lm'], check=True
    )
    return out


def floor(hogs: int) -> dict:
    """loop_floor.measure in a child (SCHED_FIFO 50, memory locked) beside ``hogs``."""
    from bench_realtime import start_hogs, stop_hogs

    code = (
        'import json, sys; sys.path.insert(0, sys.argv[1]); import loop_floor as F; '
        'from im_drive_sim import rt; rt.apply(rt.RtOptions(50, -1, True)); '
        f'print(json.dumps(F.measure({FLOOR_S})))'
    )
    h = start_hogs(hogs)
    try:
        p = subprocess.run([sys.executable, '-c', code, str(HERE)], capture_output=True, text=True)
    finally:
        stop_hogs(h)
    if p.returncode != 0:
        raise RuntimeError(p.stderr[-2000:])
    return json.loads(p.stdout.strip().splitlines()[-1])


def env_for(tmp: Path) -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault('ROS_DOMAIN_ID', str(150 + os.getpid() % 50))
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env['PYTHONPATH'] = os.pathsep.join([str(REPO / 'test'), env.get('PYTHONPATH', '')])
    env['IM_TEST_DRIVE_LOG'] = str(tmp / 'drive.log')
    return env


def drive_arg(drive: str, lib: Path) -> list[str]:
    return {
        'sim': [],
        'example': ['--drive', 'example'],
        'library': ['--drive', f'lib:{lib}'],
        'python': ['--drive', 'recording_hardware:RecordingHardware'],
    }[drive]


def run_once(
    drive: str, hogs: int, budget: int, seed: int, lib: Path, tolerance: str | None = None
) -> dict:
    from bench_realtime import start_hogs, stop_hogs

    fl = floor(hogs)
    tmp = Path(tempfile.mkdtemp(prefix='bench_user_'))
    env = env_for(tmp)
    env['RECORDING_HW_FILE'] = str(tmp / 'hw.bin')
    run = tmp / 'run'
    cmd = [ROS2, 'run', 'im_tuner', 'tuner', '--bench', 'realtime', *drive_arg(drive, lib)]
    cmd += ['--budget', str(budget), '--seed', str(seed), '--remeasure', '0', '--quiet']
    cmd += ['--fault-policy', 'reset', *RT, '--out', str(run)]
    if tolerance is not None:
        cmd += ['--timing-tolerance', tolerance]
    h = start_hogs(hogs)
    try:
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)
    finally:
        stop_hogs(h)
    try:
        s = json.loads((run / 'summary.json').read_text())
        recs = [json.loads(x) for x in (run / 'results.jsonl').read_text().splitlines()]
        d = s['sessions'][-1]['drive'] or {}
        loop = d.get('loop') or {}
        steps = max(int(d.get('steps', 0)), 1)
        out = {
            'exit': p.returncode,
            'floor_overrun_pct': fl['overrun_pct'],
            'floor_max_lateness_us': fl['max_lateness_us'],
            'overrun_pct': 100.0 * d.get('overruns', 0) / steps,
            'max_lateness_us': loop.get('max_lateness_us', float('nan')),
            'work_p50': loop['period_work_us']['p50'],
            'work_p99': loop['period_work_us']['p99'],
            'compiled': loop.get('compiled'),
            'held_pct': 100.0 * d.get('held', 0) / steps,
            'counted': s['held_periods']['counted'],
            'with_held': s['held_periods']['with_held'],
            'max_held': s['held_periods']['max'],
            'timing': sum(r['status'] == 'timing' for r in recs),
            'outbox_lost': loop.get('outbox_lost', 0),
            'tolerance': s['timing_tolerance'],
            'check_late_pct': ((loop.get('realtime') or {}).get('host_check') or {}).get(
                'late_pct', float('nan')
            ),
        }
        if drive == 'example':
            try:
                out.update(replayed(recs))
            except ValueError as exc:  # a run the replay cannot follow (a fault reset)
                out['replay_error'] = str(exc)
        return out
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


#: the documented noise of a repeated experiment: the `bench` profile's CV
#: (docs/calibration.md; docs/real-drive.md, "Timing tolerance")
BENCH_CV = 0.024


def replayed(recs: list[dict]) -> dict:
    """The run's counted losses against the same experiments replayed in lock-step on the
    same plant, every period fresh (``offline.replay_stand_in``). Until the first held
    period both histories are one: those losses must be equal bit for bit. The first
    experiment with held periods shows what they did to its loss alone. After it the
    plant's history differs (where each experiment starts, within an encoder count), so
    a later difference is that and the held periods together."""
    from im_controller.config import GAIN_NAMES, Gains
    from im_drive_sim.drive_file import load_config
    from im_tuner.offline import replay_stand_in, stand_in_losses

    cfg = load_config(None)
    ran = [r for r in recs if r.get('experiment_id') is not None]
    res = replay_stand_in(ran, cfg)
    before, first, later, inside, within = [], None, [], 0, 0
    counted = 0
    for r, x in zip(ran, res, strict=True):
        loss = r['loss'] if r['status'] in ('ok', 'aborted') else r.get('off_timing_loss')
        if loss is None:
            continue
        held = r['periods']['held'] + r['periods']['late']
        rel = abs(loss / x.loss - 1.0)
        counted += 1
        within += rel <= 2.0 * BENCH_CV
        if first is None and held == 0:
            before.append(loss == x.loss)
        elif first is None:
            first = (held, rel)
        else:
            later.append(rel)
            # the same gains at ideal timing from 8 start states: the loss's own spread
            g = Gains(*(float(r['gains'][n]) for n in GAIN_NAMES))
            ideal = stand_in_losses(cfg, g, 8, seed=int(r['experiment_id']))
            inside += min(ideal) <= loss <= max(ideal) or rel <= 0.0
    return {
        'replay_later_inside': f'{inside}/{len(later)}',
        'replay_within_2cv': f'{within}/{counted}',
        'replay_equal': f'{sum(before)}/{len(before)}',
        'replay_first_held': first[0] if first else 0,
        'replay_first_pct': 100.0 * first[1] if first else 0.0,
        'replay_later_max_pct': 100.0 * max(later, default=0.0),
    }


def stop_latency_s(log: Path) -> float:
    """When the library's current was last set to zero from non-zero [s, CLOCK_MONOTONIC]
    (``test/wallclock_drive.c``'s slot 6; NaN before any)."""
    import numpy as np

    v = np.fromfile(log, dtype=np.float64, count=7)
    return float(v[6]) if v.size == 7 and v[6] > 0 else float('nan')


def stops(lib: Path, n: int, hogs: int = 0, rt: bool = True) -> dict[str, Any]:
    """The library run stopped mid-experiment by each signal ``n`` times beside ``hogs``
    busy processes: how often its last write was zero current and close came once,
    nothing after; and the time from the signal (sent from here) to the drive's first
    zero write [ms] (CLOCK_MONOTONIC on both sides: ``time.monotonic`` here, the
    library's own clock there)."""
    from bench_realtime import start_hogs, stop_hogs
    from recording_hardware import read_log

    ok = {'SIGINT': 0, 'SIGTERM': 0}
    delays: list[float] = []
    h = start_hogs(hogs)
    try:
        for sig in ok:
            for i in range(n):
                tmp = Path(tempfile.mkdtemp(prefix='bench_stop_'))
                env = env_for(tmp)
                log = tmp / 'drive.log'
                cmd = [ROS2, 'run', 'im_tuner', 'tuner', '--bench', 'realtime']
                cmd += [*drive_arg('library', lib), '--budget', '50', '--seed', str(i)]
                cmd += ['--quiet', *(RT if rt else []), '--out', str(tmp / 'run')]
                proc = subprocess.Popen(
                    cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
                )
                try:
                    deadline = time.monotonic() + 300
                    while time.monotonic() < deadline:
                        if log.exists() and read_log(str(log))['writes'] >= 2 * 5625 + 1000:
                            break
                        time.sleep(0.05)
                    # a random moment within a period, not the poll's phase
                    time.sleep((i * 0.37) % 1 * 2e-4)
                    t_sig = time.monotonic()
                    proc.send_signal(getattr(signal, sig))
                    proc.communicate(timeout=300)
                    w = read_log(str(log))
                    good = (
                        proc.returncode == 130
                        and w['max_abs_isq'] > 0.5
                        and (w['isq_ref'], w['load_torque']) == (0.0, 0.0)
                        and w['closes'] == 1.0
                        and w['writes_after_close'] == 0.0
                    )
                    ok[sig] += int(good)
                    t_zero = stop_latency_s(log)
                    if good and t_zero >= t_sig:
                        delays.append(1e3 * (t_zero - t_sig))
                finally:
                    if proc.poll() is None:
                        proc.kill()
                    shutil.rmtree(tmp, ignore_errors=True)
    finally:
        stop_hogs(h)
    return {**ok, 'delays_ms': delays}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--budget', type=int, default=10)
    ap.add_argument('--runs', type=int, default=1)
    ap.add_argument('--drives', nargs='*', default=list(DRIVES), choices=DRIVES)
    ap.add_argument('--hogs', nargs='+', type=int, default=[0, 2])
    ap.add_argument('--stops', type=int, default=0)
    ap.add_argument('--timing-tolerance', default=None, help="the tuner's: auto or N")
    ap.add_argument(
        '--stops-without-rt',
        action='store_true',
        help='the stops with the tuner defaults, not --lock-memory',
    )
    a = ap.parse_args(argv if argv is not None else [])
    tmp = Path(tempfile.mkdtemp(prefix='bench_lib_'))
    lib = build_library(tmp)
    figures: dict[str, float] = {}
    sim_p99: dict[int, float] = {}
    for hogs in a.hogs:
        for drive in a.drives:
            runs = [
                run_once(drive, hogs, a.budget, seed, lib, a.timing_tolerance)
                for seed in range(1, a.runs + 1)
            ]

            def med(k: str, runs: list[dict] = runs) -> float:
                return float(statistics.median(float(r[k]) for r in runs))

            tag = f'user_{drive}_{"hogs" if hogs else "quiet"}'
            if drive == 'sim':
                sim_p99[hogs] = med('work_p99')
            fl = med('floor_overrun_pct')
            line = (
                f'{drive:<8} {f"beside {hogs} hogs" if hogs else "quiet":<14} exits '
                f'{[r["exit"] for r in runs]}; overruns {med("overrun_pct"):.3f} % (floor '
                f'{fl:.3f} %, target <= {2 * fl + 0.05:.3f} %); worst lateness '
                f'{med("max_lateness_us"):.0f} us (floor {med("floor_max_lateness_us"):.0f}); '
                f'work p50/p99 {med("work_p50"):.0f} / {med("work_p99"):.0f} us'
            )
            if a.timing_tolerance is not None:
                line += (
                    f'; tolerance {a.timing_tolerance}: chose {[r["tolerance"] for r in runs]}, '
                    f'its check late {[r["check_late_pct"] for r in runs]} %'
                )
            if hogs in sim_p99 and drive != 'sim':
                line += f' (simulator p99 {sim_p99[hogs]:.0f}, target <= {2 * sim_p99[hogs]:.0f})'
            line += (
                f'; compiled {runs[0]["compiled"]}; held {med("held_pct"):.3f} % of the '
                f'periods; counted {med("counted"):.0f} experiments, {med("with_held"):.0f} '
                f'with held periods (at most {med("max_held"):.0f}); flagged timing '
                f'{med("timing"):.0f}; messages lost {med("outbox_lost"):.0f}'
            )
            if drive == 'example' and 'replay_error' in runs[0]:
                line += f'; no lock-step replay of run 1: {runs[0]["replay_error"]}'
            elif drive == 'example':
                r0 = runs[0]
                line += (
                    f'; against the lock-step replay (run 1): before the first held period '
                    f'{r0["replay_equal"]} losses equal bit for bit; the first experiment with '
                    f'held periods ({r0["replay_first_held"]}) {r0["replay_first_pct"]:.2f} %; '
                    f'the later ones at most {r0["replay_later_max_pct"]:.2f} % (their start '
                    f'differs too), {r0["replay_later_inside"]} within the spread of the same '
                    'gains at ideal timing from 8 start states; '
                    f'{r0["replay_within_2cv"]} within 2 CV of the bench noise '
                    f'({200 * BENCH_CV:.1f} %) of their replay'
                )
            print(line, flush=True)
            for k in ('overrun_pct', 'floor_overrun_pct', 'work_p50', 'work_p99', 'held_pct',
                      'timing', 'exit'):  # fmt: skip
                figures[f'{tag}_{k}'] = med(k)
    if a.stops:
        for hogs in a.hogs:
            ok = stops(lib, a.stops, hogs, rt=not a.stops_without_rt)
            d = sorted(ok['delays_ms'])
            tag = f'beside {hogs} hogs' if hogs else 'quiet'
            tag += ', the default options' if a.stops_without_rt else ', ' + ' '.join(RT)
            spread = (
                f'median {statistics.median(d):.2f} ms, max {d[-1]:.2f} ms over {len(d)}'
                if d
                else 'not measured'
            )
            print(
                f'library stopped mid-experiment ({tag}): SIGINT {ok["SIGINT"]}/{a.stops}, '
                f'SIGTERM {ok["SIGTERM"]}/{a.stops} with its last write zero current, then '
                f'one close; signal to the first zero write: {spread}',
                flush=True,
            )
            key = 'hogs' if hogs else 'quiet'
            if d:
                figures[f'user_library_stop_ms_median_{key}'] = statistics.median(d)
                figures[f'user_library_stop_ms_max_{key}'] = d[-1]
            for k in ('SIGINT', 'SIGTERM'):
                figures[f'user_library_{k.lower()}_zero_{key}'] = float(ok[k])
    shutil.rmtree(tmp, ignore_errors=True)
    return figures


if __name__ == '__main__':
    main(sys.argv[1:])
