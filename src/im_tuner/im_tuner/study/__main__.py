"""``python -m im_tuner.study``."""

import sys

from .cli import main

sys.exit(main())
