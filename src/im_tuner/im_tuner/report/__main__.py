"""``python -m im_tuner.report``."""

import sys

from .cli import main

sys.exit(main())
