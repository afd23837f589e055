"""What the ``drive_sim`` loop counts, and how the counts are written out.

:class:`Counters` (names: ``contract.STATUS_COUNTERS``) is published on ``drive/status``
and logged at shutdown; :func:`counter_values` is the one text form of both. Pure: no
rclpy, no numba.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Counters:
    """What the loop counts (module docstring)."""

    steps: int = 0  #: model steps taken since start
    commands: int = 0  #: commands received
    fresh: int = 0  #: real time: steps driven by a command answering the latest state
    held: int = 0  #: real time: steps that held the previous command
    late: int = 0  #: commands answering an older state than the latest one
    #: commands ignored: lock-step, answering another step; real time, a duplicate or
    #: out of order (answering the same or an older state than the held command)
    stale_ignored: int = 0
    overruns: int = 0  #: real time: periods that started later than one period
    #: real time, hardware-like: whole periods those late starts skipped, run by the model
    #: with the held command (counted held too)
    missed: int = 0
    republished: int = 0  #: lock-step: state re-sent while waiting for a command
    max_lateness_us: float = 0.0  #: real time: worst start-of-period lateness
    backpressure: int = 0  #: publish retries while a reliable reader (recorder) was full
    watchdog_trips: int = 0  #: real time: times commands stopped for > command_timeout
    watchdog_steps: int = 0  #: real time: steps run at zero current by the watchdog


def counter_values(c: Counters) -> dict[str, str]:
    """The counters as text, in declaration order: a count as an integer, a time [us]
    with one decimal."""
    return {k: (f'{v:.1f}' if isinstance(v, float) else str(v)) for k, v in vars(c).items()}
