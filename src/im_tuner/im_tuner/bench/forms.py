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

:func:`.open.open_bench` decides which and builds it (the tuner's and ``sim_bench``'s);
the tuner hands its ``spin_until`` and ``supervise`` to the controller link, asks it for
the drive's report, and closes it. What a bench needs of the run (a new bag for a replaced
recorder, the checkpoint after it) comes through a :class:`RunHost`.
"""

from __future__ import annotations

import contextlib
import os
import posixpath
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

from im_drive_sim.cli import spawn_child
from im_drive_sim.contract import STATE_TOPIC

from ..names import DRIVE_HOST_NODE, HOST_LOOP_TOPICS, controller_topics
from ..tuning import BenchFailure
from .drive_status import DriveMonitor, drive_delta, drive_report
from .recorder_watch import (
    RecorderWatch,
    SpinUntil,
    recorder_subscribed,
    stop_recorder,
    wait_recorder_gone,
)
from .spec import BenchPlan

RECORDER_RESTARTS = 3  # replacements of a recorder child that died, per session
RECORDER_READY_TIMEOUT = 20.0  # [s] for a replacement recorder to subscribe


class RunHost(Protocol):
    """What a bench needs of the run it serves (the tuner's session; ``sim_bench``'s own)."""

    def begin(self, plan: BenchPlan) -> Path | None:
        """The bench is decided: make what the run needs; this session's bag directory
        (None: nothing is recorded)."""
        ...

    def tuner_metadata(self) -> dict[str, Any] | None:
        """The run's settings for the bag's metadata (None: no tuner run)."""
        ...

    def next_bag(self) -> Path | None:
        """A new bag directory for a recorder that replaces a dead one (None: none; a
        dead recorder then ends the bench)."""
        ...

    def bag_replaced(self, bag: Path) -> None:
        """A replacement recorder records into ``bag`` from now on (the run's books)."""
        ...

    def warn(self, text: str) -> None:
        """Say ``text`` to the person at the bench (one line)."""
        ...


class Bench(Protocol):
    """What a tuner run needs of a bench (see the module docstring)."""

    mode: str  #: 'inproc', 'realtime', 'processes', 'realtime-processes' or 'external'
    plan: BenchPlan

    def spin_until(self, pred: Callable[[], bool], timeout: float | None = None) -> bool:
        """Advance the bench and serve the tuner's node until ``pred()`` or the timeout."""
        ...

    def supervise(self) -> None:
        """Between spins: raise BenchFailure if a bench process died."""
        ...

    def recording_ready(
        self, timeout: float, received: Callable[[], dict[str, int]] | None = None
    ) -> bool:
        """The recorder takes every topic the run records (or nothing is recorded).

        ``received``: how many messages the tuner itself has received, per topic it
        subscribes to (the loss topic); before it stops the recorder, a bench whose
        recorder is another process waits until the bag holds as many since this call."""
        ...

    def session_start(self) -> None:
        """The session's experiments begin: a long-lived drive's counters are taken."""
        ...

    def drive_report(self) -> dict[str, Any] | None:
        """The drive's counters after the last experiment (summary.json); a long-lived
        (external) drive's over this session only (drive_status.drive_delta)."""
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


def _ended_by(rc: int) -> str:
    return f'killed by signal {-rc}' if rc < 0 else f'exit code {rc}'


def parameters(params: tuple[tuple[str, Any], ...]) -> list[Parameter]:
    """rclpy parameters of (name, value) pairs (BenchPlan)."""
    return [Parameter(name, value=value) for name, value in params]


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
        plan: BenchPlan,
        ctx: Context | None,
        node: Node | None,
        exe: Executor | None,
        *,
        bag_dir: Path | None,
        tuner_metadata: dict[str, Any] | None,
        command: list[str],
        should_stop: Callable[[], bool] | None = None,
    ) -> None:
        """``node``: the tuner's node, served by the bench's executor from now on (None:
        none, ``sim_bench``); ``tuner_metadata``: the run's settings in the bag's
        metadata (None: none). ``should_stop()``: the run was asked to stop (a signal);
        a real-time drive then gets zero current at once, before the tuner winds down."""
        from . import InProcessBench, bench_metadata

        self.plan = plan
        self.rec: Any = None
        self._final_status_sent = False

        realtime = plan.mode == 'realtime'

        def start_recorder(b: Any) -> None:
            if bag_dir is None:
                return
            from ..record.node import RECORD_POLL_STEPS, Recorder

            meta = bench_metadata(b)
            if tuner_metadata is not None:
                meta |= {'im_tuner.tuner': tuner_metadata}
            self.rec = Recorder(
                Node('recorder', context=ctx, start_parameter_services=False),
                bag_dir,
                compression=plan.spec.compression,
                extra_metadata=meta,
                command=command,
                # the real-time loop's topics: from its outbox's tap, lossless
                taps=b.outbox.tap() if realtime else None,
                # beside a real-time loop, the graph is looked at every 2 s (a graph
                # query holds the GIL for up to milliseconds); every topic it records
                # exists before the first period (wait_matched below)
                discovery_period=2.0 if realtime else 0.2,
                live=plan.spec.live,
            )
            self.rec.wait_matched(10.0)
            # beside a real-time loop every 50 ms (its tap rings hold 5 s): fewer rounds
            # holding the GIL; lock-step: every RECORD_POLL_STEPS steps
            b.add_poller(self.rec.poll, 250 if realtime else RECORD_POLL_STEPS)

        if exe is not None and node is not None:
            exe.executor.remove_node(node)
        self.mode = plan.mode
        drive_over = parameters(plan.drive_parameters)
        ctl_over = parameters(plan.controller_parameters) or None
        self.bench: Any
        if realtime:
            from .realtime import RealtimeBench

            self.bench = RealtimeBench(
                context=ctx,
                drive=plan.spec.drive_choice or plan.spec.drive,
                drive_overrides=drive_over,
                controller_overrides=ctl_over,
                before_start=start_recorder,
                should_stop=should_stop,
                rt_options=plan.spec.rt_options,
                host_check=plan.spec.host_check,
            )
        else:
            self.bench = InProcessBench(
                context=ctx,
                drive_overrides=drive_over or None,
                controller_overrides=ctl_over,
                before_start=start_recorder,
            )
        self.spin_until = self.bench.spin_until
        if node is None:
            return
        self.bench.executor.add_node(node)
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

    def recording_ready(
        self, timeout: float, received: Callable[[], dict[str, int]] | None = None
    ) -> bool:
        return True  # the recorder matched every topic before the first step

    def session_start(self) -> None:
        pass  # the drive starts with the session: its counters are the session's

    def _final_status(self) -> None:
        """The drive's counters at exit, published once (into the bag, if recording):
        before the summary's figures are taken, so that they count it too."""
        if not self._final_status_sent:
            self._final_status_sent = True
            self.bench.final_status()

    def drive_report(self) -> dict[str, Any] | None:
        if self.mode == 'realtime':
            self.bench.stop_loop()  # the run is over: zero current, counters stand still
        # the last status now, so that the summary's loop.outbox counts what the bag has
        self._final_status()
        d = self.bench.drive
        report = drive_report(
            {
                'mode': d.mode,
                'model': getattr(d.config, 'model', '-'),
                # as the bag's im_tuner.drive says: the delay the drive runs with
                'command_delay': str(int(getattr(d, 'command_delay', d.config.command_delay))),
                **{k: str(v) for k, v in vars(d.counters).items()},
            }
        )
        probe = getattr(d, 'delay_probe', None)
        if probe is not None:  # the declared delay as measured at start (hardware_probe)
            report['delay_probe'] = probe.text()
        if self.mode == 'realtime':
            report['loop'] = self.bench.timing()  # the composed loop's per-period figures
        return report

    def close_recording(self) -> list[str]:
        if self.rec is None:
            return []
        rec, self.rec = self.rec, None
        self._final_status()  # the drive's counters at exit, into the bag (once)
        if self.mode == 'realtime':  # what the loop could not hand to DDS or the recorder
            rec.add_metadata('im_tuner.outbox', self.bench.outbox.counts())
            say_outbox_losses(self.bench.outbox)
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
    """``processes`` / ``realtime-processes``: drive and controller as children;
    ``external``: the controller on the graph. Either way the recorder is a child (unless
    no bag). ``node`` None (``sim_bench``): nothing of the tuner's on the graph, the
    children only started, watched and stopped."""

    def __init__(
        self,
        plan: BenchPlan,
        node: Node | None,
        exe: Executor | None,
        *,
        bag_dir: Path | None,
        host: RunHost,
    ) -> None:
        self.plan = plan
        self.mode = plan.mode
        self.node = node
        self.spin_until = exe.spin_until if exe is not None else None
        self.host = host
        self.quiet = plan.spec.quiet
        self.children: dict[str, subprocess.Popen] = {}  # the live bench processes, by role
        self.ended: list[subprocess.Popen] = []  # ... and those already gone
        self.recorder_restarts = 0
        self.names = controller_topics(plan.spec.controller)
        self.rec_topics = (
            [self.names['loss'], '/' + STATE_TOPIC]
            if plan.mode in ('processes', 'realtime-processes')
            else [self.names['loss']]
        )
        if node is not None:  # the tuner's: its result topic (published before this)
            self.rec_topics.append(self.names['result'])
        self._ros2 = str(Path(sys.prefix) / 'bin' / 'ros2')
        self.recording = bag_dir is not None
        self.bag = bag_dir  #: the bag being recorded (a replacement's once replaced)
        #: the recorder child's status, and the tuner's counts it must reach
        self.watch = RecorderWatch(node) if node is not None and self.recording else None
        #: a drive host's 5 kHz topics, left to the host's own bag (a host is on the graph)
        self.excluded: list[str] = []
        if plan.mode == 'external' and node is not None and self.spin_until is not None:
            # wait for the controller's node name (a drive host announces its own first)
            # as long as discovery may take: a bag that took a host's 5 kHz topics across
            # the network would load it for the whole run
            ctl_name = posixpath.basename(self.names['node'])
            wait = plan.spec.probe_timeout()
            if not self.spin_until(lambda: ctl_name in node.get_node_names(), wait):
                host.warn(
                    f'warning: the controller {ctl_name!r} answered but its node name did not '
                    f'reach this computer within {wait:g} s; the bag '
                    "records every topic, a drive host's 5 kHz ones included"
                )
            if DRIVE_HOST_NODE in node.get_node_names():
                ns = posixpath.dirname(self.names['node'])
                self.excluded = [posixpath.join(ns, t) for t in HOST_LOOP_TOPICS]
        if bag_dir is not None:
            self._start_recorder(bag_dir)
        if plan.mode in ('processes', 'realtime-processes'):
            for pkg, role in (('im_drive_sim', 'drive_sim'), ('im_controller', 'controller')):
                self._spawn(role, [self._ros2, 'run', pkg, role, *plan.child_args(role)])
        self.monitor = DriveMonitor(node, self.names['drive_status']) if node else None

    def _spawn(self, role: str, argv: list[str]) -> None:
        out = subprocess.DEVNULL if self.quiet else None
        self.children[role] = spawn_child(argv, stdout=out)

    def _start_recorder(self, out_dir: Path) -> None:
        self.bag = out_dir
        if self.watch is not None:
            self.watch.expect(out_dir)
        quiet = ['--ros-args', '--disable-stdout-logs'] if self.quiet else []
        compression = self.plan.spec.compression
        exclude = ['--exclude-topics', *self.excluded] if self.excluded else []
        live = self.plan.spec.live.args() if self.plan.spec.live is not None else []
        args = ['--out', str(out_dir), '--compression', compression, *exclude, *live, *quiet]
        self._spawn('recorder', [self._ros2, 'run', 'im_tuner', 'recorder', *args])

    def _recorder_died(self, why: str) -> None:
        """Keep what the dead recorder wrote; go on recording into a new bag."""
        from ..record.repair import RepairError, repair_bag

        assert self.node is not None and self.bag is not None
        warn = self.host.warn
        dead = self.bag
        warn(
            f'warning: the recorder died ({why}); {dead.name} keeps what it '
            'wrote up to its last complete chunk'
        )
        self.node.get_logger().error(f'recorder child died ({why}); bag {dead} repaired')
        try:
            warn('  ' + repair_bag(dead).summary().splitlines()[0])
        except RepairError as exc:
            warn(f'  could not repair {dead}: {exc}')
        if self.recorder_restarts >= RECORDER_RESTARTS:
            warn(f'  not recording any more (already replaced {RECORDER_RESTARTS} times)')
            return
        new = self.host.next_bag()
        if new is None:
            return
        self.recorder_restarts += 1
        dead_endpoints = wait_recorder_gone(self.node, self.rec_topics)  # (ignored if left)
        self._start_recorder(new)
        self.host.bag_replaced(new)
        deadline = time.monotonic() + RECORDER_READY_TIMEOUT
        ready = False
        while time.monotonic() < deadline and self.children['recorder'].poll() is None:
            ready = recorder_subscribed(self.node, self.rec_topics, dead_endpoints)
            if ready:
                break
            time.sleep(0.05)  # graph queries need no spinning
        if ready:
            if self.watch is not None:
                self.watch.ready()
            warn(f'  recording again into {new.name} (messages in between are in no bag)')
        else:
            warn(
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
            why = _ended_by(rc)
            if role == 'recorder':
                self._recorder_died(why)
            else:
                if self.node is not None:
                    self.node.get_logger().error(f'bench process {role} died ({why})')
                raise BenchFailure(
                    f'the bench process {role} died ({why}); the run '
                    'stops here (the simulated plant cannot be restored '
                    'under a running search)'
                )

    def wait(self, should_stop: Callable[[], bool]) -> int:
        """``sim_bench``: until ``should_stop()`` or a bench process ends; the exit code
        (a nonzero one of a process that ended, else 0)."""
        drive = self.children['drive_sim']
        procs = list(self.children.values())
        while not should_stop() and all(p.poll() is None for p in procs):
            with contextlib.suppress(subprocess.TimeoutExpired):
                drive.wait(timeout=0.2)  # wakes at once if the drive exits
        code = 0
        for p in procs:
            if p.poll() is not None and p.returncode not in (0, None):
                code = p.returncode
        return code

    def recording_ready(
        self, timeout: float, received: Callable[[], dict[str, int]] | None = None
    ) -> bool:
        if not self.recording or self.node is None or self.spin_until is None:
            return True
        node, watch = self.node, self.watch
        assert watch is not None

        # the graph shows the recorder's subscriptions before they are matched: its own
        # status says when they are (record/status.py)
        def subscribed() -> bool:
            return recorder_subscribed(node, self.rec_topics) and watch.matched(self.rec_topics)

        ready = self.spin_until(subscribed, timeout)
        child = self.children.get('recorder')
        if not ready and child is not None:
            # a loaded machine: the child still imports, compiles or discovers -- waited
            # for as long as it works (im_tuner.patience), not failed at a fixed limit
            from ..patience import Patience

            def dead() -> None:
                if child.poll() is not None:
                    raise BenchFailure(f'the recorder child ended (exit {child.returncode})')

            wait = Patience(
                child.pid,
                'the recorder child to subscribe to every recorded topic',
                BenchFailure,
                note=self.host.warn,
                alive=dead,
            )
            while not (ready := self.spin_until(subscribed, 1.0)):
                wait.check()
        if ready:
            watch.ready(received)
        return ready

    def session_start(self) -> None:
        if self.mode == 'external' and self.monitor is not None and self.spin_until:
            # a long-lived drive's counters run on from before this session: the summary
            # gives their difference over the session (drive_status.drive_delta)
            self.monitor.mark(self.spin_until, 2.0)

    def drive_report(self) -> dict[str, Any] | None:
        monitor = self.monitor
        if monitor is None or self.spin_until is None:
            return None
        # the drive's counters after the last experiment (it reports about once a second)
        n0 = monitor.received
        self.spin_until(lambda: monitor.received > n0, 1.5)
        if self.mode == 'external':
            return drive_delta(monitor.start, monitor.last)
        return monitor.last

    def close_recording(self) -> list[str]:
        """Stop the recorder child (SIGINT: it closes its bag within ~1 s however much
        traffic flows) and check that it did: a recorder that had to be killed, or that
        exited with an error, left its bag unclosed -- it is repaired and reported."""
        from ..record.repair import bag_is_closed

        if 'recorder' in self.children and self.watch is not None and self.spin_until:
            self.watch.catch_up(self.spin_until, self.host.warn)  # the bag holds the losses
        p = self.children.pop('recorder', None)
        if p is None:
            return []
        self.ended.append(p)
        rc = stop_recorder(p, self.bag, self.host.warn)
        if rc == 0:
            return []
        why = _ended_by(rc)
        if self.bag is not None and bag_is_closed(self.bag):
            # the bag is whole (footer, counts): only the process's end was slow or unclean
            self.host.warn(f'note: the recorder closed {self.bag.name} whole, then ended ({why})')
            return []
        problem = f'the recorder did not close its bag ({why})'
        if self.bag is not None and self.bag.exists():  # (a refused recorder made none)
            from ..record.repair import RepairError, repair_bag

            try:
                rep = repair_bag(self.bag)
                problem += f'; {self.bag.name} repaired: ' + rep.summary().splitlines()[0]
            except RepairError as exc:
                problem += f'; could not repair {self.bag}: {exc}'
        return [problem]

    def stop_nodes(self) -> None:
        """Stop the drive and the controller, the recorder still recording (it takes what
        they sent last): ``sim_bench``'s order."""
        from im_drive_sim.runtime import stop_child

        for role in ('controller', 'drive_sim'):
            p = self.children.pop(role, None)
            if p is not None:
                self.ended.append(p)
                stop_child(p)

    def close(self) -> None:
        from im_drive_sim.runtime import stop_child

        self.close_recording()
        for p in [*reversed(list(self.children.values())), *self.ended]:
            stop_child(p)
