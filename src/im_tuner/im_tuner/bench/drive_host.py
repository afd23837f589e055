"""The drive host: ``ros2 run im_tuner drive_host --drive sim|example|lib:PATH|pkg.mod:Class``.

A real bench puts the power stage on a real-time computer of its own and the engineer
tunes from another, as ros2_control puts the controller manager on the robot and the
planners elsewhere. This process is the drive's computer's half: the composed real-time
loop of ``--bench realtime`` (:class:`.realtime.RealtimeBench`: the drive's period, the
controller and its supervisor, every 200 us on the wall clock) and the recorder, which
takes the loop's topics from its outbox (lossless, whatever the network does). A tuner on
any computer of the same ``ROS_DOMAIN_ID`` attaches with ``--bench none`` (``auto`` finds
it) and reaches it at experiment rate only: the gains (parameters), ``start_experiment``,
``controller/loss``, ``reset_fault``, ``drive/status`` -- never the 5 kHz path.

The network may fail (docs/two-computers.md). The controller's tuner watchdog
(``tuner_timeout`` = ``--tuner-timeout``): once a tuner sent a heartbeat, none for that
long brings the drive to zero current, aborts a running experiment (``tuner_lost``) and
latches FAULT; a tuner that comes back clears it (the link's fault, not the drive's) and
runs the experiment again. A SIGINT/SIGTERM of the host: zero current at once, the bag
closed.
"""

from __future__ import annotations

import os
import sys
import time
from typing import Any

from rclpy.node import Node

from im_drive_sim import host as host_floor, rt
from im_drive_sim.cli import UsageError, check_ros_args
from im_drive_sim.contract import STATE_TOPIC
from im_drive_sim.runtime import RosSession

from ..names import DEFAULT_TIMING_TOLERANCE, DRIVE_HOST_NODE
from ..record.live import live_settings
from . import drive_spec
from .drive_host_main import DriveHostOptions, parser
from .forms import InProcess
from .open import open_bench
from .sim_bench import _Bag
from .spec import BenchSpec, bench_parameters


def _spec(
    cli: DriveHostOptions, choice: Any, host_check: dict | None = None, live: Any = None
) -> BenchSpec:
    """The composed real-time bench of ``cli`` (``choice``: the checked ``--drive``;
    ``host_check``: the host's check at start-up, recorded with the loop)."""
    config = str(cli.drive_config) if cli.drive_config else None
    drive, ctl = bench_parameters(config, cli.model, cli.seed)
    ctl = (
        ('timing_tolerance', int(cli.timing_tolerance)),
        ('tuner_timeout', float(cli.tuner_timeout)),
        *ctl,
    )
    return BenchSpec(
        requested='realtime',
        drive=cli.drive,
        drive_choice=choice,
        record=not cli.no_record,
        compression=cli.compression or 'lz4',
        drive_parameters=drive,
        controller_parameters=ctl,
        rt_options=rt.RtOptions.from_cli(cli, rt.DEFAULT_PRIORITY),
        host_check=host_check,
        quiet=False,
        live=live,
    )


#: [s] a new drive host looks for another drive on its domain before it starts its own
#: (discovery on one machine or a LAN: well under a second when nothing is lost)
PEER_WAIT_S = 2.0


def _another_drive(node: Node) -> str:
    """What of another drive is on the graph within PEER_WAIT_S ('' if nothing): a second
    node named drive_host, or a publisher of the drive's state."""
    deadline = time.monotonic() + PEER_WAIT_S
    while True:
        hosts = [n for n, ns in node.get_node_names_and_namespaces() if n == DRIVE_HOST_NODE]
        if len(hosts) > 1:  # (this node is one of them)
            return 'another drive_host'
        if node.count_publishers('/' + STATE_TOPIC) > 0:
            return f'a drive publishing /{STATE_TOPIC}'
        if time.monotonic() > deadline:
            return ''
        time.sleep(0.05)  # the graph is updated by the middleware: no spin needed


