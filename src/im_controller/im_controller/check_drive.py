"""Moved: check_drive is a tool of the drive contract, now ``im_drive_sim.check_drive``
(``ros2 run im_drive_sim check_drive``). This name keeps working for one release."""

from im_drive_sim.check_drive import *  # noqa: F403
from im_drive_sim.check_drive import __all__ as __all__
from im_drive_sim.check_drive import main

if __name__ == '__main__':
    import sys

    sys.exit(main())
