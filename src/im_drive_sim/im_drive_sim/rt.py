"""Real-time scheduling of a 5 kHz loop, as ros2_control_node does it (docs/real-drive.md,
"Real-time set-up"): ``--thread-priority N`` (SCHED_FIFO), ``--cpu-affinity CPU`` and
``--lock-memory`` (``mlockall``, through ctypes), applied to the thread that runs the loop,
and the kernel's PM QoS CPU latency request held whenever a real-time loop runs
(:func:`hold_latency`). What the system does not permit is not applied: :func:`apply`
returns one line saying why and how to grant it, and the run goes on; :func:`report`
describes what the loop runs with. No rclpy here.
"""

from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import errno
import os
import resource
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .cli import int_in
from .numeric import cpu_model

MCL_CURRENT, MCL_FUTURE = 1, 2

#: How to grant what was refused (one line each).
GRANT_PRIORITY = (
    'grant it with an rtprio limit (/etc/security/limits.conf: "<user> - rtprio 99") or '
    'CAP_SYS_NICE (docker: --cap-add=sys_nice --ulimit rtprio=99)'
)
GRANT_MEMLOCK = (
    'grant it with a memlock limit (/etc/security/limits.conf: "<user> - memlock '
    'unlimited") or CAP_IPC_LOCK (docker: --cap-add=ipc_lock --ulimit memlock=-1)'
)


#: The kernel's PM QoS CPU latency request (docs/real-drive.md, "The CPU latency request").
PM_QOS_PATH = '/dev/cpu_dma_latency'
GRANT_PM_QOS = (
    'grant it with a udev rule (/etc/udev/rules.d/99-cpu-dma-latency.rules: '
    'KERNEL=="cpu_dma_latency", GROUP="realtime", MODE="0660") or run as root'
)
#: What the request buys (docs/real-drive.md, "The CPU latency request").
PM_QOS_COST = 'the CPUs may sleep in deep idle states between periods, and more periods start late'

_pm_qos: dict[str, object] = {}  #: the held request: its file descriptor and what it says


def hold_latency() -> str | None:
    """Hold the PM QoS CPU latency request (:data:`PM_QOS_PATH`) at 0 us for the rest of
    the process (the file stays open; idempotent). None when held; else one line saying
    why not, what it costs and how to grant it (the caller says it and goes on)."""
    if _pm_qos.get('held'):
        return None
    path = PM_QOS_PATH
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CLOEXEC)
    except OSError as exc:
        _pm_qos.update(held=False, reason=f'{path}: {exc.strerror}')
        grant = GRANT_PM_QOS if exc.errno in (errno.EACCES, errno.EPERM) else 'no PM QoS here'
        return (
            f'the CPU latency request ({path}) is not held ({exc.strerror}): {PM_QOS_COST}; {grant}'
        )
    try:
        os.write(fd, (0).to_bytes(4, 'little', signed=True))
    except OSError as exc:
        os.close(fd)
        _pm_qos.update(held=False, reason=f'{path}: {exc.strerror}')
        return f'the CPU latency request ({path}) is not held ({exc.strerror}): {PM_QOS_COST}'
    _pm_qos.update(held=True, fd=fd, reason='', path=path)
    return None


def latency_report() -> dict[str, object]:
    """The CPU latency request as held by this process: ``held``, ``latency_us`` (0 when
    held), ``reason`` (why not, when not)."""
    held = bool(_pm_qos.get('held'))
    return {
        'held': held,
        'latency_us': 0 if held else None,
        'reason': '' if held else str(_pm_qos.get('reason', 'not asked')),
    }


#: The composed loop's busy-wait before each period start [us] (``loop_clock.SPIN_NS``;
#: ``host_check --spin-us`` tries others): it sleeps (timer slack 1 ns) to 40 us before
#: the start and spins the rest (research/NOTES.md, "From the source of im_drive_sim.rt").
SPIN_US = 40.0

#: The composed bench's loop priority when ``--thread-priority`` is not given: SCHED_FIFO
#: 50, as ros2_control_node's update loop (its ``thread_priority``).
DEFAULT_PRIORITY = 50


