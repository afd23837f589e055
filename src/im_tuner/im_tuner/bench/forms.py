"""The benches a tuner run opens, behind one protocol (:class:`Bench`).

* :class:`InProcess` (``--bench inproc``): drive simulator + controller nodes in this
  process, lock-step, the recorder polled between steps (``inprocess.InProcessBench``);
* :class:`InProcess` with ``realtime`` (``--bench realtime``): a drive and the controller
  composed in this process, one wall-clock loop (``realtime.RealtimeBench``);
* :class:`Children` (``processes``, ``realtime-processes``, ``external``): the drive and the
  controller as child processes (lock-step or real time), or a controller already on the
  graph; the recorder is a child process. Children are supervised between spins: a dead
  recorder is replaced (its bag repaired), a dead drive or controller ends the run. They
  end with the tuner, however it ends (``PR_SET_PDEATHSIG``).

The tuner's main only opens one, hands its ``spin_until`` and ``supervise`` to the
controller link, asks it for the drive's report, and closes it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from im_drive_sim.contract import STATE_TOPIC

from ..link import DriveMonitor, controller_topics, drive_report
from ..tuning import BenchFailure

RECORDER_RESTARTS = 3  # replacements of a recorder child that died, per session
RECORDER_READY_TIMEOUT = 20.0  # [s] for a replacement recorder to subscribe
SpinUntil = Callable[[Callable[[], bool], float | None], bool]


class Bench(Protocol):
    """What a tuner run needs of a bench (see the module docstring)."""

    mode: str  #: 'inproc', 'realtime', 'processes', 'realtime-processes' or 'external'

    def spin_until(self, pred: Callable[[], bool], timeout: float | None = None) -> bool:
        """Advance the bench and serve the tuner's node until ``pred()`` or the timeout."""
        ...

    def supervise(self) -> None:
        """Between spins: raise BenchFailure if a bench process died."""
        ...

    def recording_ready(self, timeout: float) -> bool:
        """The recorder takes every topic the run records (or nothing is recorded)."""
        ...

    def drive_report(self) -> dict[str, Any] | None:
        """The drive's counters after the last experiment (summary.json)."""
        ...

    def close_recording(self) -> list[str]:
        """Close the bag (bounded); returns what went wrong (empty: the bag is closed)."""
        ...

    def close(self) -> None:
        """Close the bag, stop what this bench started."""
        ...


class Executor:
    """spin_until over a plain executor (external controller / child processes)."""

    def __init__(self, context: Context) -> None:
        self.executor = SingleThreadedExecutor(context=context)

    def spin_until(self, pred: Callable[[], bool], timeout: float | None = None) -> bool:
        deadline = None if timeout is None else time.monotonic() + timeout
        while not pred():
            if deadline is not None and time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.005)
        return True


def controller_on_graph(node: Node, spin_until: SpinUntil, controller: str, timeout: float) -> bool:
    """Does ``controller``'s start service appear on the graph within ``timeout`` s?"""
    start = controller_topics(controller)['start']

    def seen() -> bool:
        return any(n == start for n, _t in node.get_service_names_and_types())

    return spin_until(seen, timeout)


def recorder_endpoints(node: Node, topics: list[str]) -> set[bytes]:
    """GIDs of the subscriptions a node named ``recorder`` has on ``topics``."""
    return {
        bytes(i.endpoint_gid)
        for t in topics
        for i in node.get_subscriptions_info_by_topic(t)
        if i.node_name == 'recorder'
    }


def recorder_subscribed(
    node: Node, topics: list[str], ignore: frozenset[bytes] = frozenset()
) -> bool:
    """Does a recorder subscribe to every topic of ``topics``? ``ignore``: GIDs of a dead
    recorder's subscriptions, which stay on the graph until its DDS lease runs out
    (about a second): a replacement must not be taken for ready on them."""
    for t in topics:
        if not any(
            i.node_name == 'recorder' and bytes(i.endpoint_gid) not in ignore
            for i in node.get_subscriptions_info_by_topic(t)
        ):
            return False
    return True


