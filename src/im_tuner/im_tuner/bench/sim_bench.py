"""The simulated bench: ``ros2 run im_tuner sim_bench [--processes]``: the drive
simulator and the controller, lock-step, in one process (``.inprocess``) or as two
children (``--processes``), opened as the tuner's bench is (``bench.open.open_bench``).
Either way the graph and the losses are the same (the same seed: bit-identical). All
traffic is recorded unless ``--no-record``: in one process the recorder is polled between
steps; with ``--processes`` it is a third child, ``ros2 run im_tuner recorder``.
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path
from typing import Any, NoReturn

from im_drive_sim.cli import UsageError, check_ros_args
from im_drive_sim.drive_file import load_config
from im_drive_sim.params import ConfigError
from im_drive_sim.runtime import RosSession

from ..record.run_info import default_out_dir
from ..rundir import made_by_create
from ..tuner_args import ros_parameters
from .forms import Children, InProcess, parameters
from .open import open_bench
from .sim_bench_main import SimBenchOptions, SimulatorOptions, parser
from .spec import BenchSpec, Params, bench_parameters, parameter_args


def _overrides(cli: SimBenchOptions, ros_args: list[str]) -> tuple[Params, Params]:
    """The drive's and the controller's parameters from the command line's flags (a
    packaged drive's experiment and gains but those the user's ``-p NAME:=VALUE`` sets)."""
    given = {p.split(':=', 1)[0] for p in ros_parameters(ros_args) if ':=' in p}
    config = str(cli.drive_config) if cli.drive_config else None
    return bench_parameters(config, cli.model, cli.seed, given)


def _child_args(cli: SimBenchOptions, ros_args: list[str]) -> tuple[tuple[str, ...], ...]:
    """``--processes``: the drive's and the controller's command-line tails (their own
    flags, the drive's experiment and gains, then the user's ``--ros-args``)."""
    drive: list[str] = []
    ctl: list[str] = []
    if cli.drive_config:
        drive += ['--drive-config', str(cli.drive_config)]
        ctl += ['--drive-config', str(cli.drive_config)]
        gains = _overrides(cli, ros_args)[1][1:]  # (after drive_config_file)
        if gains:
            ctl += ['--ros-args', *parameter_args(gains)]
    if cli.model:
        drive += ['--model', cli.model]
    if cli.seed is not None:
        drive += ['--seed', str(cli.seed)]
    return (*drive, *ros_args), (*ctl, *ros_args)


def _check_nodes(cli: SimBenchOptions, ros_args: list[str]) -> None:
    """``--processes`` with ``--ros-args``: build the drive and the controller here first
    (a private context, no log output, destroyed at once), so that an override either
    child would refuse at start is refused here, on one line, before the recorder child
    (which would print its own lines) or anything else is started."""
    from rclpy.context import Context

    from im_controller.controller_node import ControllerNode
    from im_drive_sim.drive_sim_node import DriveSimNode

    from .open import NODE_REFUSALS

    drive_over, ctl_over = (parameters(p) for p in _overrides(cli, ros_args))
    ctx = Context()
    session = RosSession(['sim_bench', *ros_args, '--disable-stdout-logs'], context=ctx)
    try:
        drive = DriveSimNode(context=ctx, parameter_overrides=drive_over, warn_unknown=False)
        try:
            ControllerNode(
                context=ctx, parameter_overrides=ctl_over, composed_with=drive
            ).destroy_node()
        finally:
            drive.destroy_node()
    except NODE_REFUSALS as exc:
        raise UsageError(str(exc).strip().splitlines()[0]) from None
    finally:
        session.close()


class _Bag:
    """sim_bench's side of its bench (forms.RunHost): one bag, no run; a dead recorder
    ends the bench."""

    def __init__(self, cli: SimulatorOptions, prog: str) -> None:
        self.prog = prog
        self.out = None if cli.no_record else Path(cli.out or default_out_dir(prefix=prog))
        # what this run creates (the bag and any missing parents): removed again if a
        # child refuses its configuration at start (exit 2), so a refusal leaves nothing
        self.made = None if self.out is None else made_by_create(self.out)[0]

    def begin(self, _plan: object) -> Path | None:
        return self.out

    def tuner_metadata(self) -> None:
        return None

    def next_bag(self) -> None:
        return None

    def bag_replaced(self, _bag: Path) -> None:
        pass

    def warn(self, text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    def remove(self) -> None:
        if self.made is not None and self.made.exists():
            shutil.rmtree(self.made, ignore_errors=True)  # refused at start: holds nothing

    def interrupted(self) -> NoReturn:
        """A signal while the bench starts: end now (numba's compile can take tens of
        seconds under load, and an exception raised in its callbacks is swallowed); the
        bag begun holds nothing of a run yet: removed."""
        self.remove()
        os.write(2, f'{self.prog}: interrupted\n'.encode())
        os._exit(130)


def main(args: list[str] | None = None) -> int:
    argv = sys.argv if args is None else args
    try:
        cli = parser().parse_args(check_ros_args(argv)[1:])
        if cli.drive_config is not None:  # (what the children would refuse, refused here)
            try:
                load_config(cli.drive_config)
            except ConfigError as exc:
                raise UsageError(str(exc)) from None
        cli.check_bag()
        ros_args = argv[argv.index('--ros-args') :] if '--ros-args' in argv else []
        if cli.processes and ros_args:
            _check_nodes(cli, ros_args)
    except UsageError as exc:
        print(f'error: sim_bench: {exc}', file=sys.stderr)
        return 2
    drive_over, ctl_over = _overrides(cli, ros_args)
    spec = BenchSpec(
        requested='processes' if cli.processes else 'inproc',
        record=not cli.no_record,
        compression=cli.compression,
        drive_parameters=drive_over,
        controller_parameters=ctl_over,
        child_args=_child_args(cli, ros_args) if cli.processes else None,
        quiet=False,
    )
    host = _Bag(cli, 'sim_bench')
    bench: Any = None

    def _on_signal(_signum: int) -> None:
        if bench is None:
            host.interrupted()  # still starting, a simulation
        if isinstance(bench, InProcess):
            bench.bench.stop_requested = True

    # the children's parent: the same signal handling as the tuner's (RosSession), and
    # the same end (they die with it: PR_SET_PDEATHSIG)
    session = RosSession(argv, on_signal=_on_signal)
    code = 0
    try:
        bench = open_bench(spec, host, command=argv, should_stop=lambda: session.stopped)
        if isinstance(bench, InProcess):
            bench.bench.stop_requested = session.stopped  # a signal as it came up
        if isinstance(bench, Children):
            code = bench.wait(lambda: session.stopped)
            bench.stop_nodes()  # (the recorder last: it takes what the others sent)
        else:
            lockstep = bench.bench
            if bench.rec is not None:
                lockstep.drive.get_logger().info(f'recording all topics to {bench.rec.out}')
            try:
                lockstep.run()
            finally:
                lockstep.drive.log_summary()
                if bench.rec is None:
                    lockstep.final_status()
    except UsageError as exc:
        print(f'error: sim_bench: {exc}', file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        pass
    finally:
        if bench is not None:
            bench.close()
        session.close()
    if code == 2 and cli.processes:
        host.remove()
    return code
