"""check_drive's command line: ``ros2 run im_drive_sim check_drive``."""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path

from .. import rt
from ..cli import Parser, UsageError, add_config_option, check_ros_args, output_file
from .evaluate import json_ready
from .judges import conditions_line, exit_code, summary_line
from .probe import DriveLost, Interrupted
from .procedure import Options, run_check
from .thresholds import CHECK_LIMIT_S, CheckRefused


def parse_args(argv: list[str]) -> Options:
    """The options, checked; a bad one raises UsageError (one line, exit 2 in main)."""
    ap = Parser(
        prog='ros2 run im_drive_sim check_drive',
        description='Check a drive node against docs/interfaces.md (see '
        'docs/check-drive.md). Exit 0: all items pass; 1: some fail; '
        '2: refused (bad option, no drive, another commander); 3: none fails but some '
        'could not be judged (inconclusive: the check or the link fell behind).',
    )
    ap.add_argument(
        '--namespace', help='namespace of the drive (also: --ros-args -r __ns:=/bench1)'
    )
    add_config_option(ap, 'Ts, isq_max, encoder; default: the packaged motor')
    ap.add_argument(
        '--amplitude',
        type=float,
        default=0.5,
        help='current step [A] (default 0.5; at most 50 %% of isq_max)',
    )
    ap.add_argument(
        '--step-duration',
        type=float,
        default=0.02,
        help='duration of each of the +isq and -isq steps [s] (default 0.02)',
    )
    ap.add_argument(
        '--command-timeout',
        type=float,
        help="expected watchdog time [s] (default: the drive's command_timeout "
        'parameter, else 0.05)',
    )
    ap.add_argument(
        '--max-speed',
        type=float,
        default=30.0,
        help='abort to zero current above this |omega_meas| [rad/s] (default 30)',
    )
    ap.add_argument(
        '--timeout', type=float, default=10.0, help='discovery timeout [s] (default 10)'
    )
    ap.add_argument(
        '--json',
        metavar='FILE',
        type=output_file,
        help='write the results as JSON (checked before probing)',
    )
    rt.add_arguments(ap, "the check's process (every thread: give it less than the drive's)")
    ns = ap.parse_args(argv)
    for name in ('amplitude', 'step_duration', 'max_speed', 'timeout', 'command_timeout'):
        v = getattr(ns, name)
        if v is not None and not (math.isfinite(v) and v > 0):
            ap.error(f'--{name.replace("_", "-")} must be a positive number, got {v:g}')
    if not 0.005 <= ns.step_duration <= 0.5:
        ap.error(f'--step-duration {ns.step_duration:g} s: must be in [0.005, 0.5] s')
    if ns.drive_config is not None:  # the file is read after the probe starts: check it now
        from im_drive_sim.drive_file import load_config
        from im_drive_sim.params import ConfigError

        try:
            load_config(ns.drive_config)
        except ConfigError as exc:
            ap.error(str(exc))
        ns.drive_config = str(ns.drive_config)
    if ns.namespace is not None:
        from rclpy.validate_namespace import validate_namespace

        try:
            validate_namespace(ns.namespace if ns.namespace.startswith('/') else '/' + ns.namespace)
        except Exception as exc:  # rclpy raises InvalidNamespaceException
            ap.error(f'--namespace {ns.namespace!r}: {str(exc).splitlines()[0]}')
    rt_opts = rt.RtOptions.from_cli(ns)
    del ns.thread_priority, ns.cpu_affinity, ns.lock_memory
    return Options(**vars(ns), rt=rt_opts)


def main(args: list[str] | None = None) -> int:
    argv = sys.argv if args is None else args
    try:
        opts = parse_args(check_ros_args(argv)[1:])
    except UsageError as exc:
        print(f'error: check_drive: {exc}', file=sys.stderr)
        return 2
    from rclpy.node import Node

    from im_drive_sim.params import ConfigError
    from im_drive_sim.runtime import RosSession

    # A lost command is repaired within milliseconds, not a second (the file says why).
    os.environ.setdefault(
        'FASTRTPS_DEFAULT_PROFILES_FILE',
        str(Path(__file__).parent.parent / 'config' / 'check_drive_fastdds.xml'),
    )
    # the CPU latency request, as every real-time loop of the workspace: a check that
    # wakes late from a CPU's deep idle state would judge its own lateness. And the
    # scheduling asked for, before the ROS session: the middleware's threads, started
    # with it, inherit it (beside other load a check at the normal policy answers most
    # states late, and its latency item is inconclusive).
    refused = rt.apply(opts.rt)
    for line in refused:
        print(f'warning: {line}', file=sys.stderr, flush=True)
    session = RosSession(argv)
    node = Node('check_drive', **({'namespace': opts.namespace} if opts.namespace else {}))
    code = 0
    try:
        t_end = time.monotonic() + opts.timeout + CHECK_LIMIT_S

        def stop() -> bool:
            return session.stopped or time.monotonic() > t_end

        items, info = run_check(opts, node, lambda s: print(s, flush=True), stop)
        info['pm_qos'] = rt.latency_report()
        info['rt'] = rt.report(opts.rt, refused)
        for item in items:
            print(item.line())
        if info.get('conditions') and info.get('mode') == 'realtime':
            print(conditions_line(info['conditions']))
        print(summary_line(items, info.get('mode', ''), info.get('status_mode')))
        code = exit_code(items)
        if opts.json:
            verdict = {0: 'pass', 1: 'fail', 3: 'inconclusive'}[code]
            rows = [{**asdict(i), 'verdict': i.verdict} for i in items]
            opts.json.write_text(
                json.dumps(
                    json_ready({'passed': code == 0, 'verdict': verdict, **info, 'items': rows}),
                    indent=1,
                    allow_nan=False,
                )
                + '\n'
            )
    except (CheckRefused, ConfigError, DriveLost) as exc:
        print(f'error: check_drive: {exc}', file=sys.stderr)
        code = 1 if isinstance(exc, DriveLost) else 2
    except Interrupted:
        if session.stopped:
            print('check_drive: interrupted; zero current commanded', file=sys.stderr)
            code = 130
        else:  # the whole check's limit
            print(
                f'check_drive: INCONCLUSIVE: the check did not end within '
                f'{opts.timeout + CHECK_LIMIT_S:g} s (--timeout + {CHECK_LIMIT_S:g} s: a link '
                'that holds the states, or a host that starves the check); zero current '
                'commanded',
                file=sys.stderr,
            )
            code = 3
    finally:
        node.destroy_node()
        session.close()
    return code


if __name__ == '__main__':
    sys.exit(main())
