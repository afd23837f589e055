"""Open the bench a :class:`.spec.BenchSpec` asks for: the one place that builds every form.

:func:`open_bench` makes the one probe the spec cannot (``auto``/``none``: is a controller
on the graph?) and the graph's refusals (a second simulated drive or controller beside
one), resolves the spec (:meth:`.spec.BenchSpec.resolve`: a resume that may not go on is
refused), lets the run begin (:meth:`.forms.RunHost.begin`: its directory, this session's
bag), and builds the form: :class:`.forms.InProcess` (``inproc``, ``realtime``) or
:class:`.forms.Children` (``processes``, ``realtime-processes``, ``external``). The tuner
and ``sim_bench`` both open their bench here, so their children die with them alike
(``PR_SET_PDEATHSIG``) and a node's refusal is one line (a UsageError).
"""

from __future__ import annotations

import os
from collections.abc import Callable

from rclpy.context import Context
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node

from im_controller.config import ControllerConfigError
from im_controller.controller_node import ControllerError
from im_drive_sim.cli import UsageError
from im_drive_sim.contract import STATE_TOPIC
from im_drive_sim.params import ConfigError
from im_drive_sim.runtime import ParameterOverrideError

from ..benches import IN_PROCESS_BENCHES, SIM_BENCHES
from ..names import controller_topics
from ..tuning import BenchFailure
from .drive_spec import DriveSpecError
from .forms import Bench, Children, Executor, InProcess, RunHost, controller_on_graph
from .spec import BenchSpec

#: [s] the --discovery-timeout a discovery-timeout message suggests for a loaded machine
SLOW_DISCOVERY_HINT_S = 20.0

#: what a node of the in-process bench refuses at start: its -p overrides (ranges, types,
#: the controller's cross-checks such as a move longer than the experiment), the drive
#: file, a user's drive class
NODE_REFUSALS: tuple[type[Exception], ...] = (
    ConfigError,
    ControllerConfigError,
    ControllerError,
    DriveSpecError,
    InvalidParameterTypeException,
    InvalidParameterValueException,
    ParameterOverrideError,
)


def probe(spec: BenchSpec, node: Node, exe: Executor) -> str:
    """The bench mode on this graph: ``auto`` is ``external`` with a controller on it,
    else ``inproc``; ``none`` needs one (BenchFailure). A simulated bench is refused
    beside a controller (``inproc``) or a drive (every simulated mode) already there."""
    mode = spec.requested
    if mode in ('auto', 'none'):
        timeout = spec.probe_timeout()
        found = controller_on_graph(node, exe.spin_until, spec.controller, timeout)
        if mode == 'none' and not found:
            raise BenchFailure(
                f'no controller reachable ({controller_topics(spec.controller)["start"]} '
                f'not on the graph of ROS_DOMAIN_ID {os.environ.get("ROS_DOMAIN_ID", "0")} '
                f'after {timeout:g} s): start the drive host first, on this computer or '
                "the drive's: `ros2 run im_tuner drive_host --drive lib:PATH` (your drive) "
                'or `ros2 run im_tuner drive_host` (the simulated one), '
                'docs/two-computers.md; or use --bench auto; if it is running, '
                'discovery is slow (a loaded machine): give it longer, e.g. '
                f'--discovery-timeout {max(SLOW_DISCOVERY_HINT_S, 3 * timeout):g}'
            )
        mode = 'external' if found else 'inproc'
    elif mode == 'inproc' and controller_on_graph(node, exe.spin_until, spec.controller, 0.5):
        raise BenchFailure(
            f'a controller ({spec.controller}) is already on the graph: '
            'tune it with --bench none, or use another ROS_DOMAIN_ID'
        )
    if mode in SIM_BENCHES and node.count_publishers('/' + STATE_TOPIC) > 0:
        # a drive without a controller: a second (simulated) drive would fight it
        raise BenchFailure(
            'a drive is publishing /drive/state but no controller answers '
            f'({spec.controller}): start `ros2 run im_controller controller` '
            'for it and use --bench auto, or stop that drive'
        )
    return mode


def open_bench(
    spec: BenchSpec,
    host: RunHost,
    *,
    context: Context | None = None,
    node: Node | None = None,
    exe: Executor | None = None,
    command: list[str] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> Bench:
    """The bench ``spec`` asks for, open (see the module docstring).

    ``node``/``exe``: the tuner's node and its executor (the graph is probed through
    them, the controller link spins them); None (``sim_bench``): no probe, the mode as
    asked. ``command``: this process's command line (the bag's metadata).
    ``should_stop()``: a signal asked the run to stop (the real-time loop safe-stops).
    Raises BenchFailure (the graph refuses), UsageError (a resume that may not go on, a
    node's or the recorder's refusal: nothing is started then)."""
    mode = spec.requested if node is None or exe is None else probe(spec, node, exe)
    plan = spec.resolve(mode)
    bag_dir = host.begin(plan)
    if plan.mode not in IN_PROCESS_BENCHES:
        return Children(plan, node, exe, bag_dir=bag_dir, host=host)
    from ..record.metadata import BagError
    from ..record.node import RecorderError

    try:
        return InProcess(
            plan,
            context,
            node,
            exe,
            bag_dir=bag_dir,
            tuner_metadata=host.tuner_metadata(),
            command=list(command or []),
            should_stop=should_stop,
        )
    except (*NODE_REFUSALS, BagError, RecorderError) as exc:
        # (nothing recorded yet: the nodes come first)
        raise UsageError(str(exc).strip().splitlines()[0]) from None
