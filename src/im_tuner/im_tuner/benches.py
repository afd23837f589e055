"""The tuner's bench modes and which of them simulate the drive (pure: no rclpy).

The one copy of ``--bench``'s values (``tuner_args`` imports them from here); pure, so
that the report and the tuner's summary can tell a simulated drive from a real one
without importing the tuner's command line.
"""

from __future__ import annotations

__all__ = ['BENCHES', 'IN_PROCESS_BENCHES', 'LOCKSTEP_BENCHES', 'SIM_BENCHES', 'is_simulated']

#: every ``--bench`` value (``none``: an external bench, the drive is not ours)
BENCHES = ('auto', 'inproc', 'processes', 'realtime', 'realtime-processes', 'none')
#: bench modes that run the simulator (or, with ``--drive``, a drive class) themselves
SIM_BENCHES = ('inproc', 'processes', 'realtime', 'realtime-processes')
#: benches that run the drive and the controller in the tuner's process
IN_PROCESS_BENCHES = ('inproc', 'realtime')
#: simulated benches that repeat a plant history bit for bit (a resumed run replays it)
LOCKSTEP_BENCHES = ('inproc', 'processes')


def is_simulated(bench: str | None, drive: str | None) -> bool:
    """A simulated bench: a simulated bench mode with the simulator or the example's
    stand-in (``drive`` ``sim`` or ``example``; None: ``sim``, the default). ``bench``
    ``none`` (an external bench) or a hardware class given with ``--drive`` is a real
    drive, whose experiments run on its own clock."""
    return bench in SIM_BENCHES and (drive or 'sim') in ('sim', 'example')
