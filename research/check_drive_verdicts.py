"""check_drive's verdicts, repeated: quiet, beside CPU hogs, and across two network
namespaces with packet loss: for each documented broken drive and a correct one, every
verdict correct or ``inconclusive``, never wrong.

    python research/check_drive_verdicts.py [--runs N] [--conditions quiet,hogs,netns]
                                         [--drives correct,sim,slower,...] [--loss PERCENT]
                                         [--hogs N] [--json FILE] [--keep DIR]
                                         [--check-args='--thread-priority 40']

A drive is started, ``check_drive --json`` run against it, the drive stopped (by PID); each
item's verdict is compared with the drive's expectation (the items it breaks fail, the
others pass): ``right``, ``inconclusive`` or ``WRONG``. ``netns`` puts the drive in one
network namespace and the check in another (test/netns.py; root, iproute2, nftables), with
``--loss`` % of the packets dropped at random on each side. ``--keep DIR`` saves what each
check recorded (its ``Recording``, pickled) beside its JSON, to replay a wrong verdict with
``evaluate``. ``--check-args`` are given to every check (its real-time options).
Takes about 12 s per check.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'test'))

BIN = Path(sys.prefix) / 'bin'
BROKEN = str(ROOT / 'test' / 'broken_drive.py')

EXAMPLE_RT = [
    str(BIN / 'ros2'), 'run', 'im_drive_sim', 'example_drive',
    '--thread-priority', '50', '--lock-memory',
]  # fmt: skip
#: drive name -> (argv, the items it must fail)
DRIVES: dict[str, tuple[list[str], set[str]]] = {
    'example': ([str(BIN / 'ros2'), 'run', 'im_drive_sim', 'example_drive'], set()),
    'sim': ([str(BIN / 'ros2'), 'run', 'im_drive_sim', 'drive_sim', '--mode', 'realtime'], set()),
    'rate': ([sys.executable, BROKEN, '--break', 'rate'], {'rate'}),
    'watchdog': ([sys.executable, BROKEN, '--break', 'watchdog'], {'watchdog'}),
    'degrees': ([sys.executable, BROKEN, '--break', 'degrees'], {'fields'}),
    'late': ([sys.executable, BROKEN, '--break', 'late'], {'latency'}),
    'slower': ([sys.executable, BROKEN, '--break', 'slower'], {'latency'}),
    'sign': ([sys.executable, BROKEN, '--break', 'sign'], {'step_response'}),
    'slow_current': ([sys.executable, BROKEN, '--break', 'slow_current'], {'step_response'}),
    'joint_type': ([sys.executable, BROKEN, '--break', 'joint_type'], {'topics'}),
    # a C library on the wall clock in the example drive node (test/wallclock_drive.c),
    # with the real-time options docs/real-drive.md gives a real drive: it acts with
    # command delay 2; ``clib`` declares 2, ``clib_late`` declares 1 (it acts one period
    # later than it says)
    'clib': ([*EXAMPLE_RT, '--hardware'], set()),
    'clib_late': ([*EXAMPLE_RT, '--hardware'], {'latency'}),
}
#: the environment a drive needs beyond the test's
DRIVE_ENV = {'clib': {'IM_TEST_DRIVE_DELAY': '2'}, 'clib_late': {'IM_TEST_DRIVE_DELAY': '1'}}


def wallclock_lib(tmp: Path) -> Path:
    """test/wallclock_drive.c built into ``tmp``."""
    out = tmp / 'libwallclock.so'
    if not out.exists():
        include = ROOT / 'src' / 'im_drive_sim' / 'include'
        subprocess.run(
            [
                'cc',
                '-O2',
                '-shared',
                '-fPIC',
                f'-I{include}',
                '-o',
                str(out),
                str(ROOT / 'test' / 'wallclock_drive.c'),
                '-lm',
            ],
            check=True,
        )
    return out


def hog() -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, '-c', 'while True: pass'],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def stop(p: subprocess.Popen, timeout: float = 10.0) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


#: check_drive run with its Recording pickled to the file $CDV_KEEP before it is judged
KEEPING = """
import os, pickle, sys
from im_drive_sim.check_drive import cli, procedure
judge = procedure.evaluate
def keep(rec, kept_up):
    with open(os.environ['CDV_KEEP'], 'wb') as f:
        pickle.dump(rec, f)
    return judge(rec, kept_up)
