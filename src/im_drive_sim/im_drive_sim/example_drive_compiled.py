"""The example drive's side of a compiled loop: :class:`CompiledPeriodHooks`, a mixin of
``example_drive.ExampleDrive`` (which owns the attributes named below) with the methods
the composed bench's loop (``im_tuner.bench.compiled_loop``) runs its periods by, around a
power stage given by address (``hardware_abi``) without the GIL. Pure: no rclpy.
"""

from __future__ import annotations

from typing import Any

from . import hardware_period
from .hardware_abi import HardwareEntry


class CompiledPeriodHooks:
    """The compiled period's hooks (``hardware_period``; the composed bench's loop) of a
    drive node that owns these attributes (``ExampleDrive``'s)."""

    hw: Any  #: the hardware object (``entry()``: its addresses, if compiled)
    joint_decimation: int  #: drive/joint_states every N steps
    ts_ns: int  #: the period [ns]
    isq_max: float  #: the clamp of isq* [A]
    cmd_watchdog: Any  #: ``pacing.CommandWatchdog``
    wire: Any  #: drive/state, pre-serialised (``cdr.Float64ArrayWire``)
    joint: Any  #: drive/joint_states, pre-serialised (``cdr.JointStateWire``)

    def hardware_entry(self) -> HardwareEntry | None:
        """The power stage's addresses for a compiled loop (``hardware_abi``: a C library,
        a compiled class); None for a Python hardware class (its periods run as Python)."""
        entry = getattr(self.hw, 'entry', None)
        return entry() if callable(entry) else None

    def period_words(self) -> tuple[Any, Any]:
        """The held command, latch, step index and counters as ``hardware_period``'s
        ``D`` and ``DC``, for a compiled loop to run periods with (then
        :meth:`set_period_words`)."""
        return hardware_period.pack(
            self,
            {
                'joint_state_decimation': self.joint_decimation,
                'ts_ns': self.ts_ns,
                'isq_max': self.isq_max,
            },
        )

    def set_period_words(self, D: Any, DC: Any, commands: bool) -> None:
        """Take back what a compiled loop ran; ``commands``: it took one (the watchdog
        is fed)."""
        hardware_period.unpack(D, DC, self)
        if commands:
            self.cmd_watchdog.command()

    def period_views(self) -> dict[str, Any]:
        """The preallocated messages a compiled period writes: ``state`` and the
        joint_states fields, and each message's bytes (``*_raw``) for the loop's outbox."""
        j = self.joint
        return {
            'state': self.wire.values,
            'joint_sec': j.sec,
            'joint_nsec': j.nanosec,
            'joint_pos': j.position,
            'joint_vel': j.velocity,
            'joint_eff': j.effort,
            'state_raw': self.wire.raw,
            'joint_raw': j.raw,
        }
