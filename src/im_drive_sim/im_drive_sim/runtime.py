"""Process plumbing shared by the workspace's executables (ROS side, not the core).

* :func:`run_stepped_node`: the ``main()`` of a node with a hand-stepped loop -- rclpy
  initialised without its signal handlers (they would shut the context down under the
  loop), SIGINT/SIGTERM asking the loop to stop at the next step boundary, a clean
  summary/flush/destroy, configuration errors as one line and exit code 2.
* :func:`stop_child`: end a child process we started, by PID (SIGINT, grace, SIGKILL).
* :func:`publish_retry`: back-pressure instead of a crash when a reliable KEEP_ALL reader
  (the recorder) is full.
"""
from __future__ import annotations

import signal
import subprocess
import sys
import time
from typing import Callable

import rclpy
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.signals import SignalHandlerOptions

RCLError = _rclpy.RCLError


class PublishStalled(RuntimeError):
    """A reliable reader took nothing for longer than the back-pressure timeout."""


def publish_retry(pub, msg, context, timeout: float = 30.0) -> int:
    """Publish ``msg`` after a publish raised: wait for the readers to make room.

    With a reliable KEEP_ALL publisher, a reader that does not take (a stalled recorder)
    fills up; Fast DDS then blocks ``publish`` for its max blocking time (100 ms) and rmw
    raises -- the sample is not queued and no sequence number is used. Retrying until
    the reader drains turns that into back-pressure: the publisher slows down, nothing is
    dropped. Returns the number of retries; raises :class:`PublishStalled` after
    ``timeout`` s, or re-raises at once when the context is shut down.
    """
    deadline = time.monotonic() + timeout
    retries = 0
    while True:
        if not rclpy.ok(context=context):
            raise RCLError(f'{pub.topic_name}: cannot publish, context shut down')
        retries += 1
        try:
            pub.publish(msg)
            return retries
        except RCLError:
            if time.monotonic() > deadline:
                raise PublishStalled(
                    f'{pub.topic_name}: a reliable reader took no message for {timeout:.0f} s '
                    '(recorder stalled?); refusing to drop data') from None


def run_stepped_node(argv: list[str], make_node: Callable[[], object],
                     config_errors: tuple[type[BaseException], ...], prog: str,
                     on_exit: Callable[[object], None] | None = None) -> int:
    """Create the node with ``make_node()``, run ``node.run(executor)`` until it returns
    or a signal sets ``node.stop_requested``; returns the process exit code.

    The node must provide ``run(executor)``, ``stop_requested``, ``flush()`` and
    ``destroy_node()``; ``on_exit(node)`` runs first at shutdown (a summary log).
    """
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    executor = None
    stop = {'requested': False}

    def _on_signal(signum, _frame) -> None:
        stop['requested'] = True
        if node is None:
            raise KeyboardInterrupt  # still starting: nothing to stop cleanly yet
        node.stop_requested = True
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    try:
        node = make_node()
        node.stop_requested = stop['requested']
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)
        node.run(executor)
    except (*config_errors, InvalidParameterValueException,
            InvalidParameterTypeException) as exc:
        # A bad file or a bad --ros-args -p value at start: one line, nothing started.
        print(f'error: {prog}: {exc}', file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            if on_exit is not None:
                on_exit(node)
            node.flush()
            if executor is not None:
                executor.shutdown()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def stop_child(proc: subprocess.Popen, grace: float = 5.0) -> int:
    """End a child we started, by PID: SIGINT, wait ``grace`` s, then SIGKILL."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=grace)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=grace)
    return proc.returncode
