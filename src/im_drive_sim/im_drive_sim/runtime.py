"""Process plumbing shared by the workspace's executables (ROS side, not the core): a
hand-stepped node's ``main()`` (:func:`run_stepped_node`, :class:`RosSession`), lossless
publishing (:func:`publish_lossless`), the nodes' parameter conventions
(:func:`parameter_hygiene`, :class:`LenientDoubles`) and :func:`stop_child`.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from typing import Any

import rclpy
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
)
from rclpy.duration import Duration
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterNotDeclaredException,
)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions

RCLError = _rclpy.RCLError


class PublishStalled(RuntimeError):
    """A reliable reader took nothing for longer than the back-pressure timeout."""


#: publishers whose messages a real-time loop hands to an ``outbox.Outbox`` instead of
#: publishing them itself (id(publisher) -> its Outbox; ``Outbox.route``)
ROUTES: dict[int, Any] = {}


def publish_lossless(pub, msg, context) -> int:
    """Publish ``msg`` on a reliable KEEP_ALL publisher, never dropping it: the common
    case is one ``publish``; if a full reader made it raise, :func:`publish_retry`.
    Returns the back-pressure retries (0 when the first publish went through).

    ``msg``: a message, its CDR bytes, or a ``cdr.Float64ArrayWire``. A publisher routed
    to an outbox (a composed real-time loop, :data:`ROUTES`) hands the message over
    instead: never blocks, 0 retries."""
    box = ROUTES.get(id(pub))
    if box is not None:
        box.emit(pub, msg)
        return 0
    payload = getattr(msg, 'payload', None)
    if payload is not None:
        msg = payload()
    try:
        pub.publish(msg)
        return 0
    except RCLError:
        return publish_retry(pub, msg, context)


def publish_retry(pub, msg, context, timeout: float = 30.0) -> int:
    """Publish ``msg`` after a publish raised: wait for the readers to make room.

    With a reliable KEEP_ALL publisher, a reader that does not take (a stalled recorder)
    fills up; Fast DDS then blocks ``publish`` for its max blocking time and rmw raises,
    the sample not queued. Retrying until the reader drains turns that into
    back-pressure: nothing is dropped. Returns the number of retries; raises
    :class:`PublishStalled` after ``timeout`` s, or re-raises at once when the context is
    shut down.
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
                    '(recorder stalled?); refusing to drop data'
                ) from None


class LenientDoubles:
    """Mixin for an rclpy ``Node`` with the workspace's parameter conventions:

    * an integer given at start for a double parameter (``-p k_iw:=20``, or ``k_iw: 20``
      in a params file) is taken as that double, as a ``set_parameters`` call is
      (:meth:`integers_as_doubles`, a node's pre-set callback); rclpy would refuse it at
      declaration ('expecting type DOUBLE');
    * a request to set an undeclared parameter is refused naming it (rclpy's own message
      names none). Done here rather than in a pre-set callback: rclpy hands every
      pre-set callback the original list and concatenates what they return.
    """

    def integers_as_doubles(self, params: list[Parameter]) -> list[Parameter]:
        """A pre-set parameters callback: an integer for a double parameter is that double
        (``k_iw:=20`` means 20.0)."""
        out = []
        for p in params:
            if (
                p.type_ == Parameter.Type.INTEGER
                and self.has_parameter(p.name)
                and self.get_parameter(p.name).type_ == Parameter.Type.DOUBLE
            ):
                p = Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
            out.append(p)
        return out

    def _refuse_undeclared(self, parameter_list) -> None:
        missing = [p.name for p in parameter_list if not self.has_parameter(p.name)]
        # rclpy (7.1) has no public reader of the node's allow_undeclared_parameters: this
        # mixin reads its own base class's attribute
        if missing and not self._allow_undeclared_parameters:
            raise ParameterNotDeclaredException(missing)

    def set_parameters_atomically(self, parameter_list):
        self._refuse_undeclared(parameter_list)
        return super().set_parameters_atomically(parameter_list)

    def set_parameters(self, parameter_list):
        self._refuse_undeclared(parameter_list)
        return super().set_parameters(parameter_list)

    def declare_parameter(self, name, value=None, descriptor=None, ignore_override=False):
        # rclpy (7.1) has no public API for the start-up overrides (-p, params files): the
        # mixin rewrites its own base class's table before Node.declare_parameter reads it
        over = getattr(self, '_parameter_overrides', {})
        p = over.get(name)
        if (
            isinstance(value, float)
            and not ignore_override
            and p is not None
            and p.type_ == Parameter.Type.INTEGER
        ):
            over[name] = Parameter(name, Parameter.Type.DOUBLE, float(p.value))
        return super().declare_parameter(name, value, descriptor, ignore_override)


