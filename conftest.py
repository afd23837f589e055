"""Test-run hygiene for every test in the workspace (the rules: README.md, "Two commands").

* Each test run gets its own DDS domain (``ROS_DOMAIN_ID``) and discovery stays on this
  host (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``), so concurrent runs and other
  programs on the machine cannot cross-talk.
* ROS finds the venv's ament index and a writable log directory.
* Child processes are started through the ``procs`` fixture and ended by PID
  (SIGINT, a grace period, then SIGKILL), never by name.
* Every test process runs on the project's numeric baseline (``im_drive_sim.numeric``:
  numpy's and OpenBLAS's dispatch held at x86-64-v3), set here before anything imports
  numpy and inherited by every child; the run's header says what it is.
"""

from __future__ import annotations

import contextlib
import faulthandler
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import pytest

import im_drive_sim  # noqa: F401 (the numeric baseline, set before anything imports numpy)

REPO = Path(__file__).resolve().parent
VENV = Path(sys.prefix)

# A domain per run, and per worker of a run (`make test` runs two, pytest-xdist):
# derived from the run's PID, within Fast DDS's usable range 0..232. The workers' domains
# are spread 200 / workers apart: test_faults walks up from its worker's domain, one
# fresh domain per test (a SIGKILLed node stays on a graph until its lease ends).
_WORKER = os.environ.get('PYTEST_XDIST_WORKER', '')  # 'gw0', 'gw1', ... in a worker
_RUN_PID = os.getppid() if _WORKER else os.getpid()  # a worker's parent is the run
_SPREAD = 200 // max(1, int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1')))
_DOMAIN = 20 + (_RUN_PID + (1 + _SPREAD * int(_WORKER[2:]) if _WORKER else 0)) % 200
os.environ['ROS_DOMAIN_ID'] = os.environ.get('IM_TEST_DOMAIN_ID', str(_DOMAIN))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
# A run started in the background of a script (`bash .ci/run &`) gets SIGINT ignored from
# bash, and every child would inherit that: the tests that send SIGINT to a study then
# wait for ever. A Python handler here becomes SIG_DFL in each exec'd child.
signal.signal(signal.SIGINT, signal.default_int_handler)
os.environ.setdefault('AMENT_PREFIX_PATH', str(VENV))
if str(VENV) not in os.environ['AMENT_PREFIX_PATH'].split(os.pathsep):
    os.environ['AMENT_PREFIX_PATH'] = os.pathsep.join([str(VENV), os.environ['AMENT_PREFIX_PATH']])
os.environ.setdefault('ROS_LOG_DIR', tempfile.mkdtemp(prefix='im_tuner_test_roslog_'))
# The first steps safe computes (im_tuner.prior, 5-10 s each) shared by every process of
# the run: the suite's tuner runs on one drive identify the same few models. `make test`
# names one directory for both passes; otherwise the run makes one and removes it.
_OWN_PRIOR_CACHE = not os.environ.get('IM_TUNER_PRIOR_CACHE')
if _OWN_PRIOR_CACHE:
    os.environ['IM_TUNER_PRIOR_CACHE'] = tempfile.mkdtemp(prefix='im_tuner_test_priors_')
if not os.environ.get('HOME'):
    os.environ['HOME'] = tempfile.gettempdir()


#: The whole run must end within this many seconds (about 12 minutes here; a machine 2x
#: slower needs 24). Past it, every thread's stack is printed and the run ends
#: with exit 1 -- a hang that pytest-timeout cannot break (in C code, or at exit) fails
#: with a word of where, instead of running out CI's 90 minutes in silence.
SESSION_LIMIT_S = 60 * 60
#: After the last test, the interpreter must be gone within this many seconds (a thread
#: or child that keeps it alive is a hang at exit: same stacks, same exit 1).
EXIT_GRACE_S = 180
_STDERR_FD: list[int] = []  # a copy of the real stderr (fd 2 is captured during tests)


