"""A minimal real-time drive node to start from: ``ros2 run im_drive_sim example_drive``.

Copy this file for a real drive. It has two parts:

(a) :class:`Hardware` -- the only code that touches the power stage. Replace its two
    methods: ``write(isq_ref, load_torque)`` applies the current reference (and the load
    machine's torque) for the coming period, ``read()`` samples the sensors and returns a
    :class:`Measurement`; an optional attribute ``command_delay`` (1 or 2, default 1)
    declares over which period a write acts (docs/real-drive.md, "Command delay"); an
    optional ``close()`` runs once at the stop, right after a last ``write(0.0, 0.0)``
    (every way out of a run writes zero first; SIGKILL cannot -- the inverter's own
    communication-loss trip must cover it). Here they are backed by a small simulated
    stand-in plant with constants from the drive parameter file.
(b) :class:`ExampleDrive` -- the ROS side, honouring docs/interfaces.md in real-time mode
    (state every period, commands taken at each period start, joint states, status, the
    isq clamp and the command watchdog), run by drive_sim's real-time loop
    (``drive_io.run_realtime``), or period by period by the composed bench's loop, as
    Python or compiled (``period_words``: ``hardware_period``).

Check a drive built from it with ``ros2 run im_drive_sim check_drive`` (docs/check-drive.md).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, fields
from numbers import Integral
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus

from . import contract, hardware_period as HP, period_kernel as PK, rt
from .cli import check_ros_args, parse_cli, run_cli
from .command_latch import CommandLatch, HeldCommand
from .drive_file import load_config
from .drive_io import DriveNode, run_drive_node
from .drive_sim_parameters import parameter_specs
from .example_drive_main import check_hardware, hardware_factory, parser
from .hardware_abi import HardwareEntry, Measurement
from .pacing import CommandWatchdog
from .params import ConfigError, DriveConfig
from .runtime import (
    param_descriptor,
    parameter_hygiene,
    publish_lossless,
)


class Hardware:
    """Simulated stand-in for the power stage and sensors. Replace ``read``/``write``.

    ``write`` applies a command for the coming period; ``read`` samples the sensors at the
    period start. The stand-in advances its model by one period Ts inside ``read`` (time
    that passes by itself on real hardware). ``command_delay`` comes from the parameter
    file: with 2 the stand-in runs each period on the command written one period earlier,
    as a power stage that latches its reference at the period start.
    """

    #: over which period a write acts (docs/real-drive.md, "Command delay"); None: the
    #: parameter file's ``command_delay`` (a subclass may set 1 or 2 here)
    command_delay: int | None = None

    def __init__(self, config: DriveConfig) -> None:
        m, s = config.machine, config.sensors
        self.ts = config.Ts  # [s]
        self.kt = m.Kt  # [N m/A]
        self.inv_j, self.b = 1.0 / m.J, m.B  # [1/(kg m^2)], [N m s/rad]
        self.isd_ref = m.rated_flux_current  # [A]
        self.pole_pairs = m.pole_pairs
        self.a_i = math.exp(-self.ts * config.control.current_bandwidth)  # current-loop pole
        self.a_w = math.exp(-self.ts / s.speed_filter_tau) if s.speed_filter_tau > 0 else 0.0
        self.counts_per_rad = s.encoder_counts / (2.0 * math.pi)
        if self.command_delay is None:
            self.command_delay = config.command_delay
        self.isq_ref = self.load_ref = 0.0  # the command acting now
        self._next = (0.0, 0.0)  # delay 2: the command written, acting from the next period
        self.isq = self.theta = self.omega = 0.0  # true plant state
        self.count = 0  # encoder count
        self.m = Measurement(isd=self.isd_ref)

    def write(self, isq_ref: float, load_torque: float) -> None:
        """Apply isq* [A] (already clamped) and the load torque [N m] for the next period."""
        if self.command_delay == 2:
            self._next = (isq_ref, load_torque)
        else:
            self.isq_ref, self.load_ref = isq_ref, load_torque

    def elapse(self, periods: int) -> None:
        """Stand-in only (a real plant lives on the wall clock and needs nothing like it):
        ``periods`` periods went by unsampled, the last command held."""
        for _ in range(periods):
            self._integrate()
            self._encoder()  # the inverter's own speed estimate runs every period

    def _integrate(self) -> float:
        """One period of the stand-in plant under the held command; returns the torque."""
        ts = self.ts
        self.isq = self.a_i * self.isq + (1.0 - self.a_i) * self.isq_ref
        torque = self.torque_of(self.isq)
        # Load: positive opposes positive rotation (docs/interfaces.md).
        self.omega += (torque - self.load_ref - self.b * self.omega) * self.inv_j * ts
        self.theta += self.omega * ts
        if self.command_delay == 2:  # the latched command acts from the next period on
            self.isq_ref, self.load_ref = self._next
        return torque

    def _encoder(self) -> None:
        """Sample the encoder: position and the filtered backward-difference speed."""
        m = self.m
        count = math.floor(self.theta * self.counts_per_rad)
        raw = (count - self.count) / (self.counts_per_rad * self.ts)  # backward difference
        self.count = count
        m.theta_meas = count / self.counts_per_rad
        m.omega_meas = self.a_w * m.omega_meas + (1.0 - self.a_w) * raw

    def read(self) -> Measurement:
        """Sample the sensors (the stand-in first integrates the plant over one period)."""
        m = self.m
        load = self.load_ref  # the load torque that acts over this period
        torque = self._integrate()
        self._encoder()
        m.torque, m.isq, m.load_torque = torque, self.isq, load
        rho = self.pole_pairs * m.theta_meas  # field angle of the stand-in (slip neglected)
        c, s = math.cos(rho), math.sin(rho)
        m.i_alpha = c * m.isd - s * m.isq
        m.i_beta = s * m.isd + c * m.isq
        return m

    def torque_of(self, isq: float) -> float:
        """Electromagnetic torque [N m] of a q current [A]."""
        return self.kt * isq

    def close(self) -> None:
        """Optional: called once when the drive stops, right after a last ``write(0.0,
        0.0)``; release the bus, disable the inverter's output. Nothing to do here."""


