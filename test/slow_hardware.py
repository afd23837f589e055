"""A hardware class slower than it declares, for the tests of the command-delay probe:
the example drive's stand-in plant, declaring command delay 1 while every write acts a
period later (delay 2) -- an inverter whose latch the class's author forgot."""

from __future__ import annotations

from im_drive_sim.example_drive import Hardware
from im_drive_sim.params import DriveConfig


class SlowerThanDeclared(Hardware):
    command_delay = 1

    def __init__(self, config: DriveConfig) -> None:
        super().__init__(config)
        self._pending = (0.0, 0.0)

    def write(self, isq_ref: float, load_torque: float) -> None:
        super().write(*self._pending)  # last period's command acts now
        self._pending = (isq_ref, load_torque)
