"""The simulated bench: ``ros2 run im_tuner sim_bench [--processes]``.

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

All traffic is recorded (``im_tuner.record.node``) unless ``--no-record``: in one
process the recorder runs in the bench's loop and is polled between steps, so not a
message is lost; with ``--processes`` it is a third child, ``ros2 run im_tuner recorder``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.parameter import Parameter

from im_controller.config import ControllerConfigError
from im_controller.controller_node import ControllerError
from im_drive_sim.cli import Parser, UsageError, input_file, int_in, parse_cli
from im_drive_sim.params import ConfigError, load_config
from im_drive_sim.runtime import (
    ParameterOverrideError,
    RosSession,
    stop_child,
)

from ..record import node as recorder_node
from .inprocess import InProcessBench, bench_metadata


def _parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog='ros2 run im_tuner sim_bench',
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
        help='do not record (default: all traffic to a bag, see --out); refused with '
        '--out or --compression, which would be ignored',
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
    if cli.no_record:  # a bag option with no bag would be silently ignored
        for flag, value in (('--out', cli.out), ('--compression', cli.compression)):
            if value is not None:
                raise UsageError(
                    f'{flag} {value} is for the bag, and --no-record records none: '
                    'give one or the other'
                )
    cli.compression = cli.compression or 'lz4'
    if cli.out is not None and cli.out.exists():
        raise UsageError(f'--out {cli.out}: already exists; choose a new directory')


NODE_REFUSALS = (
    ConfigError,
    ControllerError,
    ControllerConfigError,
    ParameterOverrideError,
    InvalidParameterValueException,
    InvalidParameterTypeException,
)


def _overrides(cli: argparse.Namespace) -> tuple[list[Parameter], list[Parameter]]:
    """The drive's and the controller's parameters from the command line's flags."""
    config = str(cli.config) if cli.config else None
    drive_over = [
        Parameter(n, value=v)
        for n, v in (('config_file', config), ('model', cli.model), ('seed', cli.seed))
        if v is not None
    ]
    ctl_over = [Parameter('drive_config_file', value=config)] if config else []
    return drive_over, ctl_over


def _check_nodes(cli: argparse.Namespace, ros_args: list[str]) -> None:
    """``--processes`` with ``--ros-args``: build the drive and the controller here first
    (a private context, no log output, destroyed at once), so that an override either
    child would refuse at start is refused here, on one line, before the recorder child
    (which would print its own lines) or anything else is started."""
    from rclpy.context import Context

    from im_controller.controller_node import ControllerNode
    from im_drive_sim.drive_sim_node import DriveSimNode

    drive_over, ctl_over = _overrides(cli)
    ctx = Context()
    session = RosSession(['sim_bench', *ros_args, '--disable-stdout-logs'], context=ctx)
    try:
        drive = DriveSimNode(context=ctx, parameter_overrides=drive_over, warn_unknown=False)
        try:
            ControllerNode(
                context=ctx, parameter_overrides=ctl_over, warn_unknown=False
            ).destroy_node()
        finally:
            drive.destroy_node()
    except NODE_REFUSALS as exc:
        raise UsageError(str(exc).strip().splitlines()[0]) from None
    finally:
        session.close()


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
        rn = recorder_node
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
        if ros_args:
            try:
                _check_nodes(cli, ros_args)
            except UsageError as exc:
                print(f'error: sim_bench: {exc}', file=sys.stderr)
                return 2
        return _children(cli, ros_args)
    drive_over, ctl_over = _overrides(cli)
    bench = None
    rec = None

    def _on_signal(_signum: int) -> None:
        if bench is None:
            raise KeyboardInterrupt  # still starting: nothing to stop cleanly yet
        bench.stop_requested = True

    session = RosSession(argv, on_signal=_on_signal)

    def _start_recorder(b: InProcessBench) -> None:
        nonlocal rec
        rn = recorder_node
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
    except NODE_REFUSALS as exc:
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
        session.close()
    return 0


if __name__ == '__main__':
    os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    sys.exit(main())