def hardware_command_delay(hw: object) -> int:
    """A hardware object's declared ``command_delay`` (absent: 1); ConfigError unless 1 or 2."""
    d = getattr(hw, 'command_delay', 1)
    if isinstance(d, bool) or not isinstance(d, int) or d not in contract.COMMAND_DELAYS:
        raise ConfigError(f'{type(hw).__name__}.command_delay must be 1 or 2 (periods), got {d!r}')
    return d


@dataclass
class Counters:
    """Published on drive/status and logged at exit (names as in docs/interfaces.md)."""

    steps: int = 0  #: periods run
    commands: int = 0  #: valid commands received
    fresh: int = 0  #: steps driven by a command answering the latest state
    held: int = 0  #: steps that held an older command
    late: int = 0  #: commands answering an older state than the latest
    stale_ignored: int = 0  #: out-of-order or duplicate commands, ignored
    overruns: int = 0  #: periods that started more than one period late
    missed: int = 0  #: whole periods those late starts skipped (counted held too)
    max_lateness_us: float = 0.0  #: worst period-start lateness [us]
    watchdog_trips: int = 0  #: times commands stopped for more than command_timeout
    watchdog_steps: int = 0  #: steps run at zero current by the watchdog
    backpressure: int = 0  #: publish retries while a reliable reader was full

    def texts(self) -> dict[str, str]:
        """Each counter as published and logged: counts exact (a run passes 10^6 steps in
        200 s), the lateness as ``%g`` [us]."""
        return {
            f.name: str(int(v)) if isinstance(v := getattr(self, f.name), Integral) else f'{v:g}'
            for f in fields(self)
        }