def pytest_configure(config: pytest.Config) -> None:
    # Output capture is suspended here, so fd 2 is the terminal or CI's log.
    _STDERR_FD.append(os.dup(2))
    faulthandler.dump_traceback_later(SESSION_LIMIT_S, exit=True, file=_STDERR_FD[0])


def pytest_report_header(config: pytest.Config) -> str:
    from im_drive_sim import numeric

    return f'numeric baseline: {numeric.describe(numeric.status())}'


def pytest_unconfigure(config: pytest.Config) -> None:
    faulthandler.dump_traceback_later(EXIT_GRACE_S, exit=True, file=_STDERR_FD[0])
    if _OWN_PRIOR_CACHE and not _WORKER:
        shutil.rmtree(os.environ['IM_TUNER_PRIOR_CACHE'], ignore_errors=True)


#: The test files that take longest, longest first (seconds of their tests not marked
#: serial, `--durations=0` on the 2-core machine while two other jobs ran, 2026-11-28:
#: 455, 249, 193, 193, 147, 132, 123, 121, 116, 94, 73, 73, 70): `make test` runs files on
#: two workers (pytest-xdist ``--dist loadfile``, so a module's shared fixture is made
#: once), these first, so neither worker is left with a long file at the end.
LONGEST_FIRST = (
    'test_tuner.py',
    'test_faults.py',
    'test_numeric_baseline.py',
    'test_study.py',
    'test_study_drives.py',
    'test_study_bad_input.py',
    'test_replay.py',
    'test_bad_input.py',
    'test_bag_clients.py',
    'test_report.py',
    'test_drive_stop.py',
    'test_controller_node.py',
    'test_documented_paths.py',
    # the pure tier's longest (`make test-unit --durations=0`, 2026-12-06: 30, 21, 16, 13,
    # 11 s, two other jobs running)
    'test_first_step.py',
    'test_study_plant.py',
    'test_optim_cga.py',
    'test_optim_api.py',
    'test_hardware_abi.py',
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The tiers: a package's own tests (src/<package>/test) are the pure unit tier; the
    workspace tests (test/) start nodes and processes, unless marked unit. The longest
    files run first (:data:`LONGEST_FIRST`; a stable sort keeps every other order)."""
    for item in items:
        rel = Path(str(item.path)).resolve().relative_to(REPO)
        if rel.parts[0] == 'src' or item.get_closest_marker('unit') is not None:
            item.add_marker(pytest.mark.unit)  # (a static test in test/ says so itself)
        else:
            item.add_marker(pytest.mark.integration)
    if _WORKER:  # on workers only (make test); one process keeps pytest's order
        rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
        items.sort(key=lambda it: rank.get(it.path.name, len(rank)))


def wait_for(
    predicate: Callable[[], object],
    timeout: float,
    interval: float = 0.01,
    message: str = 'condition',
) -> object:
    """Poll ``predicate`` on a steady clock until truthy or ``timeout`` s pass (then fail)."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise AssertionError(f'timed out after {timeout} s waiting for {message}')
        time.sleep(interval)


class Child(subprocess.Popen):
    """A child whose stdout and stderr, unless given, go to files, not pipes: a chatty
    child (warnings of a loaded machine) never blocks on a full pipe that a test reads
    only at its end. :meth:`communicate` waits for it and returns their text."""

    def __init__(self, argv: list[str], **kwargs) -> None:
        self._files: dict[str, object] = {}
        for name in ('stdout', 'stderr'):
            if name not in kwargs:
                kwargs[name] = self._files[name] = tempfile.TemporaryFile()  # noqa: SIM115 (stop_all)
        super().__init__(argv, **kwargs)

    def communicate(self, input=None, timeout=None):
        try:
            out, err = super().communicate(input, timeout)
        except subprocess.TimeoutExpired as exc:
            raise StuckChild(exc.cmd, exc.timeout, self._stacks()) from None
        return self._read('stdout', out), self._read('stderr', err)

    def _stacks(self) -> str:
        """Ask the child and its descendants (found by PID in /proc) for every thread's
        Python stack (the executables dump it on SIGUSR1: ``cli.executable``); the tail
        of its stderr, for the failure's message."""
        pids, i = [self.pid], 0
        while i < len(pids):
            for task in Path(f'/proc/{pids[i]}/task').glob('*/children'):
                with contextlib.suppress(OSError, ValueError):
                    pids += [int(c) for c in task.read_text().split()]
            i += 1
        asked = [pid for pid in pids if _catches_sigusr1(pid)]  # (else SIGUSR1 ends it)
        for pid in asked:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGUSR1)
        f = self._files.get('stderr')
        if f is None:
            return ''
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:  # the dump ends with the main thread's stack
            f.seek(0)  # type: ignore[attr-defined]
            text = f.read().decode(errors='replace')  # type: ignore[attr-defined]
            if not asked or 'Current thread' in text:
                break
            time.sleep(0.1)
        time.sleep(0.2)
        f.seek(0)  # type: ignore[attr-defined]
        return f.read().decode(errors='replace')[-6000:]  # type: ignore[attr-defined]

    def _read(self, name: str, piped):
        f = self._files.get(name)
        if f is None:
            return piped
        f.seek(0)  # type: ignore[attr-defined]
        data = f.read()  # type: ignore[attr-defined]
        return data.decode(errors='replace') if self.text_mode else data