class IoNodeOwner:
    """Mixin for an rclpy ``Node`` that owns a hidden ``io_node`` (destroyed with it) and
    publishers whose last samples must reach their subscribers before it exits.

    A subclass says which publishers those are in :meth:`flushed_publishers`.
    """

    io_node: Any

    def flushed_publishers(self) -> tuple[Any, ...]:
        """The publishers :meth:`flush` waits on, in order."""
        raise NotImplementedError

    def flush(self, timeout: float = 1.0) -> None:
        """Wait (bounded: ``timeout`` [s] a publisher) until subscribers acknowledged
        everything published: the last samples before an exit are not lost (reliable QoS
        only promises this while the writer lives)."""
        for pub in self.flushed_publishers():
            pub.wait_for_all_acked(Duration(seconds=timeout))

    def destroy_node(self) -> None:
        self.io_node.destroy_node()
        super().destroy_node()  # (the Node this is mixed into)


def start_overrides(options: Iterable[tuple[str, object]]) -> list[Parameter] | None:
    """The start-up parameter overrides of the command-line shortcuts that were given
    (``(parameter name, option value)``, None: not given); None when none was."""
    return [Parameter(name, value=value) for name, value in options if value is not None] or None


class ParameterOverrideError(ValueError):
    """A start-up override the node cannot honour: one line, exit code 2."""


def parameter_hygiene(
    node,
    facts: dict[str, object] | None = None,
    *,
    warn_unknown: bool = True,
    composed_with: object | None = None,
) -> list[str]:
    """Call at the end of a node's ``__init__``, once every parameter is declared.

    ``facts``: read-only parameters that report what the node enforces or publishes
    (name -> the true value); an override that differs raises
    :class:`ParameterOverrideError` (the node would otherwise advertise a value it does
    not use). Returns the override names that match no parameter of this node, logged
    as a warning unless ``warn_unknown`` is false. ``composed_with``: the other node of
    a composed bench (both receive the process's ``-p`` overrides): an override that
    neither declares is refused (ParameterOverrideError) -- it set nothing, and a bench
    is not run without what was asked.
    """
    for name, true in (facts or {}).items():
        given = node.get_parameter(name).value
        if _as_plain(given) != _as_plain(true):
            raise ParameterOverrideError(
                f'parameter {name!r} is read-only and reports what the node uses '
                f'({_as_plain(true)!r}); it cannot be set (got {_as_plain(given)!r})'
            )
    if composed_with is not None:
        unknown = unknown_composed(composed_with, node)
        if unknown:
            raise ParameterOverrideError(
                f'no such parameter: {", ".join(unknown)} (neither '
                f'{composed_with.get_fully_qualified_name()} nor '
                f'{node.get_fully_qualified_name()} declares it; their parameters: '
                'docs/controller.md, "Parameters", and docs/interfaces.md, "Parameters of the '
                'simulator node")'
            )
        return unknown
    unknown = unknown_overrides(node)
    if warn_unknown:
        warn_unknown_overrides(node, unknown)
    return unknown


def unknown_composed(a, b) -> list[str]:
    """The ``-p`` overrides that neither of two nodes composed in one process declares
    (each receives the other's: only what matches neither is a typo)."""
    # every declared parameter ('' matches all: rclpy's public view of node._parameters)
    declared = set(a.get_parameters_by_prefix('')) | set(b.get_parameters_by_prefix(''))
    return sorted((set(unknown_overrides(a)) | set(unknown_overrides(b))) - declared)


def unknown_overrides(node) -> list[str]:
    """The ``-p``/params-file overrides that name no declared parameter of ``node``."""
    # rclpy (7.1) has no public API for the start-up overrides (-p, params files): read
    # from the Node's own table, the one place they are kept
    overrides = node._parameter_overrides
    return sorted(n for n in overrides if not node.has_parameter(n))


def warn_unknown_overrides(node, names: list[str]) -> None:
    """Log once, naming them, that these overrides were ignored (a typo, most likely)."""
    if names:
        node.get_logger().warn(
            f'ignored override(s) of undeclared parameter(s) {", ".join(names)}: no such '
            f'parameter on {node.get_fully_qualified_name()} (typo?)'
        )


