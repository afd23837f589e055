"""ROS 2 node of the drive simulator: ``ros2 run im_drive_sim drive_sim``.

A thin node around :class:`im_drive_sim.sim.DriveSim` that speaks the drive interface of
``docs/interfaces.md``: lock-step (default; one period per command answering the state,
bit-for-bit deterministic) or real time (a hand-paced 5 kHz loop holding the last
command, with the command watchdog). The command path never goes through an executor
(``drive_io.DriveNode.wait_command``); the visible node (parameters, diagnostics) is spun between
steps, every ``service_period_steps`` steps and whenever the loop is idle.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from rosgraph_msgs.msg import Clock

from . import contract, period_kernel, rt
from .cdr import ClockWire
from .cli import parse_cli, run_cli
from .command_latch import CommandLatch, HeldCommand
from .contract import NS_PER_S
from .drive_file import load_config
from .drive_io import DriveNode, run_drive_node
from .drive_sim_counters import Counters, counter_values
from .drive_sim_main import parser
from .drive_sim_parameters import declare_initial_position, declare_parameters
from .pacing import CommandWatchdog
from .qos import RECORDED_QOS
from .runtime import (
    parameter_hygiene,
    publish_lossless,
    start_overrides,
)
from .sim import DriveSim

F_APPLIED = contract.STATE_INDEX['applied_step']


class DriveSimNode(DriveNode):
    """The drive simulator node (module docstring; its parameters: drive_sim_parameters)."""

    def __init__(
        self,
        *,
        node_name: str = 'drive_sim',
        context=None,
        parameter_overrides: list | None = None,
        warn_unknown: bool = True,
    ) -> None:
        super().__init__(node_name, context=context, parameter_overrides=parameter_overrides)
        p = declare_parameters(self)
        self.mode: str = p['mode']
        overrides: dict = {'model': p['model']} if p['model'] else {}
        if p['command_delay']:
            overrides['command_delay'] = p['command_delay']
        self.config = load_config(p['config_file'] or None, overrides=overrides)
        p['initial_position'] = declare_initial_position(self, self.config)
        self.sim = DriveSim(self.config, seed=p['seed'] if p['seed'] >= 0 else None)
        self.sim.reset(theta=p['initial_position'], omega=0.0, fluxed=True)
        self.ts_ns: int = self.config.Ts_ns
        self.clock_decimation: int = p['clock_decimation']
        self.joint_state_decimation: int = p['joint_state_decimation']
        self.max_steps: int = p['max_steps']
        self.service_period_steps: int = p['service_period_steps']
        self.republish_period: float = p['republish_period']
        self.realtime_wait_for_controller: bool = p['realtime_wait_for_controller']
        self.spin_margin: float = p['realtime_spin_margin']
        self.period_s: float = self.config.Ts  #: the real-time loop's period [s]
        self.command_timeout: float = p['command_timeout']
        #: a drive that cannot pause (``pacing.Pacer``'s ``wall_clock``): real time only
        self.wall_clock: bool = bool(p['hardware_like']) and self.mode == 'realtime'
        self.stall_step: int = p['test_stall_step']
        self.stall_s: float = p['test_stall_duration']
        self.counters = Counters()
        self._t_made = time.perf_counter()

        self.open_topics(node_name)
        self.clock_pub = self.create_publisher(Clock, '/clock', RECORDED_QOS)

        # the model writes straight into drive/state's CDR buffer (``wire``, cdr.py)
        self._state = self.wire.values
        self._clock_wire = ClockWire()  # pre-serialised: patched in place, no conversion
        #: the held command (zero before the first one) and the latch of a drive with
        #: command delay 2 (the command that acts over the next period)
        self.held = HeldCommand()
        self.latch = CommandLatch(self.config.command_delay)
        self.cmd_watchdog = CommandWatchdog(self.command_timeout, self.config.Ts)
        #: latched by :meth:`safe_stop`: zero current and no load from then on
        self.safe_stopped = False
        # Compiled (or loaded from numba's cache) now, not in the first period: on a cold
        # cache (a fresh install) that would be seconds with no state, and the
        # controller's drive-state watchdog aborts the first experiment.
        self.warm_up()

        # The layouts are facts of this node: an override may not advertise another one.
        parameter_hygiene(self, self.LAYOUTS, warn_unknown=warn_unknown)
        # logged at start(): a process composing more nodes may still refuse to start
        self._start_text = (
            f'mode={self.mode} model={self.config.model} '
            f'Ts={self.config.Ts * 1e6:.0f} us command_delay={self.config.command_delay} '
            f'config={p["config_file"] or "(packaged default)"} seed={p["seed"]}'
        )

    # -- publishing --------------------------------------------------------------------
    def publish_state(self) -> None:
        """Publish the current state (and the decimated /clock, joint_states)."""
        k = self.sim.step_index
        self.counters.backpressure += publish_lossless(self.state_pub, self.wire, self.context)
        if k % self.clock_decimation == 0:
            c = self._clock_wire
            c.sec[0], c.nanosec[0] = divmod(k * self.ts_ns, NS_PER_S)
            self.counters.backpressure += publish_lossless(self.clock_pub, c, self.context)
        if k % self.joint_state_decimation == 0:
            self.publish_joint_state()

    def publish_status(self, wall_elapsed: float | None = None) -> None:
        """drive/status: mode, sim time, real-time factor over ``wall_elapsed`` [s] (None:
        since the node was made) and the counters."""
        if wall_elapsed is None:
            wall_elapsed = time.perf_counter() - self._t_made
        c = self.counters
        sim_s = self.sim.step_index * self.config.Ts
        st = DiagnosticStatus(
            name=f'{self.get_name()}: drive simulator',
            hardware_id=f'im_drive_sim/{self.config.model}',
        )
        problems = c.overruns + c.late + c.held if self.mode == 'realtime' else c.stale_ignored
        st.level = DiagnosticStatus.OK if problems == 0 else DiagnosticStatus.WARN
        st.message = 'ok' if problems == 0 else 'late commands / overruns counted'
        if self.cmd_watchdog.tripped:
            st.level = DiagnosticStatus.ERROR
            st.message = (
                f'command watchdog: no command for more than '
                f'{self.command_timeout:g} s, zero current'
            )
        values = {
            'mode': self.mode,
            'model': self.config.model,
            'command_delay': str(self.config.command_delay),
            'step_index': str(self.sim.step_index),
            'sim_time_s': f'{sim_s:.6f}',
            'real_time_factor': f'{sim_s / wall_elapsed:.3f}' if wall_elapsed > 0 else 'nan',
            **counter_values(c),
        }
        self.send_status(st, values)

    # -- the command path ------------------------------------------------------------------
    def drop_latched(self) -> None:
        """Zero current and no load at once (a safe stop, the watchdog): no latched command
        runs after it."""
        self.sim.clear_command()
        self.latch.drop()

    def step(self, isq_ref: float, load_torque: float, applied: int) -> None:
        """Advance the model one period with this command and publish the new state;
        ``applied``: the ``answers_step`` of the command that acted over the period (-1:
        none; the latch's), the new state's ``applied_step``."""
        self.sim.step_into(isq_ref, load_torque, self._state)
        self._state[F_APPLIED] = applied
        self.counters.steps += 1
        self.publish_state()

    # -- loops -----------------------------------------------------------------------
    def start(self) -> None:
        """Publish the initial state (step 0, or wherever the model was reset to)."""
        if self._start_text:
            self.get_logger().info(self._start_text)
            self._start_text = ''
        self.sim.read_into(self._state)
        self.publish_state()

    def lockstep_poll(self, timeout_ns: int) -> bool:
        """Wait up to ``timeout_ns`` for the command answering the current state.

        Steps once and publishes the new state when it comes; returns whether it stepped.
        Commands answering another step are dropped and counted (``stale_ignored``).
        Usable by an in-process bench that interleaves the drive with its peers.
        """
        cmd = self.next_command()  # in one process the answer is usually there already
        if cmd is None and self.wait_command(timeout_ns / NS_PER_S):
            cmd = self.next_command()
        while cmd is not None:
            answers, isq, load = cmd
            if answers < 0 or answers == self.sim.step_index:
                self.step(isq, load, self.latch.latch(answers, True)[0])
                return True
            self.counters.stale_ignored += 1  # a duplicate answer to a re-sent state
            cmd = self.next_command()
        return False

    # -- one real-time period (the composed bench runs these; drive_io.DriveNode) -------
    def period(self, missed: int = 0) -> None:
        """``DriveNode.period``, then the test hook's stall (:meth:`stall_due`)."""
        super().period(missed)
        self.stall_due()

    def skip(self, missed: int) -> None:
        """Hardware-like mode: the model runs the ``missed`` periods first with the command
        it held (unpublished: a late loop sampled nothing); periods as any other, the first
        takes the command."""
        held, state = self.held, self._state
        acting = held.applied
        for _ in range(missed):
            acting = self.latch.latch(held.applied, held.fresh)[0]
            held.fresh = False
            self.sim.step_into(held.isq_ref, held.load, state)
        state[F_APPLIED] = acting

    # -- the same period compiled (period_kernel; a composed loop: bench.compiled_loop) --
    def period_words(self) -> tuple[np.ndarray, np.ndarray]:
        """The held command, its latch and the counters as ``period_kernel``'s ``D`` and
        ``DC`` arrays, for a compiled loop to run periods with (then
        :meth:`set_period_words`)."""
        constants = {
            'command_delay': self.config.command_delay,
            'wall_clock': self.wall_clock,
            'clock_decimation': self.clock_decimation,
            'joint_state_decimation': self.joint_state_decimation,
            'ts_ns': self.ts_ns,
        }
        return period_kernel.pack_words(
            self.held, self.latch, self.safe_stopped, constants, self.counters
        )

    def set_period_words(self, D: np.ndarray, DC: np.ndarray, commands: bool) -> None:
        """Take back what a compiled loop ran (:meth:`period_words`); ``commands``: it
        took one (the watchdog is fed)."""
        self.safe_stopped = period_kernel.unpack_words(D, DC, self.held, self.latch, self.counters)
        if commands:
            self.cmd_watchdog.command()

    def period_views(self) -> dict[str, np.ndarray]:
        """``DriveNode.period_views`` and /clock's fields and bytes."""
        c = self._clock_wire
        clock = {'clock_sec': c.sec, 'clock_nsec': c.nanosec, 'clock_raw': c.raw}
        return {**super().period_views(), **clock}

    def stall_due(self) -> bool:
        """The test hook (``test_stall_step``): the loop stalls once, here -- in the first
        period at or past the step (a drive that cannot pause may skip the step itself)."""
        if 0 <= self.stall_step <= self.sim.step_index:
            self.stall_step = -1
            time.sleep(self.stall_s)
            return True
        return False

    def warm_up(self) -> None:
        """Compile the model's kernels now, not in the first real-time period."""
        self.sim.warm_up(self._state)

    def safe_stop(self) -> None:
        """Zero current and no load from the next period on, whatever command comes (a
        latch: the stop of a real-time run; ``drive_io.DriveNode``)."""
        self.safe_stopped = True
        self.held.zero()
        self.drop_latched()

    def close_hardware(self) -> None:
        """The simulated drive has no power stage to release: the safe stop only."""
        self.safe_stop()

    @property
    def step_index(self) -> int:
        """The step index of the latest published state."""
        return self.sim.step_index

    def log_summary(self) -> None:
        c = self.counters
        self.get_logger().info(
            f'stopped at step {self.sim.step_index} '
            f'(sim time {self.sim.step_index * self.config.Ts:.4f} s): '
            + ', '.join(f'{k}={v}' for k, v in counter_values(c).items())
        )

    def flushed_publishers(self) -> tuple[Any, ...]:
        return (self.state_pub, self.clock_pub, self.joint_pub, self.status_pub)


def main(args: list[str] | None = None) -> int:
    argv = sys.argv if args is None else args

    def body() -> int:
        cli = parse_cli(parser(), argv)
        overrides = start_overrides(
            (
                ('mode', cli.mode),
                ('config_file', cli.drive_config and str(cli.drive_config)),
                ('model', cli.model),
                ('seed', cli.seed),
                ('max_steps', cli.max_steps),
            )
        )
        return run_drive_node(
            argv,
            lambda: DriveSimNode(parameter_overrides=overrides),
            'drive_sim',
            rt.RtOptions.from_cli(cli),
        )

    return run_cli('drive_sim', body)


if __name__ == '__main__':
    sys.exit(main())
