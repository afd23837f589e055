"""``ros2 run im_tuner study`` on bad input and on bad ends.

* A refusal is one line on stderr, exit 2, nothing written, and comes before any heavy
  module is imported (no Dask, scipy, matplotlib, numba, optimisers).
* ``--cluster``: a malformed address, ``tls://`` and a port outside 1..65535 are refused
  before any network; a port nobody listens on at once; a server that is not Dask (silent,
  talking garbage, hanging up) within ``--cluster-timeout``; a scheduler without workers
  after a progress line and ``--cluster-wait``.  Each within a deadline asserted here.
* A study of one run per configuration writes its tables (means without intervals), and
  ``--from`` re-tabulates it.
* However the study ends (SIGTERM, SIGINT, SIGKILL), its worker processes end with it.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import pytest

ROS2 = str(Path(sys.prefix) / 'bin' / 'ros2')
STUDY = [ROS2, 'run', 'im_tuner', 'study']
#: Modules a refusal must not import (each takes from 0.3 s to seconds).
HEAVY = ('dask', 'distributed', 'scipy', 'matplotlib', 'numba', 'cma', 'optuna')


def study(*args: str, timeout: float = 120) -> tuple[subprocess.CompletedProcess, float]:
    """Run the study command; its result and its wall time [s]."""
    t0 = time.monotonic()
    proc = subprocess.run([*STUDY, *args], capture_output=True, text=True, timeout=timeout)
    return proc, time.monotonic() - t0


def assert_refused(proc: subprocess.CompletedProcess, expect: str | tuple[str, ...]) -> str:
    """One line on stderr naming ``expect`` (or one of them), exit 2, nothing on stdout;
    the line."""
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith('error: study: '), proc.stderr
    expects = (expect,) if isinstance(expect, str) else expect
    assert any(e in lines[0] for e in expects), lines[0]
    assert proc.stdout == ''
    return lines[0]


def free_port() -> int:
    """A TCP port nobody listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


# -- refusals: fast, and before anything heavy is imported -----------------------------------------
REFUSALS = [
    (['--runs', '0'], '--runs must be an integer >= 1'),
    (['--budget', '0'], 'argument --budget: must be >= 1, got 0'),
    (['--algos', 'spsa,simplex'], "no study grid for 'simplex'"),
    (['--jobs', '0'], '--jobs: must be >= 1'),
    (['--satisfactory', 'nan'], '--satisfactory must be a normalised loss > 0'),
    (['--from', '/nonexistent/study'], 'not a study directory'),
    (['--params', '/nonexistent.yaml'], 'cannot read'),
    (['--cluster', 'localhost:8786'], 'Dask scheduler address tcp://HOST:PORT'),
    (['--cluster', 'tls://127.0.0.1:8786'], 'tls:// needs TLS certificates'),
    (['--cluster', 'tcp://127.0.0.1:99999'], 'the port must be 1..65535'),
    (['--cluster', 'tcp://127.0.0.1:0'], 'the port must be 1..65535'),
    (['--cluster', 'tcp://:8786'], 'Dask scheduler address tcp://HOST:PORT'),
    (['--cluster', 'tcp://127.0.0.1'], 'Dask scheduler address tcp://HOST:PORT'),
    (['--cluster', 'tcp://bad_host!:8786'], 'is not a host name or an IP address'),
    (['--cluster', 'tcp://[::1:8786'], 'Dask scheduler address tcp://HOST:PORT'),
    (['--cluster', 'tcp://[fe80::zz]:8786'], 'is not an IPv6 address'),
    (['--cluster', 'udp://127.0.0.1:8786'], 'scheme udp:// not supported'),
    (['--cluster', 'tcp://127.0.0.1:8786', '--jobs', '2'], 'exclude each other'),
    (['--cluster-timeout', '5'], '--cluster-timeout needs --cluster'),
    (['--plant-mismatch', 'J=1.5'], 'a machine key takes a factor xF'),
    (['--ripple-limit', '0.9'], "--ripple-limit: a ratio >= 1 or 'off', got '0.9'"),
    (['--ripple-limit', 'quiet'], "--ripple-limit: a ratio >= 1 or 'off', got 'quiet'"),
    (['--plant', 'im3700w-j1'], 'machine.isq_max 17.66 A, the told drive 7 A'),
    (['--cluster', 'tcp://127.0.0.1:8786', '--cluster-wait', '-1'], 'must be a number'),
    (['--cluster', 'tcp://127.0.0.1:8786', '--cluster-timeout', 'inf'], 'must be a number'),
]


