"""Clear a controller's safety fault: ``ros2 run im_controller reset_fault``.

Calls the controller's ``~/reset_fault`` service once and prints its answer on one line
(the shipped ``ros2`` has no ``ros2 service call``).  Check the drive first: the
controller then holds the position it measures (docs/controller.md, "Services").  Exit
0 cleared (or no fault), 1 refused or no answer within ``--timeout``, 2 bad input, 130
interrupted.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from typing import Any

from im_drive_sim.cli import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK

from . import contract as C

DEFAULT_TIMEOUT = 10.0  # [s] to find the service and get its answer (a loaded machine)


def reset_command(controller: str = '/controller') -> str:
    """The shell command that clears the fault of the controller node ``controller``
    (fully qualified), for the messages that tell a user to reset a fault."""
    node = controller if controller.startswith('/') else '/' + controller
    extra = '' if node == '/controller' else f' --controller {node}'
    return f'ros2 run im_controller reset_fault{extra}'


def service_name(controller: str) -> str:
    """The fully qualified reset service of the controller node ``controller``."""
    node = controller if controller.startswith('/') else '/' + controller
    return f'{node.rstrip("/")}/{C.RESET_SERVICE}'


def _parser():
    from im_drive_sim.cli import Parser, finite_float

    ap = Parser(
        prog='ros2 run im_controller reset_fault',
        description="Clear the controller's safety fault (its ~/reset_fault service) after "
        'checking the drive; prints the answer. Exit 0 cleared (or no fault), 1 refused or '
        'no answer, 2 bad input.',
    )
    ap.add_argument(
        '--controller',
        default='/controller',
        metavar='NODE',
        help='the controller node (default /controller)',
    )
    ap.add_argument(
        '--timeout',
        type=finite_float(0.0, 3600.0, lo_open=True, unit='s'),
        default=DEFAULT_TIMEOUT,
        metavar='S',
        help='how long to wait for the service and its answer [s] (default '
        f'{DEFAULT_TIMEOUT:g}; a loaded machine may need more)',
    )
    return ap


def _wait(
    done: Callable[[], bool],
    wait: Callable[[], object],
    ros: Any,
    deadline: float,
    timeout_line: str,
) -> tuple[int, str] | None:
    """``wait()`` until ``done()``; None then, else the exit code and line: interrupted
    (``ros.stopped``), or ``timeout_line`` past ``deadline`` (monotonic [s])."""
    while not done():
        if ros.stopped:
            return EXIT_INTERRUPTED, 'reset_fault: interrupted'
        if time.monotonic() > deadline:
            return EXIT_FAILED, timeout_line
        wait()
    return None


def call_reset(argv: list[str], srv: str, timeout: float) -> tuple[int, str]:
    """Call ``srv`` once; returns the exit code and the line to print."""
    from rclpy.node import Node
    from std_srvs.srv import Trigger

    from im_drive_sim.runtime import RosSession

    ros = RosSession(argv)
    node = None
    try:
        node = Node(
            f'reset_fault_{os.getpid()}', start_parameter_services=False, context=ros.context
        )
        cli = node.create_client(Trigger, srv)
        deadline = time.monotonic() + timeout
        missing = _wait(
            cli.service_is_ready,
            lambda: cli.wait_for_service(timeout_sec=0.05),
            ros,
            deadline,
            f'error: reset_fault: {srv} not on the graph of ROS_DOMAIN_ID '
            f'{os.environ.get("ROS_DOMAIN_ID", "0")} after {timeout:g} s (is the '
            'controller running? --controller names it; a loaded machine may need '
            'a longer --timeout)',
        )
        if missing is not None:
            return missing
        import rclpy

        fut = cli.call_async(Trigger.Request())
        silent = _wait(
            fut.done,
            lambda: rclpy.spin_once(node, timeout_sec=0.05),
            ros,
            deadline,
            f'error: reset_fault: {srv} did not answer within {timeout:g} s',
        )
        if silent is not None:
            return silent
        resp = fut.result()
        if resp.success:
            return EXIT_OK, f'{srv}: {resp.message}'
        return EXIT_FAILED, f'error: reset_fault: {srv}: {resp.message}'
    finally:
        if node is not None:
            node.destroy_node()
        ros.close()


def main(args: list[str] | None = None) -> int:
    from im_drive_sim.cli import UsageError, parse_cli, run_cli

    argv = list(sys.argv if args is None else args)

    def body() -> int:
        cli = parse_cli(_parser(), argv)
        srv = service_name(cli.controller)
        from rclpy.exceptions import InvalidServiceNameException, InvalidTopicNameException
        from rclpy.validate_full_topic_name import validate_full_topic_name

        try:
            validate_full_topic_name(srv)
        except (InvalidTopicNameException, InvalidServiceNameException) as exc:
            raise UsageError(
                f'--controller {cli.controller!r}: not a valid node name '
                f'({str(exc).splitlines()[0]})'
            ) from None
        code, line = call_reset(argv, srv, cli.timeout)
        print(line, file=sys.stdout if code == EXIT_OK else sys.stderr, flush=True)
        return code

    return run_cli('reset_fault', body)


if __name__ == '__main__':
    from im_drive_sim.cli import executable

    executable('reset_fault', main)
