"""im_tuner. Importing im_drive_sim first sets the numeric baseline before numpy is
imported (im_drive_sim.numeric: the same bits on every x86-64 CPU)."""

import im_drive_sim  # noqa: F401

__version__ = '0.1.0'
