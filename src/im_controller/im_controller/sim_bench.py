"""The simulated bench: ``ros2 run im_controller sim_bench [--processes]``.

Brings up the drive simulator and the controller together, lock-step:

* one process (default, the fast path): both nodes in one thread; each step the
  controller takes state k and answers, the drive takes the command, steps and publishes
  state k+1 -- real DDS traffic, but no executor in the per-step path (parameters and
  services are served every ``service_period_steps`` steps and whenever idle);
* ``--processes``: ``ros2 run im_drive_sim drive_sim`` and ``ros2 run im_controller
  controller`` as two child processes (ended by PID: SIGINT, grace, SIGKILL).

Either way the graph is the same (``drive_sim``, ``controller``, their topics and
services), and so is what it computes: the same seed gives bit-identical losses.
The tuner brings this bench up itself when no controller is on the graph.

All traffic is recorded (``im_tuner``'s recorder) unless ``--no-record``: in one process
the recorder runs in the bench's loop and is polled between steps, so not a message is
lost; with ``--processes`` it is a third child, ``ros2 run im_tuner recorder``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import rclpy
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions

from im_drive_sim.cli import Parser, UsageError, input_file, int_in, parse_cli
from im_drive_sim.drive_sim_node import DriveSimNode
from im_drive_sim.params import ConfigError, load_config
from im_drive_sim.runtime import (
    ParameterOverrideError,
    stop_child,
    unknown_overrides,
    warn_unknown_overrides,
)

from .config import ControllerConfigError
from .controller_node import ControllerError, ControllerNode

NS_PER_S = 1_000_000_000


class InProcessBench:
    """Drive simulator + controller in one process, stepped lock-step by hand.

    ``spin_until(predicate, timeout)`` advances the bench (steps when the controller
    answers, serves services when idle) until ``predicate()`` is true -- usable by tests
    and by the tuner running in the same process.
    """

    def __init__(
        self,
        *,
        context=None,
        drive_overrides: list | None = None,
        controller_overrides: list | None = None,
        before_start=None,
    ) -> None:
        """``before_start(bench)`` runs once both nodes exist and match, before state 0 is
        published: the place to start a recorder that must not miss the first message."""
        self.drive = DriveSimNode(
            context=context, parameter_overrides=drive_overrides, warn_unknown=False
        )
        try:
            self.controller = ControllerNode(
                context=context, parameter_overrides=controller_overrides, warn_unknown=False
            )
        except Exception:
            self.drive.destroy_node()
            raise
        # `-p` overrides reach both nodes of this process: warn about those neither has.
        declared = set(self.drive._parameters) | set(self.controller._parameters)
        warn_unknown_overrides(
            self.controller,
            sorted(
                (set(unknown_overrides(self.drive)) | set(unknown_overrides(self.controller)))
                - declared
            ),
        )
        self.executor = SingleThreadedExecutor(context=self.drive.context)
        self.executor.add_node(self.drive)
        self.executor.add_node(self.controller)
        self.stop_requested = False
        self._since_service = 0
        #: (callable, period in steps): run every ``period`` lock-step round trips and at
        #: every idle iteration -- the recorder's poll goes here (see add_poller).
        self._pollers: list[tuple[object, int]] = []
        self._steps = 0
        # State 0 must not be published before the controller's subscription matches.
        if not self.controller.client.wait_for_drive(10.0):
            self.destroy()
            raise RuntimeError('controller and drive_sim did not match within 10 s')
        if before_start is not None:
            try:
                before_start(self)
            except Exception:
                self.destroy()
                raise
        self.drive.start()
        # drive/status about once a second, as the drive's own loop publishes it
        self._t0 = time.perf_counter()
        self._next_status = self._t0 + 1.0

    def _status(self) -> None:
        now = time.perf_counter()
        if now >= self._next_status:
            self.drive.publish_status(now - self._t0)
            self._next_status = now + 1.0

    def final_status(self) -> None:
        """The drive's counters at exit (before a recorder in this process is closed)."""
        self.drive.publish_status(time.perf_counter() - self._t0)

    def add_poller(self, poll, period_steps: int = 16) -> None:
        """Call ``poll()`` every ``period_steps`` lock-step steps and whenever idle.

        For a recorder in this process: it must take its messages between steps (an
        executor callback would serve one message per spin). Fast DDS holds at most 5000
        samples per reader, so ``period_steps`` must stay far below that."""
        if not 1 <= period_steps <= 1000:
            raise ValueError(f'period_steps must be in [1, 1000], got {period_steps}')
        self._pollers.append((poll, int(period_steps)))

    def step(self, idle_timeout: float = 0.01) -> bool:
        """One bench iteration: a lock-step round trip if the controller steps, otherwise
        serve services for up to ``idle_timeout`` s. True if the drive stepped."""
        ctl = self.controller
        ctl.take()
        if ctl.answer():
            if not self.drive.lockstep_poll(NS_PER_S):
                raise RuntimeError('drive did not receive the command within 1 s')
            self._steps += 1
            for poll, period in self._pollers:
                if self._steps % period == 0:
                    poll()
            self._since_service += 1
            if self._since_service >= ctl.service_period_steps:
                self._since_service = 0
                self.executor.spin_once(timeout_sec=0.0)
                self._status()
            return True
        self._status()
        for poll, _period in self._pollers:
            poll()
        self.executor.spin_once(
            timeout_sec=idle_timeout if not self._pollers else min(idle_timeout, 0.002)
        )
        return False

    def spin_until(self, predicate, timeout: float | None = None) -> bool:
        """Run the bench until ``predicate()`` (checked between iterations) or timeout [s]."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self.stop_requested and rclpy.ok(context=self.drive.context):
            if predicate():
                return True
            if deadline is not None and time.monotonic() > deadline:
                return False
            self.step()
        return predicate()

    def run(self) -> None:
        self.spin_until(lambda: False)

    def destroy(self) -> None:
        self.executor.shutdown()
        self.controller.destroy_node()
        self.drive.destroy_node()


def _parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog='ros2 run im_controller sim_bench',
        description='The simulated bench: drive_sim + controller, lock-step. Start '
        'experiments with /controller/start_experiment (std_srvs/Trigger); '
        'results on /controller/loss.',
    )
    ap.add_argument(
        '--processes',
        action='store_true',
        help='run drive_sim and controller as two processes (default: one)',
    )
    ap.add_argument('--config', metavar='FILE', type=input_file, help='drive parameter file (YAML)')
    ap.add_argument('--model', choices=('full', 'reduced'), help='drive model fidelity')
    ap.add_argument('--seed', type=int_in(0, 2**31 - 1), help='disturbance seed (>= 0)')
    ap.add_argument(
        '--no-record',
        action='store_true',
        help='do not record (default: all traffic to a bag, see --out)',
    )
    ap.add_argument(
        '--out',
        metavar='DIR',
        type=Path,
        help='bag directory to create (default: bags/sim_bench_<UTC time>)',
    )
    ap.add_argument(
        '--compression',
        choices=('none', 'zstd', 'lz4'),
        default='lz4',
        help='MCAP chunk compression of the bag (default: lz4; zstd: smaller files)',
    )
    return ap


def _check_cli(cli: argparse.Namespace) -> None:
    """What the children would refuse, refused here before anything is started."""
    if cli.config is not None:
        try:
            load_config(cli.config)
        except ConfigError as exc:
            raise UsageError(str(exc)) from None
    if cli.out is not None and not cli.no_record and cli.out.exists():
        raise UsageError(f'--out {cli.out}: already exists; choose a new directory')


def _recorder_module():
    """im_tuner's recorder, imported late: im_tuner depends on this package, not the
    reverse, and the bench runs without it when asked not to record."""
    try:
        from im_tuner import recorder_node
    except ImportError as exc:
        raise ControllerError(
            f'recording needs the im_tuner package ({exc}); install it or pass --no-record'
        ) from None
    return recorder_node


def bench_metadata(bench: InProcessBench) -> dict[str, dict]:
    """What the bag should say about this bench: the drive's configuration and seed, and
    the controller's parameters at start."""
    d = bench.drive
    drive = {
        'config_file': d.get_parameter('config_file').value or '(packaged default)',
        'model': d.config.model,
        'seed': d.get_parameter('seed').value,
        'config': json.dumps(dataclasses.asdict(d.config), sort_keys=True),
    }
    ctl = {name: p.value for name, p in sorted(bench.controller._parameters.items())}
    return {
        'im_tuner.drive': drive,
        'im_tuner.controller': {'parameters': json.dumps(ctl, sort_keys=True, default=str)},
    }