procedure.evaluate = keep
sys.exit(cli.main(['check_drive', *sys.argv[1:]]))
"""


def one_check(
    drive: str,
    condition: str,
    tmp: Path,
    net,
    keep: Path | None = None,
    extra: tuple[str, ...] = (),
) -> dict:
    argv, expect = DRIVES[drive]
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(random.Random().randrange(1, 200))
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    out_json = (keep or tmp) / f'{drive}_{condition}_{time.monotonic_ns()}.json'
    check = [str(BIN / 'ros2'), 'run', 'im_drive_sim', 'check_drive', '--json', str(out_json)]
    if keep is not None:
        env['CDV_KEEP'] = str(out_json.with_suffix('.pkl'))
        check = [sys.executable, '-c', KEEPING, '--json', str(out_json)]
    check = [*check, *extra]
    env.update(DRIVE_ENV.get(drive, {}))
    if drive.startswith('clib'):
        argv = [*argv, f'lib:{wallclock_lib(tmp)}']
    if net is not None:
        env = net.env(env)
        argv, check = net.argv('a', argv), net.argv('b', check)
    d = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        t0 = time.monotonic()
        try:
            c = subprocess.run(check, env=env, capture_output=True, text=True, timeout=180)
        except subprocess.TimeoutExpired as exc:
            c = subprocess.CompletedProcess(check, -9, exc.stdout or '', 'hung: no end in 180 s')
        took = time.monotonic() - t0
    finally:
        stop(d)
    data = json.loads(out_json.read_text()) if out_json.exists() else None
    row = {
        'drive': drive,
        'condition': condition,
        'exit': c.returncode,
        'items': {},
        'seconds': round(took, 1),
    }
    if data is None:
        row['error'] = (c.stderr.strip().splitlines() or ['?'])[-1]
        return row
    for it in data['items']:
        verdict = it.get('verdict', 'pass' if it['passed'] else 'fail')
        want = 'fail' if it['name'] in expect else 'pass'
        grade = (
            'right' if verdict == want else 'inconclusive' if verdict == 'inconclusive' else 'WRONG'
        )
        row['items'][it['name']] = {'verdict': verdict, 'grade': grade, 'figures': it['figures']}
    row['stdout'] = c.stdout
    if keep is not None:
        row['json'] = str(out_json)
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--runs', type=int, default=10)
    ap.add_argument('--conditions', default='quiet,hogs,netns')
    ap.add_argument('--drives', default=','.join(DRIVES))
    ap.add_argument('--loss', type=float, default=0.1, help='packet loss in netns [%%]')
    ap.add_argument('--hogs', type=int, default=2)
    ap.add_argument('--json', help='write every row here')
    ap.add_argument('--keep', type=Path, help="save each check's JSON and recording here")
    ap.add_argument('--check-args', default='', help='more options for every check_drive')
    ns = ap.parse_args()
    # a SIGTERM ends the run through the ``finally`` blocks: no hog or namespace left behind
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    drives = ns.drives.split(',')
    if ns.keep is not None:
        ns.keep.mkdir(parents=True, exist_ok=True)
    conditions = ns.conditions.split(',')
    rows = []
    with tempfile.TemporaryDirectory() as tmpd:
        tmp = Path(tmpd)
        for condition in conditions:
            hogs = [hog() for _ in range(ns.hogs)] if condition == 'hogs' else []
            net = None
            try:
                if condition == 'netns':
                    import netns

                    why = netns.why_not()
                    if why:
                        print(f'netns: skipped: {why}')
                        continue
                    net = netns.TwoComputers('cdv').__enter__()
                    net.loss(ns.loss)
                for run in range(ns.runs):
                    for drive in drives:
                        row = one_check(
                            drive, condition, tmp, net, ns.keep, tuple(ns.check_args.split())
                        )
                        rows.append(row)
                        wrong = [k for k, v in row['items'].items() if v['grade'] == 'WRONG']
                        inc = [k for k, v in row['items'].items() if v['grade'] == 'inconclusive']
                        print(
                            f'{condition:6s} run {run} {drive:13s} exit {row["exit"]} '
                            f'{row["seconds"]:5.1f} s '
                            f'wrong {wrong or "-"} inconclusive {inc or "-"}'
                            + (f' ERROR {row["error"]}' if 'error' in row else ''),
                            flush=True,
                        )
                        for k in wrong:
                            print(f'    {k}: {row["items"][k]["figures"]}', flush=True)
            finally:
                for h in hogs:
                    h.kill()
                    h.wait()
                if net is not None:
                    net.__exit__(None, None, None)
    print(
        '\n| drive (must fail) | '
        + ' | '.join(f'{c}: right / inconc. / WRONG' for c in conditions)
        + ' |'
    )
    print('|---|' + '---|' * len(conditions))
    for drive in drives:
        cells = []
        for condition in conditions:
            sel = [r for r in rows if r['condition'] == condition and r['drive'] == drive]
            grades = [
                'WRONG'
                if 'error' in r or any(v['grade'] == 'WRONG' for v in r['items'].values())
                else 'inconclusive'
                if any(v['grade'] == 'inconclusive' for v in r['items'].values())
                else 'right'
                for r in sel
            ]
            cells.append(
                f'{grades.count("right")} / {grades.count("inconclusive")} / '
                f'{grades.count("WRONG")}'
            )
        must = ', '.join(sorted(DRIVES[drive][1])) or 'nothing'
        print(f'| {drive} ({must}) | ' + ' | '.join(cells) + ' |')
    if ns.json:
        Path(ns.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
