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


def test_refusals_say_why_and_how_to_grant_and_the_run_goes_on(monkeypatch):
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
        f'o = rt.RtOptions(10, {cpu}, True); r = rt.apply(o); print(json.dumps(rt.report(o, r)))'
    )
    p = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    r = json.loads(p.stdout)
    assert r['affinity'] == [cpu]  # needs no privilege
    assert r['kernel'] == f'{os.uname().release} {os.uname().version}' and r['cpu_model']
    assert isinstance(r['preempt_rt'], bool) and r['cpus'] == os.cpu_count()
    if os.geteuid() == 0:
        assert (r['policy'], r['priority'], r['memory_locked']) == ('SCHED_FIFO', 10, True), r
        assert r['refused'] == []
    else:
        assert r['policy'] == 'SCHED_OTHER' or r['priority'] == 10, r
        assert all('not permitted' in line for line in r['refused']), r
