"""``python -m im_tuner.foxglove``."""

import sys

from .cli import main

sys.exit(main())