def _as_plain(v: object) -> object:
    """Parameter values compared as plain Python (arrays arrive as lists or arrays)."""
    if isinstance(v, (list, tuple)) or hasattr(v, 'tolist'):
        return list(v.tolist() if hasattr(v, 'tolist') else v)
    return v


def run_stepped_node(
    argv: list[str],
    make_node: Callable[[], object],
    config_errors: tuple[type[BaseException], ...],
    prog: str,
    on_exit: Callable[[object], None] | None = None,
) -> int:
    """Create the node with ``make_node()``, run ``node.run(executor)`` until it returns
    or a signal sets ``node.stop_requested``; returns the process exit code.

    The node must provide ``run(executor)``, ``stop_requested``, ``flush()`` and
    ``destroy_node()``; ``on_exit(node)`` runs first at shutdown (a summary log).
    """
    node: Any = None
    executor = None

    def _on_signal(_signum: int) -> None:
        if node is None:
            raise KeyboardInterrupt  # still starting: nothing to stop cleanly yet
        node.stop_requested = True

    session = RosSession(argv, on_signal=_on_signal)
    try:
        node = make_node()
        node.stop_requested = session.stopped
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)
        node.run(executor)
    except (
        *config_errors,
        ParameterOverrideError,
        InvalidParameterValueException,
        InvalidParameterTypeException,
    ) as exc:
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
        session.close()
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


def param_descriptor(
    description: str,
    *,
    read_only: bool = True,
    int_range: tuple[int, int] | None = None,
    float_range: tuple[float, float] | None = None,
    additional: str = '',
    param_type: int = ParameterType.PARAMETER_NOT_SET,
) -> ParameterDescriptor:
    """The one ParameterDescriptor idiom of the nodes: a description (with its unit), read
    only unless said otherwise, the range the node enforces as an rcl range, and any other
    constraint in words (``additional``). ``param_type`` pins the type (e.g. a double that
    an integer override must not change)."""
    d = ParameterDescriptor(
        type=param_type,
        description=description,
        read_only=read_only,
        additional_constraints=additional,
    )
    if int_range is not None:
        d.integer_range = [IntegerRange(from_value=int_range[0], to_value=int_range[1], step=1)]
    if float_range is not None:
        d.floating_point_range = [
            FloatingPointRange(from_value=float_range[0], to_value=float_range[1], step=0.0)
        ]
    return d


class RosSession:
    """The rclpy start/stop idiom of every executable of the workspace.

    ``RosSession(argv)`` initialises rclpy (in ``context``, or the default one) with this
    process's own SIGINT/SIGTERM handlers instead of rclpy's, which would raise
    KeyboardInterrupt anywhere, inside a 5 kHz loop or a bag write included. A signal sets
    ``signum`` (``stopped`` is then True) and calls ``on_signal(signum)`` -- which may raise
    KeyboardInterrupt while nothing is up yet to stop cleanly. ``close()`` (in the
    caller's ``finally``) shuts rclpy down and puts the previous handlers back.
    """

    def __init__(
        self,
        argv: list[str],
        *,
        context: object | None = None,
        on_signal: Callable[[int], None] | None = None,
    ) -> None:
        self.context = context
        self.signum: int | None = None
        self._on_signal = on_signal
        rclpy.init(args=argv, context=context, signal_handler_options=SignalHandlerOptions.NO)
        self._old = {s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)}
        self._old_unraisable = sys.unraisablehook
        sys.unraisablehook = self._unraisable

    def _handle(self, signum: int, _frame: object) -> None:
        self.signum = signum
        if self._on_signal is not None:
            self._on_signal(signum)

    def _unraisable(self, info: Any) -> None:
        # A KeyboardInterrupt raised by on_signal while the main thread runs a ctypes
        # callback (numba's object cache, as it compiles) cannot propagate: Python would
        # print it as a traceback and go on. The signal is already in ``signum``, which the
        # starting code checks once it is up: nothing to print.
        if isinstance(info.exc_value, KeyboardInterrupt) and self.stopped:
            return
        self._old_unraisable(info)

    @property
    def stopped(self) -> bool:
        return self.signum is not None

    def close(self) -> None:
        rclpy.try_shutdown(context=self.context)
        for s, h in self._old.items():
            signal.signal(s, h)
        sys.unraisablehook = self._old_unraisable
