"""``python -m im_tuner.study``."""

from im_drive_sim.cli import executable

executable('study', 'im_tuner.study.cli:main')