@dataclass(frozen=True)
class RtOptions:
    """What the loop asks for: ``priority`` 0 = the normal policy (SCHED_OTHER), 1-99 =
    SCHED_FIFO at that priority; ``cpu`` -1 = any CPU; ``lock_memory``: mlockall."""

    priority: int = 0
    cpu: int = -1
    lock_memory: bool = False

    @property
    def requested(self) -> bool:
        return bool(self.priority or self.cpu >= 0 or self.lock_memory)

    @classmethod
    def from_cli(cls, ns: Any, default_priority: int = 0) -> RtOptions:
        """The options given (``--thread-priority`` not given: ``default_priority``):
        ``ns`` has the three (an argparse namespace, the tuner's typed options)."""
        priority = default_priority if ns.thread_priority is None else ns.thread_priority
        return cls(priority, ns.cpu_affinity, ns.lock_memory)


_integer = int_in()  # any integer; the checks below say which


def _cpu(text: str) -> int:
    """A CPU this process may run on (``os.sched_getaffinity``)."""
    v = _integer(text)
    allowed = sorted(os.sched_getaffinity(0))
    if v not in allowed:
        raise argparse.ArgumentTypeError(
            f'CPU {v} is not one this process may use ({", ".join(map(str, allowed))})'
        )
    return v


def _priority(text: str) -> int:
    """A SCHED_FIFO priority this system offers, or 0 (off)."""
    v = _integer(text)
    lo, hi = os.sched_get_priority_min(os.SCHED_FIFO), os.sched_get_priority_max(os.SCHED_FIFO)
    if not (v == 0 or lo <= v <= hi):
        raise argparse.ArgumentTypeError(f'must be 0 (off) or {lo}-{hi} (SCHED_FIFO), got {v}')
    return v


_priority.__name__ = _cpu.__name__ = 'integer'


def add_arguments(
    parser: argparse.ArgumentParser,
    what: str = 'the real-time loop',
    default_priority: int = 0,
    helps: Mapping[str, str] | None = None,
) -> None:
    """The three options (docs/real-drive.md, "Real-time set-up"). ``--thread-priority``
    not given parses as None: :meth:`RtOptions.from_cli` puts ``default_priority``.
    ``helps``: an executable's own text of an option, by flag (the tuner's)."""
    g = parser.add_argument_group('real-time scheduling (docs/real-drive.md, "Real-time set-up")')
    default = (
        f'default {default_priority}, as ros2_control_node; 0: the normal policy'
        if default_priority
        else 'default 0: the normal policy'
    )
    text = {
        '--thread-priority': f'run {what} SCHED_FIFO at priority N (1-99; {default}); when '
        'not permitted, one line says how to grant it and the run goes on',
        '--cpu-affinity': f'pin {what} to this CPU (default: any)',
        '--lock-memory': 'lock the process memory in RAM (mlockall), so no page fault lands '
        'in a period',
        **(helps or {}),
    }
    g.add_argument(
        '--thread-priority',
        type=_priority,
        default=None,
        metavar='N',
        help=text['--thread-priority'],
    )
    g.add_argument(
        '--cpu-affinity', type=_cpu, default=-1, metavar='CPU', help=text['--cpu-affinity']
    )
    g.add_argument('--lock-memory', action='store_true', help=text['--lock-memory'])


def _mlockall() -> int:
    """mlockall(MCL_CURRENT | MCL_FUTURE); 0 or the errno."""
    libc = ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6', use_errno=True)
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
        return ctypes.get_errno() or errno.EPERM
    return 0


def apply(opts: RtOptions) -> list[str]:
    """Apply ``opts`` to the calling thread (and the process, for the memory lock).
    Returns one line per option that was not applied (why, and how to grant it). The
    CPU latency request is held whatever was asked (:func:`hold_latency`)."""
    refused: list[str] = []
    pm_qos = hold_latency()
    if pm_qos:
        refused.append(pm_qos)
    if opts.cpu >= 0:
        try:
            os.sched_setaffinity(0, {opts.cpu})
        except OSError as exc:
            refused.append(f'--cpu-affinity {opts.cpu}: not applied ({exc.strerror})')
    if opts.priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(opts.priority))
        except OSError as exc:
            soft = resource.getrlimit(resource.RLIMIT_RTPRIO)[0]
            refused.append(
                f'--thread-priority {opts.priority}: not permitted ({exc.strerror}; rtprio '
                f'limit {soft}), running SCHED_OTHER; {GRANT_PRIORITY}'
            )
    if opts.lock_memory:
        err = _mlockall()
        if err:
            soft = resource.getrlimit(resource.RLIMIT_MEMLOCK)[0]
            limit = 'unlimited' if soft == resource.RLIM_INFINITY else f'{soft} bytes'
            refused.append(
                f'--lock-memory: not permitted ({os.strerror(err)}; memlock limit {limit}); '
                f'{GRANT_MEMLOCK}'
            )
    return refused