def _children(cli: argparse.Namespace, ros_args: list[str]) -> int:
    ros2 = str(Path(sys.prefix) / 'bin' / 'ros2')
    drive = [ros2, 'run', 'im_drive_sim', 'drive_sim']
    ctl = [ros2, 'run', 'im_controller', 'controller']
    if cli.config:
        drive += ['--config', str(cli.config)]
        ctl += ['--config', str(cli.config)]
    if cli.model:
        drive += ['--model', cli.model]
    if cli.seed is not None:
        drive += ['--seed', str(cli.seed)]
    if ros_args:
        drive += ros_args
        ctl += ros_args
    procs = []
    out = made = None
    if not cli.no_record:
        rn = _recorder_module()  # fail early, with the reason, if it is not installed
        out = Path(cli.out or rn.default_out_dir(prefix='sim_bench'))
        # what this run creates (the bag and any missing parents): removed again if a
        # child refuses its configuration at start (exit 2), so a refusal leaves nothing
        made = out
        while not made.parent.exists() and made.parent != made.parent.parent:
            made = made.parent
        rec = [
            ros2,
            'run',
            'im_tuner',
            'recorder',
            '--compression',
            cli.compression,
            '--out',
            str(out),
        ]
        procs.append(subprocess.Popen(rec))
    procs += [subprocess.Popen(drive), subprocess.Popen(ctl)]
    stop = {'sig': None}

    def _on_signal(signum, _frame) -> None:
        stop['sig'] = signum

    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    code = 0
    try:
        while stop['sig'] is None and all(p.poll() is None for p in procs):
            with contextlib.suppress(subprocess.TimeoutExpired):
                procs[-2].wait(timeout=0.2)  # wakes at once if the drive exits
        for p in procs:
            if p.poll() is not None and p.returncode not in (0, None):
                code = p.returncode
    finally:
        for p in reversed(procs):  # the recorder last: it takes what the others sent
            stop_child(p)
    if code == 2 and made is not None and made.exists():
        shutil.rmtree(made, ignore_errors=True)  # refused at start: the bag holds nothing
    return code


