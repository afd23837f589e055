"""The run log: what a tuning run writes, as typed objects (pure: no rclpy).

* ``records`` -- results.jsonl: one record per line (:class:`Evaluation`,
  :class:`Reference`, :class:`Remeasurement`, :class:`Timing`, :class:`Lost`), each with
  its format version and exact JSON (``to_json`` / ``Record.from_json``); the check of a
  line (:func:`check_record`);
* ``columns`` -- the report's CSV export of the records (``CSV_COLUMNS``: not imported
  here, it needs numpy, which the readers of the files do not);
* ``files`` -- run.yaml (:class:`RunConfig`) and summary.json (:class:`Summary`);
* ``tally`` -- what the records add up to (:class:`TunerState`, :func:`tally`,
  :func:`final_choice`, :func:`summarize`) and where they go (:class:`RunRecord`,
  :class:`MemoryRecord`).

The run directory itself (atomic writes, the lock, the bags) is ``im_tuner.rundir``; the
file formats are described in docs/tuner.md ("The run directory"), which a unit test
checks against the record classes here.  The package exports what its modules export
(each module's ``__all__``: one list each, re-exported by name below).
"""

from .files import (
    FILE_VERSION as FILE_VERSION,
)
from .files import (
    FileError as FileError,
)
from .files import (
    RunConfig as RunConfig,
)
from .files import (
    Summary as Summary,
)
from .files import (
    VersionError as VersionError,
)
from .records import (
    FORMAT_VERSION as FORMAT_VERSION,
)
from .records import (
    KINDS as KINDS,
)
from .records import (
    MEASURED as MEASURED,
)
from .records import (
    RECORD_TYPES as RECORD_TYPES,
)
from .records import (
    STATUSES as STATUSES,
)
from .records import (
    Evaluation as Evaluation,
)
from .records import (
    Lost as Lost,
)
from .records import (
    Measured as Measured,
)
from .records import (
    Record as Record,
)
from .records import (
    RecordError as RecordError,
)
from .records import (
    Reference as Reference,
)
from .records import (
    Remeasurement as Remeasurement,
)
from .records import (
    Timing as Timing,
)
from .records import (
    check_record as check_record,
)
from .records import (
    parse_results as parse_results,
)
from .tally import (
    MemoryRecord as MemoryRecord,
)
from .tally import (
    RunRecord as RunRecord,
)
from .tally import (
    TunerState as TunerState,
)
from .tally import (
    brief as brief,
)
from .tally import (
    final_choice as final_choice,
)
from .tally import (
    replay_plan as replay_plan,
)
from .tally import (
    summarize as summarize,
)
from .tally import (
    tally as tally,
)
from .tally import (
    tally_all as tally_all,
)
