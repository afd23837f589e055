"""``python -m im_drive_sim.check_drive``."""

import sys

from .cli import main

sys.exit(main())
