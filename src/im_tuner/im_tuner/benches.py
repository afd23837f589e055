"""The tuner's bench modes, its drives by name, and which of them simulate the drive
(pure: no rclpy).

The one copy of ``--bench``'s values and ``--drive``'s names and help (``tuner_args``
and ``bench.drive_spec`` take them from here); pure, so that the report and the tuner's
summary can tell a simulated drive from a real one without importing the tuner's command
line.
"""

from __future__ import annotations

from dataclasses import dataclass

#: every ``--bench`` value (``none``: an external bench, the drive is not ours)
BENCHES = ('auto', 'inproc', 'processes', 'realtime', 'realtime-processes', 'none')
#: bench modes that run the simulator (or, with ``--drive``, a drive class) themselves
SIM_BENCHES = ('inproc', 'processes', 'realtime', 'realtime-processes')
#: benches that run the drive and the controller in the tuner's process
IN_PROCESS_BENCHES = ('inproc', 'realtime')
#: simulated benches that repeat a plant history bit for bit (a resumed run replays it)
LOCKSTEP_BENCHES = ('inproc', 'processes')
#: [s] --discovery-timeout's default per bench mode: auto simulates when it finds no
#: controller (short: the default run); none has nothing else to do (it waits only until
#: the controller is found)
DISCOVERY_TIMEOUT = {'auto': 2.0, 'none': 20.0}


@dataclass(frozen=True)
class NamedDrive:
    """A drive ``--drive`` takes by name: ``says`` what it is (the help, the refusals);
    ``simulated``: its plant is simulated (its runs repeat, a safety fault is reset and
    the run goes on: :func:`is_simulated`); ``make``: ``module:function`` that builds its
    node in real time, ``function(context, overrides)`` (``bench.drive_spec.make_drive``)."""

    says: str
    simulated: bool
    make: str


#: Drives by name, in the order the help lists them (the first is the default); anything
#: else is ``lib:PATH`` or ``package.module:Class`` (``bench.drive_spec``)
NAMED_DRIVES: dict[str, NamedDrive] = {
    'sim': NamedDrive('the simulator', True, 'im_tuner.bench.drive_spec:sim_drive'),
    'example': NamedDrive(
        "the example drive's stand-in hardware", True, 'im_tuner.bench.drive_spec:example_drive'
    ),
}


def is_simulated(bench: str | None, drive: str | None) -> bool:
    """A simulated bench: a simulated bench mode with a named drive whose plant is
    simulated (``drive`` None: the default, the simulator). ``bench`` ``none`` (an
    external bench) or a drive of the user's given with ``--drive`` is a real drive,
    whose experiments run on its own clock."""
    named = NAMED_DRIVES.get(drive or next(iter(NAMED_DRIVES)))
    return bench in SIM_BENCHES and named is not None and named.simulated


def drive_help() -> str:
    """``--drive``'s help: the named drives, then the forms of a user's drive."""
    named = ', '.join(
        f"'{k}' ({d.says}{', default' if i == 0 else ''})"
        for i, (k, d) in enumerate(NAMED_DRIVES.items())
    )
    return (
        f'the drive in the loop: {named}, lib:PATH (a C library, '
        'share/im_drive_sim/include/im_drive.h) or package.module:Class (your hardware class, '
        'as example_drive.Hardware, or your drive node class; docs/real-drive.md)'
    )