@pytest.mark.parametrize('args, expect', REFUSALS, ids=[' '.join(a) for a, _ in REFUSALS])
def test_a_refusal_imports_nothing_heavy(tmp_path, args, expect):
    """The command's own main, in a fresh interpreter: one line, exit 2, nothing written,
    and none of the heavy modules loaded (what made a refusal take 3.7 s)."""
    out = tmp_path / 'never'
    code = (
        'import json, sys\n'
        'from im_tuner.study.cli import main\n'
        f'rc = main({[*args, "--out", str(out)]!r})\n'
        f'heavy = sorted(m for m in sys.modules if m.split(".")[0] in {HEAVY!r})\n'
        'print(json.dumps({"rc": rc, "heavy": heavy}))\n'
    )
    proc = subprocess.run(
        [sys.executable, '-c', code], capture_output=True, text=True, timeout=60, cwd=tmp_path
    )
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report['rc'] == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and expect in lines[0], proc.stderr
    assert report['heavy'] == [], report['heavy'][:10]
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []  # no bags/ either


def test_a_refusal_through_ros2_run(tmp_path):
    """The installed executable, end to end, with the address checks."""
    for args, expect in REFUSALS[7:12]:
        out = tmp_path / 'never'
        proc, _ = study(*args, '--out', str(out), timeout=60)
        assert_refused(proc, expect)
        assert not out.exists()


# -- --cluster: bounded waits ---------------------------------------------------------------------
@contextmanager
def not_dask_server(mode: str) -> Iterator[str]:
    """A TCP server on 127.0.0.1 that is not Dask: 'silent' reads and never answers,
    'garbage' answers with HTTP, 'hangup' closes every connection at once.  Yields its
    tcp:// address; the thread ends at exit."""
    srv = socket.create_server(('127.0.0.1', 0))
    srv.settimeout(0.1)
    stop = threading.Event()
    conns: list[socket.socket] = []

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if mode == 'hangup':
                conn.close()
                continue
            conns.append(conn)
            if mode == 'garbage':
                with suppress(OSError):
                    conn.sendall(b'HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n' * 8)

    thread = threading.Thread(target=serve, name=f'not-dask-{mode}', daemon=True)
    thread.start()
    try:
        yield f'tcp://127.0.0.1:{srv.getsockname()[1]}'
    finally:
        stop.set()
        thread.join(5)
        srv.close()
        for c in conns:
            c.close()


def test_nobody_listening_is_refused_at_once(tmp_path):
    # the default --cluster-timeout is 10 s: a refusal well before it did not wait for it
    out = tmp_path / 'never'
    address = f'tcp://127.0.0.1:{free_port()}'
    proc, wall = study('--cluster', address, '--runs', '1', '--out', str(out))
    line = assert_refused(proc, 'connection refused')
    assert address in line and 'dask scheduler --port' in line
    assert wall < 8.0, wall
    assert not out.exists()


@pytest.mark.parametrize(
    'mode, expect',
    [
        ('silent', 'no Dask scheduler answered within 2 s'),
        # Dask reads a frame count from the first 8 bytes and waits for (or fails to
        # allocate) that much: either way, bounded
        ('garbage', ('not a Dask scheduler', 'no Dask scheduler answered within 2 s')),
        # a hang-up the loaded host delivers after the 2 s: refused in time all the same
        ('hangup', ('not a Dask scheduler', 'no Dask scheduler answered within 2 s')),
    ],
)
def test_a_server_that_is_not_dask_fails_within_the_timeout(tmp_path, mode, expect):
    """Dask's client alone hangs on a silent server (its timeout bounds only the TCP
    connection: 300 s and more) and allocates what garbage announces (a MemoryError)."""
    out = tmp_path / 'never'
    with not_dask_server(mode) as address:
        proc, wall = study(
            '--cluster', address, '--cluster-timeout', '2', '--runs', '1', '--out', str(out)
        )
    line = assert_refused(proc, expect)
    assert address in line
    # the handshake and the identity call are each bounded by 2 s; the rest is start-up
    assert wall < 2 * 2 + 10.0, wall
    assert not out.exists()