def _catches_sigusr1(pid: int) -> bool:
    """Whether process ``pid`` has a handler for SIGUSR1 (``SigCgt`` in its status)."""
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith('SigCgt:'):
                return bool(int(line.split()[1], 16) >> (signal.SIGUSR1 - 1) & 1)
    except (OSError, ValueError):
        pass
    return False


class StuckChild(subprocess.TimeoutExpired):
    """A child that did not end in time; its message carries its stderr's tail with the
    stacks of its threads."""

    def __init__(self, cmd, timeout: float, tail: str) -> None:
        super().__init__(cmd, timeout)
        self.tail = tail

    def __str__(self) -> str:
        return f'{super().__str__()}; its stderr ends:\n{self.tail}'


class Processes:
    """Starts child processes for a test and always ends them at teardown."""

    def __init__(self) -> None:
        self.children: list[subprocess.Popen] = []

    def start(self, argv: list[str], **kwargs) -> Child:
        kwargs.setdefault('text', True)
        proc = Child(argv, **kwargs)
        self.children.append(proc)
        return proc

    def stop_all(self) -> None:
        from im_drive_sim.runtime import stop_child  # SIGINT, grace, SIGKILL, by PID

        for proc in reversed(self.children):
            stop_child(proc)
            for f in proc._files.values():
                f.close()  # type: ignore[attr-defined]


@pytest.fixture
def procs():
    p = Processes()
    try:
        yield p
    finally:
        p.stop_all()


@pytest.fixture
def ros_context():
    """A private rclpy Context for one test, shut down afterwards."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx)
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.fixture
def ros2_exe() -> Path:
    """The workspace's ``ros2`` command (installed by ``make setup``)."""
    return VENV / 'bin' / 'ros2'


@pytest.fixture
def wait_until() -> Callable[..., object]:
    """The :func:`wait_for` helper, as a fixture (tests cannot import conftest)."""
    return wait_for


