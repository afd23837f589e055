"""Drive conformance check: ``ros2 run im_drive_sim check_drive`` (its items, thresholds
and exit codes: docs/check-drive.md).

In modules by job (each module's docstring says which): ``thresholds``, ``judges``,
``response``, ``conditions`` and ``evaluate`` are pure (numpy only); ``probe``,
``procedure`` and ``cli`` talk to the graph. This package's namespace is the union of
their public names.
"""

from .cli import *  # noqa: F403
from .conditions import *  # noqa: F403
from .evaluate import *  # noqa: F403
from .judges import *  # noqa: F403
from .probe import *  # noqa: F403
from .procedure import *  # noqa: F403
from .response import *  # noqa: F403
from .thresholds import *  # noqa: F403
