"""The run log: what a tuning run writes, as typed objects (pure: no rclpy).

``records``: results.jsonl, one typed record per line; ``files``: run.yaml and
summary.json; ``tally``: what the records add up to; ``ripple``: the standstill-ripple
limit; ``columns``: the report's CSV (not imported here: it needs numpy).  The formats:
docs/tuner.md, "The run directory".
"""

from .files import RunConfig as RunConfig, Summary as Summary
from .records import (
    Evaluation as Evaluation,
    Lost as Lost,
    Measured as Measured,
    Record as Record,
    Reference as Reference,
    Remeasurement as Remeasurement,
    Timing as Timing,
    evaluation_name as evaluation_name,
)
from .tally import (
    MemoryRecord as MemoryRecord,
    replay_plan as replay_plan,
    summarize as summarize,
    tally_all as tally_all,
)
