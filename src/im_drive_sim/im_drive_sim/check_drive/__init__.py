"""Drive conformance check: ``ros2 run im_drive_sim check_drive``.

Probes the drive node on the graph (in this node's namespace) against docs/interfaces.md
and prints one line per item -- ``topics``, ``fields``, ``rate``, ``latency``,
``step_response``, ``watchdog`` -- with the measured figures and what was expected, then a
summary; exit code 0 when every item passes, 1 otherwise, 2 when it refuses to run (bad
option, no drive, another node already commanding the drive). What each item checks and
why its thresholds are what they are: docs/check-drive.md.

In modules by job (each module's docstring says which): ``thresholds``, ``judges``,
``response``, ``conditions`` and ``evaluate`` are pure (numpy only); ``probe``,
``procedure`` and ``cli`` talk to the graph. This package's namespace is the union of
their public names (each module's ``__all__``).
"""

from . import (
    cli as _cli,
    conditions as _conditions,
    evaluate as _evaluate,
    judges as _judges,
    probe as _probe,
    procedure as _procedure,
    response as _response,
    thresholds as _thresholds,
)
from .cli import *  # noqa: F403
from .conditions import *  # noqa: F403
from .evaluate import *  # noqa: F403
from .judges import *  # noqa: F403
from .probe import *  # noqa: F403
from .procedure import *  # noqa: F403
from .response import *  # noqa: F403
from .thresholds import *  # noqa: F403

__all__: list[str] = []
__all__ += _cli.__all__
__all__ += _conditions.__all__
__all__ += _evaluate.__all__
__all__ += _judges.__all__
__all__ += _probe.__all__
__all__ += _procedure.__all__
__all__ += _response.__all__
__all__ += _thresholds.__all__
