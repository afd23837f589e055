"""The run log: what a tuning run writes, as typed objects (pure: no rclpy).

``records``: results.jsonl, one typed record per line; ``files``: run.yaml and
summary.json; ``tally``: what the records add up to; ``ripple``: the standstill-ripple
limit; ``columns``: the report's CSV (not imported here: it needs numpy).  The formats:
docs/tuner.md, "The run directory".
"""

from .files import (
    FILE_VERSION as FILE_VERSION,
    FileError as FileError,
    RunConfig as RunConfig,
    Summary as Summary,
    VersionError as VersionError,
)
from .records import (
    FORMAT_VERSION as FORMAT_VERSION,
    KINDS as KINDS,
    MEASURED as MEASURED,
    RECORD_TYPES as RECORD_TYPES,
    STATUSES as STATUSES,
    Evaluation as Evaluation,
    Lost as Lost,
    Measured as Measured,
    Record as Record,
    RecordError as RecordError,
    Reference as Reference,
    Remeasurement as Remeasurement,
    Timing as Timing,
    check_record as check_record,
    parse_results as parse_results,
)
from .tally import (
    MemoryRecord as MemoryRecord,
    RunRecord as RunRecord,
    TunerState as TunerState,
    brief as brief,
    evaluation as evaluation,
    final_choice as final_choice,
    replay_plan as replay_plan,
    summarize as summarize,
    tally as tally,
    tally_all as tally_all,
)