@pytest.fixture
def scheduler_without_workers() -> Iterator[object]:
    """A real Dask scheduler with no worker (in this process, no worker processes)."""
    from distributed import LocalCluster

    with LocalCluster(
        n_workers=0, processes=False, protocol='tcp://', host='127.0.0.1', dashboard_address=None
    ) as lc:
        yield lc


def test_a_scheduler_without_workers_says_so_and_gives_up(tmp_path, scheduler_without_workers):
    lc = scheduler_without_workers
    address = lc.scheduler_address
    out = tmp_path / 'never'
    proc, wall = study(
        '--cluster', address, '--cluster-wait', '2', '--runs', '1', '--quiet', '--out', str(out)
    )
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert lines == [
        f'study: waiting for workers on {address}: 0 connected (at most 2 s, --cluster-wait)',
        f'error: study: --cluster {address}: no worker joined the scheduler within 2 s: start '
        f'workers (dask worker {address} --nthreads 1), or wait longer (--cluster-wait)',
    ], proc.stderr
    assert 2.0 <= wall < 2.0 + 12.0, wall  # it waited, and no longer than the wait
    assert not out.exists()


def test_a_worker_that_joins_during_the_wait_runs_the_study(
    tmp_path, procs, wait_until, scheduler_without_workers
):
    lc = scheduler_without_workers
    address = lc.scheduler_address
    out = tmp_path / 'study'
    err = tmp_path / 'stderr.txt'
    with err.open('w') as ef:
        proc = procs.start(
            [
                *STUDY,
                *('--cluster', address, '--cluster-wait', '120', '--runs', '1'),
                *('--budget', '2', '--algos', 'necga', '--out', str(out)),
            ],
            stdout=subprocess.DEVNULL,
            stderr=ef,
        )
        wait_until(lambda: '0 connected' in err.read_text(), 60, 0.05, 'the waiting line')
        lc.scale(1)  # one in-process worker (one thread)
        assert proc.wait(timeout=300) == 0, err.read_text()
    text = err.read_text()
    assert f'study: 1 worker(s) connected to {address}' in text
    assert json.loads((out / 'study.json').read_text())['spec']['runs'] == 1


