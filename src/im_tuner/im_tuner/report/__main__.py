"""``python -m im_tuner.report``."""

from im_drive_sim.cli import executable

executable('report', 'im_tuner.report.cli:main')
