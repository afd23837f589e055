"""Real-time scheduling options (``im_drive_sim.rt``; docs/real-drive.md, "Real-time set-up").

Applied when permitted (this runs as root in CI: SCHED_FIFO, the affinity and mlockall
are permitted, and a child process shows them applied); when not, one line per option
says why and how to grant it, and nothing stops. Bad values are usage errors.
"""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys

import pytest

from im_drive_sim import rt
from im_drive_sim.cli import Parser, UsageError


def _parse(*argv: str) -> rt.RtOptions:
    p = Parser(prog='x')
    rt.add_arguments(p)
    return rt.RtOptions.from_cli(p.parse_args(list(argv)))


def test_options_parse_and_bad_values_are_usage_errors():
    assert _parse() == rt.RtOptions(0, -1, False) and not _parse().requested
    cpu = min(os.sched_getaffinity(0))
    opts = _parse('--thread-priority', '50', '--cpu-affinity', str(cpu), '--lock-memory')
    assert opts == rt.RtOptions(50, cpu, True) and opts.requested
    for argv, says in (
        (('--thread-priority', '100'), 'must be 0 (off) or 1-99 (SCHED_FIFO), got 100'),
        (('--thread-priority', 'high'), "not an integer: 'high'"),
        (('--cpu-affinity', '4096'), 'CPU 4096 is not one this process may use'),
    ):
        with pytest.raises(UsageError, match=says.replace('(', r'\(').replace(')', r'\)')):
            _parse(*argv)


@pytest.fixture
def latency_file(tmp_path, monkeypatch):
    """The CPU latency request on a file of the test's, not the machine's device."""
    f = tmp_path / 'cpu_dma_latency'
    f.write_bytes(b'\xff' * 4)
    monkeypatch.setattr(rt, 'PM_QOS_PATH', str(f))
    monkeypatch.setattr(rt, '_pm_qos', {})
    return f


def test_the_cpu_latency_request_is_held_at_zero_and_recorded(latency_file):
    assert rt.latency_report() == {'held': False, 'latency_us': None, 'reason': 'not asked'}
    assert rt.hold_latency() is None and rt.hold_latency() is None  # (idempotent)
    assert latency_file.read_bytes() == b'\0\0\0\0'  # an s32 of 0 us, as cyclictest writes
    assert rt.report()['pm_qos'] == {'held': True, 'latency_us': 0, 'reason': ''}


def test_a_cpu_latency_request_not_permitted_is_one_line_and_the_run_goes_on(
    latency_file, monkeypatch
):
    def denied(*_a, **_k):
        raise PermissionError(errno.EACCES, 'Permission denied')

    monkeypatch.setattr(os, 'open', denied)
    (line,) = rt.apply(rt.RtOptions())
    assert line.startswith(f'the CPU latency request ({latency_file}) is not held (Permission')
    assert 'deep idle states' in line and 'udev rule' in line, line
    r = rt.report()['pm_qos']
    assert r['held'] is False and 'Permission denied' in r['reason'], r


def test_a_machine_without_the_cpu_latency_request_says_so(latency_file, monkeypatch):
    monkeypatch.setattr(rt, 'PM_QOS_PATH', str(latency_file.parent / 'none' / 'x'))
    (line,) = rt.apply(rt.RtOptions())
    assert 'No such file or directory' in line and 'no PM QoS here' in line, line


def test_refusals_say_why_and_how_to_grant_and_the_run_goes_on(monkeypatch, latency_file):
    def no_fifo(*_a):
        raise PermissionError(errno.EPERM, 'Operation not permitted')

    monkeypatch.setattr(os, 'sched_setscheduler', no_fifo)
    monkeypatch.setattr(rt, '_mlockall', lambda: errno.EPERM)
    lines = rt.apply(rt.RtOptions(50, -1, True))
    assert len(lines) == 2, lines
    assert lines[0].startswith('--thread-priority 50: not permitted (Operation not permitted')
    assert 'limits.conf' in lines[0] and '--cap-add=sys_nice --ulimit rtprio=99' in lines[0]
    assert lines[1].startswith('--lock-memory: not permitted (Operation not permitted')
    assert 'memlock' in lines[1] and '--ulimit memlock=-1' in lines[1]
    r = rt.report(rt.RtOptions(50, -1, True), lines)
    assert r['policy'] == 'SCHED_OTHER' and r['refused'] == lines
    assert r['requested'] == {'thread_priority': 50, 'cpu_affinity': -1, 'lock_memory': True}
    said: list[tuple[str, str]] = []
    rt.apply_and_say(
        rt.RtOptions(50), lambda s: said.append(('info', s)), lambda s: said.append(('warn', s))
    )
    assert [k for k, _ in said] == ['warn', 'info'] and 'SCHED_OTHER priority 0' in said[1][1]


def test_applied_when_permitted_in_a_child_process():
    """A child (so this process keeps its scheduling): as root (CI) everything applies;
    otherwise each option is refused in one line and the child still reports."""
    cpu = max(os.sched_getaffinity(0))
    code = (
        'import json; from im_drive_sim import rt; '
        f'o = rt.RtOptions(10, {cpu}, True); r = rt.apply(o); d = rt.report(o, r); '
        "import struct, os; p = '/dev/cpu_dma_latency'; d['device'] = "
        "struct.unpack('i', open(p, 'rb').read(4))[0] if os.access(p, os.R_OK) else None; "
        'print(json.dumps(d))'
    )
    p = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    r = json.loads(p.stdout)
    assert r['affinity'] == [cpu]  # needs no privilege
    assert r['kernel'] == f'{os.uname().release} {os.uname().version}' and r['cpu_model']
    assert isinstance(r['preempt_rt'], bool) and r['cpus'] == os.cpu_count()
    if os.geteuid() == 0:
        assert (r['policy'], r['priority'], r['memory_locked']) == ('SCHED_FIFO', 10, True), r
        if os.path.exists('/dev/cpu_dma_latency'):  # held: the kernel's request reads 0 us
            assert r['pm_qos']['held'] is True and r['device'] == 0, r
        assert r['refused'] == []
    else:
        assert r['policy'] == 'SCHED_OTHER' or r['priority'] == 10, r
        assert all('not permitted' in line for line in r['refused']), r


def test_after_the_loop_the_thread_runs_as_before_in_a_child_process():
    """What follows a loop (the DDS teardown, the exit, threads started then) runs with
    the thread's own policy and CPUs, not the loop's SCHED_FIFO on one CPU."""
    cpu = max(os.sched_getaffinity(0))
    code = (
        'import json, os, threading; from im_drive_sim import rt; '
        f'o = rt.RtOptions(10, {cpu}); before = rt.report()\n'
        'with rt.for_the_loop(o, print, print) as r:\n'
        '    inside = rt.report()\n'
        'after = rt.report(); later = {}\n'
        't = threading.Thread(target=lambda: later.update(rt.report())); t.start(); t.join()\n'
        "print(json.dumps([{k: d[k] for k in ('policy', 'priority', 'affinity')} "
        'for d in (before, inside, after, later)]))'
    )
    p = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    before, inside, after, later = json.loads(p.stdout.splitlines()[-1])
    assert inside['affinity'] == [cpu]
    if os.geteuid() == 0:
        assert (inside['policy'], inside['priority']) == ('SCHED_FIFO', 10), inside
    assert before['affinity'] == sorted(os.sched_getaffinity(0))
    assert after == before and later == before, (before, after, later)
