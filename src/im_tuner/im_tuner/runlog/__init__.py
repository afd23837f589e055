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
  :class:`MemoryRecord`);
* ``ripple`` -- the standstill-ripple limit (its default, bound, told loss and summary).

The run directory itself (atomic writes, the lock, the bags) is ``im_tuner.rundir``; the
file formats are described in docs/tuner.md ("The run directory"), which a unit test
checks against the record classes here.  The package re-exports its modules' public
names below.
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
    final_choice as final_choice,
    replay_plan as replay_plan,
    summarize as summarize,
    tally as tally,
    tally_all as tally_all,
)