def main(args: list[str] | None = None) -> int:
    argv = sys.argv if args is None else args
    try:
        cli = parse_cli(_parser(), argv)
        _check_cli(cli)
    except UsageError as exc:
        print(f'error: sim_bench: {exc}', file=sys.stderr)
        return 2
    ros_args = argv[argv.index('--ros-args') :] if '--ros-args' in argv else []
    if cli.processes:
        return _children(cli, ros_args)
    config = str(cli.config) if cli.config else None
    drive_over = [
        Parameter(n, value=v)
        for n, v in (('config_file', config), ('model', cli.model), ('seed', cli.seed))
        if v is not None
    ]
    ctl_over = [Parameter('drive_config_file', value=config)] if config else []
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    bench = None
    rec = None

    def _on_signal(signum, _frame) -> None:
        if bench is None:
            raise KeyboardInterrupt
        bench.stop_requested = True

    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)

    def _start_recorder(b: InProcessBench) -> None:
        nonlocal rec
        rn = _recorder_module()
        from rclpy.node import Node

        try:
            rec = rn.Recorder(
                Node('recorder', start_parameter_services=False),
                cli.out or rn.default_out_dir(prefix='sim_bench'),
                compression=cli.compression,
                extra_metadata=bench_metadata(b),
                command=argv,
            )
        except (rn.BagError, rn.RecorderError) as exc:
            raise ControllerError(str(exc)) from None
        rec.wait_matched(10.0)
        b.add_poller(rec.poll, rn.RECORD_POLL_STEPS)
        b.drive.get_logger().info(f'recording all topics to {rec.out}')

    try:
        bench = InProcessBench(
            drive_overrides=drive_over or None,
            controller_overrides=ctl_over or None,
            before_start=None if cli.no_record else _start_recorder,
        )
        bench.run()
    except (
        ConfigError,
        ControllerError,
        ControllerConfigError,
        ParameterOverrideError,
        InvalidParameterValueException,
        InvalidParameterTypeException,
    ) as exc:
        print(f'error: sim_bench: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        pass
    finally:
        if bench is not None:
            bench.drive.log_summary()
            bench.final_status()
        if rec is not None:
            rec.close(settle=0.05)
            rec.node.destroy_node()
        if bench is not None:
            bench.destroy()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    sys.exit(main())
