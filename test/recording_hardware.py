"""A hardware class for the tests of a drive's stop: the example drive's simulated plant,
with every ``write`` recorded where the test can read it after the process ended.

``RECORDING_HW_FILE`` names a file of float64 slots (a memory map: a write costs no
system call, and the page cache keeps it when the process dies):

    [0] writes so far   [1] last isq_ref [A]   [2] last load torque [N m]
    [3] close() calls   [4] writes after close()   [5] largest |isq_ref| written [A]

``RECORDING_HW_RAISE_AFTER=N`` makes ``read`` raise after N samples (an exception in the
drive's loop, as a broken fieldbus would raise).

Used as ``--drive recording_hardware:RecordingHardware`` with this directory on
PYTHONPATH, exactly as docs/real-drive.md tells a user to name a hardware class.
"""

from __future__ import annotations

import os

import numpy as np

from im_drive_sim.example_drive import ExampleDrive, Hardware, Measurement
from im_drive_sim.params import DriveConfig

SLOTS = 6


class RecordingHardware(Hardware):
    def __init__(self, config: DriveConfig) -> None:
        super().__init__(config)
        path = os.environ['RECORDING_HW_FILE']
        self.log = np.memmap(path, dtype=np.float64, mode='w+', shape=(SLOTS,))
        self.log[:] = 0.0
        self.raise_after = int(os.environ.get('RECORDING_HW_RAISE_AFTER', '0'))
        self.reads = 0
        self.closed = False

    def write(self, isq_ref: float, load_torque: float) -> None:
        super().write(isq_ref, load_torque)
        log = self.log
        log[0] += 1.0
        log[1] = isq_ref
        log[2] = load_torque
        if abs(isq_ref) > log[5]:
            log[5] = abs(isq_ref)
        if self.closed:
            log[4] += 1.0

    def read(self) -> Measurement:
        self.reads += 1
        if self.raise_after and self.reads > self.raise_after:
            raise OSError('fieldbus: no answer from the inverter (test)')
        return super().read()

    def close(self) -> None:
        self.closed = True
        self.log[3] += 1.0
        self.log.flush()


def read_log(path: str) -> dict[str, float]:
    """The slots of a recording file, by name (zeros where the file does not reach yet:
    the drive process creates it, then sizes it)."""
    v = np.zeros(SLOTS)
    got = np.fromfile(path, dtype=np.float64, count=SLOTS)
    v[: got.size] = got
    return {
        'writes': float(v[0]),
        'isq_ref': float(v[1]),
        'load_torque': float(v[2]),
        'closes': float(v[3]),
        'writes_after_close': float(v[4]),
        'max_abs_isq': float(v[5]),
    }


class RecordingDrive(ExampleDrive):
    """A whole drive node class (the other form ``--drive`` takes): the example drive's
    ROS side with :class:`RecordingHardware` as its power stage."""

    def make_hardware(self) -> RecordingHardware:
        return RecordingHardware(self.config)