#: How long the suite measures the host's floor [s] (``host_check``, once per run).
HOST_FLOOR_S = 8.0
#: How long a wall-clock test measures the floor again after a run the host made late [s].
HOST_RECHECK_S = 4.0
#: A host whose worst experiment-long window holds more periods than this cannot run a
#: wall-clock test honestly: the test skips with the floor in its reason.
HOST_FLOOR_HOPELESS = 1000
#: A hopeless floor older than this [s] is measured again before a test skips on it.
HOST_FLOOR_AGE_S = 60.0
#: The share of late periods [%] a run's drive may show beyond twice the floor's before
#: the run is called later than its host (docs/real-drive.md: the code's budget).
LATE_MARGIN_PCT = 0.05
#: A composed loop whose period work (p50) takes more than this [us] of the 200 us period
#: is slow itself (im_tuner.tuner_session.SLOW_DRIVE_SHARE): its late periods are the code's.
SLOW_WORK_US = 100.0


def measure_host(seconds: float) -> dict:
    """``host_check --seconds S --json`` in a child, as a user runs it."""
    import json

    exe = VENV / 'lib' / 'im_drive_sim' / 'host_check'
    p = subprocess.run(
        [str(exe), '--seconds', str(seconds), '--json'],
        capture_output=True,
        text=True,
        timeout=seconds + 120,
    )
    assert p.returncode == 0, p.stderr[-2000:]
    return json.loads(p.stdout)


#: A wall-clock run, given the timing tolerance to run with: its process and run directory.
WallClockRun = Callable[[int], 'tuple[subprocess.CompletedProcess, Path]']