# -- one run per configuration -------------------------------------------------------------------
def test_a_one_run_study_reports_without_intervals_and_from_retabulates_it(tmp_path):
    out = tmp_path / 'one'
    proc, _ = study(
        '--runs', '1', '--budget', '3', '--jobs', '1', '--quiet', '--out', str(out), timeout=600
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ''  # no traceback, no warning
    note = '1 run per configuration: means without intervals'
    text = (out / 'tables.txt').read_text()
    assert note in text and "The paper's conclusions in simulation" in text
    md = (out / 'reproduction.md').read_text()
    assert note in md and '1 run per configuration cannot tell' in md
    table_i = text.split('Table I:')[1].split('Table II:')[0]
    assert '[' not in table_i  # a mean of one run: no interval
    for name in ('tables.csv', 'runs.csv', 'tables.png', 'convergence.png', 'comparison.png'):
        assert (out / name).is_file(), name
    again = tmp_path / 'again'
    proc, _ = study('--from', str(out), '--satisfactory', '1.5', '--out', str(again))
    assert proc.returncode == 0, proc.stderr
    assert note in (again / 'tables.txt').read_text()
    assert 'satisfactory: final loss <= 1.5' in (again / 'tables.txt').read_text()


# -- the workers end with the study ---------------------------------------------------------------
def _stat(pid: int) -> tuple[str, int] | None:
    """(state, start time in clock ticks) of a process; None if it does not exist."""
    try:
        text = Path(f'/proc/{pid}/stat').read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    fields = text.rsplit(')', 1)[1].split()
    return fields[0], int(fields[19])


def _descendants(pid: int) -> dict[int, int]:
    """Every descendant of ``pid``: PID -> start time (an identity: PIDs are reused)."""
    found: dict[int, int] = {}
    todo = [pid]
    while todo:
        p = todo.pop()
        for task in Path(f'/proc/{p}/task').glob('*'):
            try:
                kids = [int(x) for x in (task / 'children').read_text().split()]
            except (FileNotFoundError, ProcessLookupError):
                continue
            for k in kids:
                st = _stat(k)
                if st is not None and k not in found:
                    found[k] = st[1]
                    todo.append(k)
    return found


def _alive(pid: int, start: int) -> bool:
    st = _stat(pid)
    return st is not None and st[1] == start and st[0] not in ('Z', 'X')


@pytest.mark.skipif(not Path('/proc/self/task').is_dir(), reason='needs /proc (Linux)')
@pytest.mark.parametrize(
    'sig, code',
    [(signal.SIGTERM, 143), (signal.SIGINT, 130), (signal.SIGKILL, -signal.SIGKILL)],
    ids=['SIGTERM', 'SIGINT', 'SIGKILL'],
)
def test_the_workers_end_with_the_study(tmp_path, procs, wait_until, sig, code):
    """The pool's workers are the forkserver's children and hold its "alive" pipe: before
    the fix, a killed study left the forkserver and both workers running for ever."""
    out = tmp_path / 'study'
    err = tmp_path / 'stderr.txt'
    with err.open('w') as ef:
        proc = procs.start(
            [
                *STUDY,
                *('--runs', '50', '--budget', '3000', '--algos', 'necga', '--jobs', '2'),
                *('--quiet', '--out', str(out)),
            ],
            stdout=subprocess.DEVNULL,
            stderr=ef,
        )

    def workers() -> dict[int, int]:
        """The pool's workers (grandchildren: the forkserver's children), once both run."""
        tree = _descendants(proc.pid)
        kids = {k for k in tree if _ppid(k) == proc.pid}
        grand = {k: s for k, s in tree.items() if _ppid(k) in kids}
        return tree if len(grand) >= 2 else {}

    tree = wait_until(workers, 120, 0.05, 'two pool workers')
    assert isinstance(tree, dict)
    try:
        os.kill(proc.pid, sig)
        assert proc.wait(timeout=90) == code, err.read_text()  # (a loaded machine)
        wait_until(
            lambda: not any(_alive(p, s) for p, s in tree.items()),
            10,
            0.05,
            f'every process of the study to end ({sorted(tree)})',
        )
    finally:
        for p, s in tree.items():  # (only if the test failed: ended by PID)
            if _alive(p, s):
                os.kill(p, signal.SIGKILL)
    if sig != signal.SIGKILL:
        word = 'terminated' if sig == signal.SIGTERM else 'interrupted'
        assert err.read_text().strip().splitlines() == [f'study: {word}; nothing written']
    assert not out.exists()


def _ppid(pid: int) -> int | None:
    try:
        text = Path(f'/proc/{pid}/stat').read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    return int(text.rsplit(')', 1)[1].split()[1])


def test_a_worker_off_the_numeric_baseline_is_refused_in_one_line(tmp_path):
    """A Dask worker process whose numpy/OpenBLAS dispatch is not the study's (here: the
    baseline switched off in its environment) would make the tables depend on which worker
    ran which run: the study refuses it in one line, exit 2, nothing written."""
    from distributed import LocalCluster

    with LocalCluster(
        n_workers=1,
        threads_per_worker=1,
        processes=True,
        protocol='tcp://',
        host='127.0.0.1',
        dashboard_address=None,
        env={'IM_NUMERIC_BASELINE': 'off'},
    ) as lc:
        out = tmp_path / 'never'
        proc, _ = study(
            *('--cluster', lc.scheduler_address, '--runs', '1', '--budget', '2'),
            *('--algos', 'necga', '--quiet', '--out', str(out)),
            timeout=300,
        )
    line = assert_refused(proc, 'IM_NUMERIC_BASELINE=off: every library dispatches natively')
    assert f'--cluster {lc.scheduler_address} worker ' in line
    assert 'the study began held x86-64-v3' in line
    assert 'env $(python -m im_drive_sim.numeric_main --env) dask worker' in line
    assert not out.exists()