def main(args: list[str] | None = None) -> int:
    argv = sys.argv if args is None else args
    try:
        cli = parser().parse_args(check_ros_args(argv)[1:])
        cli.check_bag()
        if cli.model is not None and cli.drive != 'sim':
            raise UsageError(f"--model is the simulator's (--drive sim), not --drive {cli.drive}")
        live = live_settings(cli.live, cli.live_host, cli.live_rate, no_record=cli.no_record)
        try:
            choice = drive_spec.resolve(cli.drive, cli.drive_config)
        except drive_spec.DriveSpecError as exc:
            raise UsageError(str(exc)) from None
    except UsageError as exc:
        print(f'error: drive_host: {exc}', file=sys.stderr)
        return 2
    try:  # the host's check at start-up: can it meet the tolerance? (auto: what it can)
        cli.timing_tolerance, host_check, line = host_floor.check_before_run(
            cli.timing_tolerance,
            DEFAULT_TIMING_TOLERANCE,
            rt.RtOptions.from_cli(cli, rt.DEFAULT_PRIORITY),
        )
    except KeyboardInterrupt:
        return 130
    host = _Bag(cli, 'drive_host')
    bench: Any = None

    def _on_signal(_signum: int) -> None:
        if bench is not None:
            return  # running: the loop sees session.stopped and stops cleanly
        if not drive_spec.holds_hardware():
            host.interrupted()  # still starting, no power stage open
        raise KeyboardInterrupt  # starting: unwind, closing what is open (zero current)

    session = RosSession(argv, on_signal=_on_signal)
    code = 0
    marker = None
    ready = False
    try:
        # who we are, on the graph, announced before the controller: a tuner that sees
        # this node leaves the 5 kHz topics to this host's bag instead of pulling them
        # across the network
        marker = Node(DRIVE_HOST_NODE, start_parameter_services=False)
        other = _another_drive(marker)
        if other:  # two drives on one domain: each controller would command both
            raise UsageError(
                f'{other} on ROS_DOMAIN_ID {os.environ.get("ROS_DOMAIN_ID", "0")}: a drive host '
                'or drive already runs here; stop it, or give this one another ROS_DOMAIN_ID'
            )
        bench = open_bench(
            _spec(cli, choice, host_check, live),
            host,
            command=argv,
            should_stop=lambda: session.stopped,
        )
        assert isinstance(bench, InProcess)
        if session.stopped:  # Ctrl-C while it started (an interrupt numba swallowed)
            raise KeyboardInterrupt
        ready = True
        # the host check's line once the bench is up (a refusal before it is one line)
        if line and host_check['auto']:
            print(line, flush=True)
        elif line:
            print(f'warning: {line}', file=sys.stderr, flush=True)
        loop = bench.bench
        log = marker.get_logger()
        log.info(
            f'drive host ready: --drive {cli.drive}, controller '
            f'{loop.controller.get_fully_qualified_name()} (tuner watchdog '
            f'{cli.tuner_timeout:g} s), '
            + (f'recording to {bench.rec.out}' if bench.rec is not None else 'not recording')
            + (f'; live: {live.url} (Foxglove: Open connection)' if live is not None else '')
            + f'; tune it from any computer of ROS_DOMAIN_ID '
            f'{os.environ.get("ROS_DOMAIN_ID", "0")}: ros2 run im_tuner tuner --bench none'
        )
        loop.spin_until(lambda: session.stopped or loop.safe_stopped)
        if loop.safe_stopped and not session.stopped:
            log.error('the drive was safe-stopped: the host ends')
            code = 1
    except UsageError as exc:
        print(f'error: drive_host: {exc}', file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        if not ready:  # interrupted while starting; once running, Ctrl-C is its normal end
            print('drive_host: interrupted', file=sys.stderr, flush=True)
            code = 130
    except Exception as exc:  # a drive loop error: one line (zero current: safe_stop)
        print(f'error: drive_host: {exc}', file=sys.stderr)
        code = 1
    finally:
        if bench is not None:
            bench.close()
        if marker is not None:
            marker.destroy_node()
        session.close()
    if code == 2:
        host.remove()
    return code
