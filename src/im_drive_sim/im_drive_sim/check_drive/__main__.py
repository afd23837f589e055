"""``python -m im_drive_sim.check_drive``."""

from im_drive_sim.cli import executable

executable('check_drive', 'im_drive_sim.check_drive.cli:main')