class HostFloor(dict):
    """``host_check --json`` of this machine (measured once per test run, in a child, as a
    user runs it) and what a wall-clock test takes from it."""

    def __init__(self, measured: dict) -> None:
        super().__init__(measured)
        self.taken = time.monotonic()  #: when it was measured [s, monotonic]

    @property
    def tolerance(self) -> int:
        """The timing tolerance a wall-clock run here is given: twice the worst
        experiment-long window of the measurement, at least the tuner's default. Not its
        95th percentile: a test must complete. Three times, the top of the range a whole
        tuner process held against the wait alone in the same minutes (1.5-3x; ``--timing-
        tolerance auto`` takes 2x its p95): a wall-clock library run stopped on timing at
        2x a worst window of 24 in an idle serial pass."""
        worst = max(int(self['tolerance']), int(self['held_per_experiment']['max']))
        return max(10, 3 * worst)

    def describe(self) -> str:
        """The floor in one line, for failure and skip messages."""
        h = self['held_per_experiment']
        return (
            f"host floor ({self['seconds']:.0f} s of the loop's wait): late "
            f'{self["late_pct"]:.3f} %, held {self["held_pct"]:.3f} %, worst '
            f'{self["max_lateness_us"]:.0f} us, held per experiment p95 {h["p95"]:.0f} / max '
            f'{h["max"]:.0f}'
        )

    def require(self) -> None:
        """Skip the calling test, saying the floor, when no tolerance would be honest. A
        hypervisor's stalls come and go within minutes: a hopeless floor measured more than
        ``HOST_FLOOR_AGE_S`` ago is measured again first (``HOST_FLOOR_S``), and a quiet one
        found then becomes the floor of the tests that follow."""
        if self.tolerance <= HOST_FLOOR_HOPELESS:
            return
        before = self.describe()
        if time.monotonic() - self.taken > HOST_FLOOR_AGE_S:
            self.clear()
            self.update(measure_host(HOST_FLOOR_S))
            self.taken = time.monotonic()
            if self.tolerance <= HOST_FLOOR_HOPELESS:
                print(f'the host is quieter than it was ({before}): now {self.describe()}')
                return
            before += f'; again: {self.describe()}'
        pytest.skip(f'this host cannot run a 5 kHz wall-clock loop: {before}')

    def louder(self, seen: dict) -> bool:
        """Whether a measurement of the host taken later in the test (``host_check``'s
        record, or a run's check before its first experiment) found it louder than this
        floor: more late periods than twice the floor's plus the margin, or experiments
        needing more held periods than the tolerance this floor derives."""
        late = float(seen['late_pct']) > 2 * float(self['late_pct']) + LATE_MARGIN_PCT
        return late or int(seen['tolerance']) > self.tolerance

    def late_run(self, p: subprocess.CompletedProcess, run: Path) -> str | None:
        """What a failed wall-clock run says of its host: None when its periods were no
        later than this floor allows (twice the floor's late share plus the margin) or its
        own period work was slow (the code's fault either way), else its figures."""
        drive = _drive_record(run)
        if drive is None:
            return None  # no record of the periods: nothing says it was the host
        work = ((drive.get('loop') or {}).get('period_work_us') or {}).get('p50')
        if drive.get('steps', 0) <= 0 or (work is not None and work > SLOW_WORK_US):
            return None
        late_pct = 100.0 * drive['overruns'] / drive['steps']
        if late_pct <= 2 * float(self['late_pct']) + LATE_MARGIN_PCT:
            return None
        check = ((drive.get('loop') or {}).get('realtime') or {}).get('host_check')
        said = (
            f'late {late_pct:.2f} % of {drive["steps"]} periods (worst '
            f'{drive["max_lateness_us"] / 1000:.1f} ms, held {drive["held"]}), period work '
            f'p50 {work} us'
        )
        if check:
            said += (
                f'; its own check before the run: late {check["late_pct"]:.3f} %, 95 % of '
                f'experiments meet {check["tolerance"]}'
            )
        return said

    def run_judged(self, start: WallClockRun) -> tuple[subprocess.CompletedProcess, Path, int]:
        """A wall-clock run judged against the host in the same test: ``start`` runs at
        this floor's tolerance; a run that failed with its periods later than the floor
        allows while its own work was short (:meth:`late_run`) had a host louder than when
        the floor was measured, so the host is measured again (``host_check``) and the run
        made once more at the tolerance that derives. When the second is late too and
        some measurement in the test found the host louder than the floor (the re-check, or
        either run's check before its first experiment), the test skips with every figure;
        a run late on a host every measurement found quiet is the code's, and is returned
        for the caller's assertions to fail. Returns the process, its run directory and
        the tolerance it ran with."""
        tol = self.tolerance
        p, run = start(tol)
        late = None if p.returncode == 0 else self.late_run(p, run)
        if late is None:
            return p, run, tol
        again = HostFloor(measure_host(HOST_RECHECK_S))
        print(f'the run was later than the floor ({late}); the host again: {again.describe()}')
        again.require()
        checks = [again, *self._checks(run)]
        tol = max(tol, again.tolerance)
        p, run = start(tol)
        late2 = None if p.returncode == 0 else self.late_run(p, run)
        checks += self._checks(run)
        if late2 is not None and any(self.louder(c) for c in checks):
            pytest.skip(
                f'the host was louder than its floor during this test: {self.describe()}; '
                f'the first run {late}; then {again.describe()}; the second run (tolerance '
                f'{tol}) {late2}'
            )
        return p, run, tol

    @staticmethod
    def _checks(run: Path) -> list[dict]:
        """The host check a run made before its first experiment (summary.json), if any."""
        drive = _drive_record(run) or {}
        check = ((drive.get('loop') or {}).get('realtime') or {}).get('host_check')
        return [check] if check and 'late_pct' in check else []


def _drive_record(run: Path) -> dict | None:
    """The drive's record of a run's last session (summary.json), None if there is none."""
    import json

    try:
        return json.loads((run / 'summary.json').read_text())['sessions'][-1]['drive']
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        return None


@pytest.fixture
def host_floor_type() -> type[HostFloor]:
    """The :class:`HostFloor` class, for tests of its judgement (tests cannot import
    conftest); its module's ``measure_host`` is what a re-check calls."""
    return HostFloor


@pytest.fixture(scope='session')
def host_floor() -> HostFloor:
    """This machine's floor for a 5 kHz loop (``ros2 run im_drive_sim host_check``): the
    wall-clock tests judge the code against it, and run with the tolerance it derives."""
    return HostFloor(measure_host(HOST_FLOOR_S))
