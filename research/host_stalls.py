"""A host that stalls, made on purpose: a command and every process it starts are frozen
for ``--hold`` seconds every ``--every`` seconds (the cgroup v1 freezer), as a hypervisor
stalls a VM -- every thread stops, SCHED_FIFO ones included, and the wall clock runs on.

    sudo .venv/bin/python research/host_stalls.py [--every 0.5] [--hold 0.006] -- CMD ...

What it is for: the wall-clock tests and a real-time run judged against a host louder
than this machine is today (``.venv/bin/python research/host_stalls.py -- .venv/bin/python
-m pytest -m serial``: the serial pass must pass, skipping only where the floor it measures
says no tolerance would be honest). Root and ``/sys/fs/cgroup/freezer``; the cgroup is made
for the run and removed after it. Prints how many stalls it made and the command's exit
status, and exits with it. A bad value is one line on stderr, exit 2.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

FREEZER = Path('/sys/fs/cgroup/freezer')


def _set(group: Path, state: str) -> None:
    (group / 'freezer.state').write_text(state)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='host_stalls', description=__doc__.splitlines()[0])
    ap.add_argument('--every', type=float, default=0.5, help='seconds between stalls')
    ap.add_argument('--hold', type=float, default=0.006, help='seconds each stall lasts')
    ap.add_argument('--after', type=float, default=0.0, help='seconds before the first stall')
    ap.add_argument('command', nargs=argparse.REMAINDER)
    a = ap.parse_args(argv)
    cmd = a.command[1:] if a.command[:1] == ['--'] else a.command
    if not cmd or not (0 < a.hold < a.every) or a.after < 0:
        print('error: host_stalls: give -- COMMAND, and 0 < --hold < --every', file=sys.stderr)
        return 2
    if not FREEZER.is_dir() or os.geteuid() != 0:
        print('error: host_stalls: needs root and the cgroup v1 freezer', file=sys.stderr)
        return 2
    group = FREEZER / f'host_stalls_{os.getpid()}'
    group.mkdir()
    stalls = 0
    try:
        # the child joins the group before it runs the command: all it starts is in it
        join = 'echo $$ > "$1" && shift && exec "$@"'
        proc = subprocess.Popen(['sh', '-c', join, 'sh', str(group / 'cgroup.procs'), *cmd])
        start = time.monotonic() + a.after
        while proc.poll() is None:
            time.sleep(max(0.0, min(a.every, start - time.monotonic()) if stalls == 0 else a.every))
            if time.monotonic() < start or proc.poll() is not None:
                continue
            _set(group, 'FROZEN')
            time.sleep(a.hold)
            _set(group, 'THAWED')
            stalls += 1
        code = proc.wait()
    finally:
        _set(group, 'THAWED')
        for _ in range(100):  # the group empties as its last process is reaped
            try:
                group.rmdir()
                break
            except OSError:
                time.sleep(0.05)
    print(f'host_stalls: {stalls} stalls of {a.hold * 1e3:g} ms every {a.every:g} s; exit {code}',
          file=sys.stderr)  # fmt: skip
    return code


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