def die_with_parent() -> None:
    """preexec_fn of the bench children: SIGTERM when the tuner dies, however it dies
    (Linux prctl PR_SET_PDEATHSIG; it survives the exec chain of `ros2 run`), so a
    SIGKILLed tuner leaves no orphan drive, controller or recorder behind."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass  # not Linux: the children outlive a killed tuner (SIGINT still ends them)


def parameter_args(params: list[Parameter]) -> list[str]:
    """``-p name:=value`` arguments of a child node."""
    return [a for p in params for a in ('-p', f'{p.name}:={p.value}')]


# ------------------------------------------------------------------------------ in process
def say_outbox_losses(outbox: Any) -> None:
    """One line on stderr when the real-time loop's outbox dropped or could not publish
    a message (a reader that stopped taking; a full ring): the run says so."""
    by_topic = outbox.lost_by_topic()
    lost = sum(by_topic.values())
    if lost:
        where = ', '.join(f'{topic} {n}' for topic, n in by_topic.items() if n)
        print(
            f'warning: the real-time loop could not deliver {lost} messages ({where}): '
            'a reader that stopped taking, or a full outbox; counted in the summary '
            "(loop.outbox) and the bag's im_tuner.outbox metadata",
            file=sys.stderr,
            flush=True,
        )


class InProcess:
    """``--bench inproc`` (lock-step) or ``realtime`` (the composed real-time bench,
    ``realtime.RealtimeBench``): the nodes in this process, the recorder polled between
    steps (periods)."""

    def __init__(
        self,
        ctx: Context,
        node: Node,
        exe: Executor,
        *,
        realtime: bool = False,
        rt_options: Any = None,  # im_drive_sim.rt.RtOptions: the loop's scheduling
        drive: Any = 'sim',  # a --drive name, or a drive_spec.DriveChoice
        drive_overrides: list[Parameter],
        controller_overrides: list[Parameter],
        bag_dir: Path | None,
        compression: str,
        tuner_metadata: dict[str, Any],
        command: list[str],
        should_stop: Callable[[], bool] | None = None,
    ) -> None:
        """``should_stop()``: the run was asked to stop (a signal); a real-time drive then
        gets zero current at once, before the tuner winds down."""
        from . import InProcessBench, bench_metadata

        self.rec: Any = None

        def start_recorder(b: Any) -> None:
            if bag_dir is None:
                return
            from ..record.node import RECORD_POLL_STEPS, Recorder

            meta = bench_metadata(b) | {'im_tuner.tuner': tuner_metadata}
            self.rec = Recorder(
                Node('recorder', context=ctx, start_parameter_services=False),
                bag_dir,
                compression=compression,
                extra_metadata=meta,
                command=command,
                # the real-time loop's topics: from its outbox's tap, lossless
                taps=b.outbox.tap() if hasattr(b, 'outbox') else None,
                # beside a real-time loop, the graph is looked at every 2 s (a graph
                # query holds the GIL for up to milliseconds); every topic it records
                # exists before the first period (wait_matched below)
                discovery_period=2.0 if hasattr(b, 'outbox') else 0.2,
            )
            self.rec.wait_matched(10.0)
            # beside a real-time loop every 50 ms (its tap rings hold 5 s): fewer rounds
            # holding the GIL; lock-step: every RECORD_POLL_STEPS steps
            b.add_poller(self.rec.poll, 250 if hasattr(b, 'outbox') else RECORD_POLL_STEPS)

        exe.executor.remove_node(node)
        self.mode = 'realtime' if realtime else 'inproc'
        self.bench: Any
        if realtime:
            from .realtime import RealtimeBench

            self.bench = RealtimeBench(
                context=ctx,
                drive=drive,
                drive_overrides=drive_overrides,
                controller_overrides=controller_overrides or None,
                before_start=start_recorder,
                should_stop=should_stop,
                rt_options=rt_options,
            )
        else:
            self.bench = InProcessBench(
                context=ctx,
                drive_overrides=drive_overrides,
                controller_overrides=controller_overrides or None,
                before_start=start_recorder,
            )
        self.bench.executor.add_node(node)
        self.spin_until = self.bench.spin_until
        # Discovery can be slow on a loaded machine: look again now that ours exist.
        if (
            node.count_publishers('/' + STATE_TOPIC) > 1
            or sum(n == 'controller' for n in node.get_node_names()) > 1
        ):
            raise BenchFailure(
                'another drive or controller appeared on the graph (ROS_DOMAIN_ID '
                f'{os.environ.get("ROS_DOMAIN_ID", "0")}): not adding a simulated one '
                'beside it; use --bench none, or another domain'
            )

    def supervise(self) -> None:
        pass  # nothing runs outside this process

    def recording_ready(self, timeout: float) -> bool:
        return True  # the recorder matched every topic before the first step

    def drive_report(self) -> dict[str, Any] | None:
        stop_loop = getattr(self.bench, 'stop_loop', None)
        if callable(stop_loop):
            stop_loop()  # the run is over: zero current, and counters that stand still
        d = self.bench.drive
        report = drive_report(
            {
                'mode': getattr(d, 'mode', 'realtime'),
                'model': getattr(d.config, 'model', '-'),
                **{k: str(v) for k, v in vars(d.counters).items()},
            }
        )
        if report is not None and hasattr(self.bench, 'timing'):
            report['loop'] = self.bench.timing()  # the composed loop's per-period figures
        return report

    def close_recording(self) -> list[str]:
        if self.rec is None:
            return []
        rec, self.rec = self.rec, None
        self.bench.final_status()  # the drive's counters at exit, into the bag
        outbox = getattr(self.bench, 'outbox', None)
        if outbox is not None:  # what the loop could not hand to DDS or the recorder
            rec.add_metadata('im_tuner.outbox', outbox.counts())
            say_outbox_losses(outbox)
        counts = rec.close(settle=0.05)
        lost = sum(c['lost'] for c in counts.values())
        if lost:
            print(
                f'warning: the recorder counted {lost} lost messages (see {rec.out}/metadata.yaml)',
                file=sys.stderr,
            )
        rec.node.destroy_node()
        return []

    def close(self) -> None:
        self.close_recording()
        self.bench.destroy()


# ------------------------------------------------------------------------------ children
class Children:
    """``processes`` / ``realtime``: drive and controller as children; ``external``: the
    controller on the graph. Either way the recorder is a child (unless no bag)."""

    def __init__(
        self,
        mode: str,
        node: Node,
        exe: Executor,
        *,
        controller: str,
        drive_overrides: list[Parameter],
        controller_overrides: list[Parameter],
        bag_dir: Path | None,
        compression: str,
        progress: Any,
    ) -> None:
        self.mode = mode
        self.node = node
        self.spin_until = exe.spin_until
        self.compression = compression
        self.progress = progress
        self.children: dict[str, subprocess.Popen] = {}  # the live bench processes, by role
        self.ended: list[subprocess.Popen] = []  # ... and those already gone
        self.recorder_restarts = 0
        self.names = controller_topics(controller)
        self.rec_topics = (
            [self.names['loss'], '/' + STATE_TOPIC]
            if mode in ('processes', 'realtime-processes')
            else [self.names['loss']]
        )
        # set by attach(): the run whose bags a replaced recorder continues
        self.rundir: Any = None
        self.tuning: Any = None
        self.session: dict[str, Any] = {}
        self._ros2 = str(Path(sys.prefix) / 'bin' / 'ros2')
        # the children log to /rosout (recorded) and their log files, not the console
        self._quiet_logs = ['--ros-args', '--disable-stdout-logs']
        self.recording = bag_dir is not None
        if bag_dir is not None:
            self._start_recorder(bag_dir)
        if mode in ('processes', 'realtime-processes'):
            rt = ['--mode', 'realtime'] if mode == 'realtime-processes' else []
            r2, q = self._ros2, self._quiet_logs
            self._spawn(
                'drive_sim',
                [r2, 'run', 'im_drive_sim', 'drive_sim', *rt, *q, *parameter_args(drive_overrides)],
            )
            self._spawn(
                'controller',
                [
                    r2,
                    'run',
                    'im_controller',
                    'controller',
                    *rt,
                    *q,
                    *parameter_args(controller_overrides),
                ],
            )
        self.monitor = DriveMonitor(node, self.names['drive_status'])

    def attach(self, rundir: Any, tuning: Any, session: dict[str, Any]) -> None:
        self.rundir, self.tuning, self.session = rundir, tuning, session

    def _spawn(self, role: str, argv: list[str]) -> None:
        self.children[role] = subprocess.Popen(
            argv,
            stdout=subprocess.DEVNULL,
            preexec_fn=die_with_parent,  # noqa: PLW1509 (only prctl, async-signal-safe)
        )

    def _start_recorder(self, out_dir: Path) -> None:
        self._spawn(
            'recorder',
            [
                self._ros2,
                'run',
                'im_tuner',
                'recorder',
                '--out',
                str(out_dir),
                '--compression',
                self.compression,
                *self._quiet_logs,
            ],
        )

    def _recorder_died(self, why: str) -> None:
        """Keep what the dead recorder wrote; go on recording into a new bag."""
        from ..record.repair import RepairError, repair_bag

        progress = self.progress
        dead = self.rundir.bag_dirs()[-1]
        progress.warn(
            f'warning: the recorder died ({why}); {dead.name} keeps what it '
            'wrote up to its last complete chunk'
        )
        self.node.get_logger().error(f'recorder child died ({why}); bag {dead} repaired')
        try:
            progress.warn('  ' + repair_bag(dead).summary().splitlines()[0])
        except RepairError as exc:
            progress.warn(f'  could not repair {dead}: {exc}')
        if self.recorder_restarts >= RECORDER_RESTARTS:
            progress.warn(f'  not recording any more (already replaced {RECORDER_RESTARTS} times)')
            return
        self.recorder_restarts += 1
        dead_endpoints = frozenset(recorder_endpoints(self.node, self.rec_topics))
        new = self.rundir.next_bag_dir()
        self._start_recorder(new)
        self.session.setdefault('more_bags', []).append(
            {'bag': new.name, 'first_record': len(self.tuning.records)}
        )
        self.tuning._checkpoint()
        deadline = time.monotonic() + RECORDER_READY_TIMEOUT
        ready = False
        while time.monotonic() < deadline and self.children['recorder'].poll() is None:
            ready = recorder_subscribed(self.node, self.rec_topics, dead_endpoints)
            if ready:
                break
            time.sleep(0.05)  # graph queries need no spinning
        if ready:
            progress.warn(f'  recording again into {new.name} (messages in between are in no bag)')
        else:
            progress.warn(
                f'  warning: the new recorder ({new.name}) did not subscribe to every recorded '
                f'topic within {RECORDER_READY_TIMEOUT:g} s; the run goes on, and what is '
                'published until it does is in no bag'
            )

    def supervise(self) -> None:
        """Between spins: a dead bench process is noticed at once."""
        for role, p in list(self.children.items()):
            rc = p.poll()
            if rc is None:
                continue
            self.ended.append(self.children.pop(role))
            why = f'killed by signal {-rc}' if rc < 0 else f'exit code {rc}'
            if role == 'recorder':
                self._recorder_died(why)
            else:
                self.node.get_logger().error(f'bench process {role} died ({why})')
                raise BenchFailure(
                    f'the bench process {role} died ({why}); the run '
                    'stops here (the simulated plant cannot be restored '
                    'under a running search)'
                )

    def recording_ready(self, timeout: float) -> bool:
        if not self.recording:
            return True
        return self.spin_until(lambda: recorder_subscribed(self.node, self.rec_topics), timeout)

    def drive_report(self) -> dict[str, Any] | None:
        # the drive's counters after the last experiment (it reports about once a second)
        n0 = self.monitor.received
        self.spin_until(lambda: self.monitor.received > n0, 1.5)
        return self.monitor.last

    def close_recording(self) -> list[str]:
        """Stop the recorder child (SIGINT: it closes its bag within ~1 s however much
        traffic flows) and check that it did: a recorder that had to be killed, or that
        exited with an error, left its bag unclosed -- it is repaired and reported."""
        from im_drive_sim.runtime import stop_child

        p = self.children.pop('recorder', None)
        if p is None:
            return []
        self.ended.append(p)
        rc = stop_child(p)
        if rc == 0:
            return []
        why = f'killed by signal {-rc}' if rc < 0 else f'exit code {rc}'
        problem = f'the recorder did not close its bag ({why})'
        if self.rundir is not None:
            from ..record.repair import RepairError, repair_bag

            bag = self.rundir.bag_dirs()[-1]
            try:
                problem += f'; {bag.name} repaired: ' + repair_bag(bag).summary().splitlines()[0]
            except RepairError as exc:
                problem += f'; could not repair {bag}: {exc}'
        return [problem]

    def close(self) -> None:
        from im_drive_sim.runtime import stop_child

        self.close_recording()
        for p in [*reversed(list(self.children.values())), *self.ended]:
            stop_child(p)