class ExampleDrive(DriveNode):
    """The ROS side (real time only). Hooks for subclasses: ``make_hardware``,
    ``apply_command``, ``fill_state``, ``make_joint_publisher``/``publish_joint_state``,
    ``watchdog`` and the attribute ``period_s``. ``start``/``period``/``take_commands``/
    ``wait_command`` are what a loop runs (``drive_io.run_realtime``, or the composed
    bench: ``drive_io.DriveNode``)."""

    def __init__(
        self,
        node_name: str = 'example_drive',
        *,
        hardware_class: Callable[[Any], Any] | None = None,
        **kwargs,
    ) -> None:
        """``hardware_class``: the class (or factory) whose instance
        (``hardware_class(config)``) talks to the power stage; None = the simulated
        stand-in :class:`Hardware`."""
        self.hardware_class = Hardware if hardware_class is None else hardware_class
        super().__init__(node_name, **kwargs)
        d = self.declare_parameter
        # drive_sim's parameters of the same names (the layouts: read-only facts)
        specs = {name: (default, desc) for name, default, desc in parameter_specs()}
        shared = ['config_file', 'command_timeout', 'realtime_spin_margin']
        shared += ['joint_state_decimation', 'state_fields', 'command_fields']
        p = {name: d(name, *specs[name]).value for name in shared}
        self.config = load_config(p['config_file'] or None)
        self.ts_ns: int = self.config.Ts_ns
        #: wall-clock period of the loop [s] (= Ts; a subclass may change it)
        self.period_s: float = self.config.Ts
        file_max = self.config.machine.isq_max
        self.isq_max: float = d(
            'isq_max',
            file_max,
            param_descriptor(
                'Clamp of isq* [A] (read-only: a limit no parameter call can change); at most the '
                "parameter file's isq_max.",
                float_range=(0.0, file_max),
            ),
        ).value
        self.command_timeout: float = p['command_timeout']
        self.spin_margin: float = p['realtime_spin_margin']
        self.joint_state_decimation: int = p['joint_state_decimation']
        # the layouts report what this node publishes and reads: not settable
        parameter_hygiene(self, self.LAYOUTS)

        self.hw = self.make_hardware()
        #: the labels (applied_step, fresh) of the command written and not yet acting
        #: (delay 2: the power stage's latch); its delay is :attr:`command_delay`
        self.latch = CommandLatch(hardware_command_delay(self.hw))
        #: applied_step of the command that acted over the period that just ended
        self.acting = -1
        self.counters = Counters()
        self.k = 0  # step index of the latest published state
        self.held = HeldCommand()  # zero before the first command
        self.cmd_watchdog = CommandWatchdog(self.command_timeout, self.period_s)
        #: latched by :meth:`safe_stop`: from then on every period writes zero current and
        #: zero load torque, whatever command comes
        self.safe_stopped = False
        self._hw_closed = False
        #: a power stage cannot pause: a late period start means periods that went by with
        #: the old command held (``pacing.Pacer``'s ``wall_clock``)
        self.wall_clock = True

        self.open_topics(node_name)
        self.wire.values[13] = self.command_delay  # declared once, in every state
        self.get_logger().info(
            f'real time, Ts={self.config.Ts * 1e6:.0f} us, isq_max='
            f'{self.isq_max:g} A, command_timeout={self.command_timeout:g} s, '
            f'command_delay={self.command_delay}'
        )

    @property
    def command_delay(self) -> int:
        """The hardware's declared command delay d (its ``command_delay``, default 1): the
        state read right after the write answering state k shows the command written
        d - 1 periods earlier; applied_step and the fresh/held counts say so (the latch
        labels by it: setting it sets the latch's)."""
        return self.latch.delay

    @command_delay.setter
    def command_delay(self, d: int) -> None:
        self.latch.delay = d

    # -- hooks ----------------------------------------------------------------------------
    def make_hardware(self) -> Hardware:
        return self.hardware_class(self.config)

    def apply_command(self, isq_ref: float, load_torque: float) -> None:
        """Clamp and hand the command to the hardware for the coming period (zero current
        and zero load torque once :meth:`safe_stop` latched)."""
        if self.safe_stopped:
            self.hw.write(0.0, 0.0)
            return
        self.hw.write(max(-self.isq_max, min(self.isq_max, isq_ref)), load_torque)

    # -- the safe stop ----------------------------------------------------------------------
    def safe_stop(self) -> None:
        """Zero current and zero load torque, now and in every later period (a latch: a
        command that still comes is not applied). Called on every way out of a run --
        its end, SIGINT/SIGTERM, an exception in the loop, a failed run -- by this node's
        own loop and by the composed bench. Idempotent; the hardware stays open (a loop
        may still run periods, e.g. to serve the tuner's last parameter calls)."""
        self.safe_stopped = True
        self.held.zero()
        if not self._hw_closed:
            try:
                self.hw.write(0.0, 0.0)
            except Exception as exc:  # a fault, or the user's write raising: said, not raised
                self.get_logger().error(f'safe stop: the write of zero raised {exc!r}')

    def close_hardware(self) -> None:
        """The last word to the power stage: zero current and zero load torque, then the
        hardware class's optional ``close()`` (release the bus, disable the inverter).
        Idempotent; after it the hardware is never touched again."""
        if self._hw_closed:
            return
        try:
            self.safe_stop()
        finally:
            self._hw_closed = True
            close = getattr(self.hw, 'close', None)
            if callable(close):
                try:
                    close()
                except Exception as exc:  # (zero was written): said, and the run goes on
                    text = str(exc).strip().splitlines()
                    self.get_logger().error(
                        f'the hardware close() raised {type(exc).__name__}'
                        + (f': {text[0]}' if text else '')
                        + ' (zero current was written before it; the power stage may not '
                        'be released)'
                    )

    def fill_state(self, m: Measurement) -> None:
        """Copy a measurement into the drive/state buffer (a real drive repeats the measured
        position and speed in the 'true' fields 10 and 11)."""
        v = self.wire.values
        v[0] = self.k
        v[1] = self.k * self.ts_ns
        v[2], v[3], v[4] = m.theta_meas, m.omega_meas, m.torque
        v[5], v[6], v[7], v[8] = m.isd, m.isq, m.i_alpha, m.i_beta
        v[9], v[10], v[11] = m.load_torque, m.theta_meas, m.omega_meas
        v[12] = self.acting  # the command applied over the period that just ended
        v[13] = self.command_delay

    @property
    def step_index(self) -> int:
        """The step index of the latest published state."""
        return self.k

    # -- publishing ------------------------------------------------------------------------
    def publish_state(self) -> None:
        # a full reliable reader (the recorder): back-pressure, never drop
        self.counters.backpressure += publish_lossless(self.state_pub, self.wire, self.context)
        if self.k % self.joint_state_decimation == 0:
            self.publish_joint_state()

    def publish_status(self, wall_elapsed: float | None = None) -> None:
        """drive/status: the counters (``wall_elapsed``: no real-time factor for a drive
        that lives on the wall clock)."""
        c = self.counters
        st = DiagnosticStatus(name=f'{self.get_name()}: example drive', hardware_id='example')
        st.level, st.message = DiagnosticStatus.OK, 'ok'
        if c.overruns or c.late or c.stale_ignored:
            st.level, st.message = DiagnosticStatus.WARN, 'late commands / overruns counted'
        if self.cmd_watchdog.tripped:
            st.level, st.message = DiagnosticStatus.ERROR, 'command watchdog: zero current'
        values = {
            'mode': 'realtime',
            'command_delay': str(self.command_delay),
            'step_index': str(self.k),
            **c.texts(),
        }
        self.send_status(st, values)

    # -- the loop ------------------------------------------------------------------------------
    def start(self) -> None:
        """Sample and publish state 0 (zero current is held until the first command)."""
        self.fill_state(self.hw.read())
        self.publish_state()

    def period(self, missed: int = 0) -> None:
        """``DriveNode.period``; nothing once the hardware is closed."""
        if not self._hw_closed:
            super().period(missed)

    def skip(self, missed: int) -> None:
        """A power stage cannot pause: it held the last command over the ``missed``
        periods (a simulated stand-in plant is told: ``elapse``); the step index advances
        by them, so the state published next is the one of the drive's real time
        (``time_ns = k Ts``)."""
        elapse = getattr(self.hw, 'elapse', None)
        if callable(elapse):
            elapse(missed)
        self.acting = self.latch.hold(self.held.applied)  # it held what it was last written
        self.k += missed

    def step(self, isq_ref: float, load_torque: float, acting: int) -> None:
        """Write the command, sample, publish state k+1 (``acting``: its applied_step)."""
        self.acting = acting
        self.apply_command(isq_ref, load_torque)
        self.k += 1
        self.fill_state(self.hw.read())
        self.publish_state()
        self.counters.steps += 1

    # -- the same period compiled (hardware_period; a composed loop: bench.compiled_loop) --
    def hardware_entry(self) -> HardwareEntry | None:
        """The power stage's addresses for a compiled loop (``hardware_abi``: a C library,
        a compiled class); None for a Python hardware class (its periods run as Python)."""
        entry = getattr(self.hw, 'entry', None)
        return entry() if callable(entry) else None

    def period_words(self) -> tuple[Any, Any]:
        """The held command, latch, step index and counters as ``hardware_period``'s
        ``D`` and ``DC``, for a compiled loop to run periods with (then
        :meth:`set_period_words`)."""
        words = {
            'command_delay': self.command_delay,
            'k': self.k,
            'acting': self.acting,
            'joint_state_decimation': self.joint_state_decimation,
            'ts_ns': self.ts_ns,
            'isq_max': self.isq_max,
        }
        return PK.pack_words(
            self.held, self.latch, self.safe_stopped, words, self.counters, HP.WORDS
        )

    def set_period_words(self, D: Any, DC: Any, commands: bool) -> None:
        """Take back what a compiled loop ran; ``commands``: it took one (the watchdog
        is fed)."""
        self.safe_stopped = PK.unpack_words(D, DC, self.held, self.latch, self.counters)
        self.k = int(D[HP.D_K])
        self.acting = int(D[HP.D_ACTING])
        if commands:
            self.cmd_watchdog.command()

    def log_summary(self) -> None:
        self.get_logger().info(
            f'stopped at step {self.k}: '
            + ', '.join(f'{k}={v}' for k, v in self.counters.texts().items())
        )

    def flushed_publishers(self) -> tuple[Any, ...]:
        return (self.state_pub, self.joint_pub, self.status_pub)

    def destroy_node(self) -> None:
        try:
            self.close_hardware()  # never destroyed with a current in the inverter
        finally:
            super().destroy_node()  # (the io node, then this one)


def main(args: list[str] | None = None, node_class: type = ExampleDrive) -> int:
    argv = sys.argv if args is None else args

    def body() -> int:
        if node_class is not ExampleDrive:
            # a drive built on this one (its own main parses its own options): only the
            # ROS arguments are checked here
            check_ros_args(argv)
            return run_drive_node(argv, node_class, 'example_drive')
        cli = parse_cli(parser(), argv)
        opts = rt.RtOptions.from_cli(cli)
        make = hardware_factory(check_hardware(cli.hardware))
        return run_drive_node(argv, lambda: node_class(hardware_class=make), 'example_drive', opts)

    return run_cli('example_drive', body)


if __name__ == '__main__':
    sys.exit(main())