def apply_and_say(opts: RtOptions, info: Any, warn: Any) -> dict[str, Any]:
    """:func:`apply`, then say it: ``warn(line)`` per refusal, ``info(line)`` with what
    the loop runs with; returns :func:`report`."""
    refused = apply(opts)
    for line in refused:
        warn(line)
    r = report(opts, refused)
    if opts.requested:
        info(
            f'real-time loop: {r["policy"]} priority {r["priority"]}, CPUs {r["affinity"]}, '
            f'memory locked {r["memory_locked"]}, CPU latency request held '
            f'{r["pm_qos"]["held"]}, PREEMPT_RT {r["preempt_rt"]}'
        )
    return r


@contextmanager
def for_the_loop(opts: RtOptions, info: Any, warn: Any) -> Iterator[dict[str, Any]]:
    """:func:`apply_and_say` for the length of a loop run on the calling thread; yields
    :func:`report`. After the loop the thread's policy, priority and CPUs are put back:
    what follows (flushing, the DDS teardown, the interpreter's exit, threads started
    then) runs as an ordinary thread, never SCHED_FIFO pinned beside the middleware's
    own threads. The memory lock and the CPU latency request are the process's: kept."""
    policy, param, cpus = os.sched_getscheduler(0), os.sched_getparam(0), os.sched_getaffinity(0)
    try:
        yield apply_and_say(opts, info, warn)
    finally:
        # (dropping a priority and widening back to CPUs the thread had are always allowed)
        if os.sched_getscheduler(0) != policy or os.sched_getparam(0) != param:
            os.sched_setscheduler(0, policy, param)
        if os.sched_getaffinity(0) != cpus:
            os.sched_setaffinity(0, cpus)


def _memory_locked() -> bool:
    """Whether the process has locked memory (VmLck > 0 in /proc/self/status)."""
    try:
        for line in Path('/proc/self/status').read_text().splitlines():
            if line.startswith('VmLck:'):
                return int(line.split()[1]) > 0
    except (OSError, ValueError, IndexError):
        pass
    return False


def _preempt_rt() -> bool:
    try:
        if Path('/sys/kernel/realtime').read_text().strip() == '1':
            return True
    except OSError:
        pass
    return 'PREEMPT_RT' in os.uname().version


def report(opts: RtOptions | None = None, refused: list[str] | None = None) -> dict[str, Any]:
    """What the calling thread runs with now: the policy and priority, the CPUs it may
    use, whether memory is locked, the kernel and the CPU; ``opts``/``refused``: what
    was asked and what was not applied."""
    policy = os.sched_getscheduler(0)
    names = {os.SCHED_OTHER: 'SCHED_OTHER', os.SCHED_FIFO: 'SCHED_FIFO', os.SCHED_RR: 'SCHED_RR'}
    u = os.uname()
    out: dict[str, Any] = {
        'policy': names.get(policy, str(policy)),
        'priority': os.sched_getparam(0).sched_priority,
        'affinity': sorted(os.sched_getaffinity(0)),
        'memory_locked': _memory_locked(),
        'pm_qos': latency_report(),
        'kernel': f'{u.release} {u.version}',
        'preempt_rt': _preempt_rt(),
        'cpu_model': cpu_model() or u.machine,
        'cpus': os.cpu_count(),
    }
    if opts is not None:
        out['requested'] = {
            'thread_priority': opts.priority,
            'cpu_affinity': opts.cpu,
            'lock_memory': opts.lock_memory,
        }
    out['refused'] = list(refused or [])
    return out
