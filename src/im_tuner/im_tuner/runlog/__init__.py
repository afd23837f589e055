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
checks against the record classes here.  The package exports what its modules export
(each module's ``__all__``: one list each, re-exported by name below).
"""

from .files import FILE_VERSION, FileError, RunConfig, Summary, VersionError
from .records import (
    FORMAT_VERSION,
    KINDS,
    MEASURED,
    RECORD_TYPES,
    STATUSES,
    Evaluation,
    Lost,
    Measured,
    Record,
    RecordError,
    Reference,
    Remeasurement,
    Timing,
    check_record,
    parse_results,
)
from .tally import (
    MemoryRecord,
    RunRecord,
    TunerState,
    brief,
    final_choice,
    replay_plan,
    summarize,
    tally,
    tally_all,
)

__all__ = [
    'FILE_VERSION',
    'FORMAT_VERSION',
    'KINDS',
    'MEASURED',
    'RECORD_TYPES',
    'STATUSES',
    'Evaluation',
    'FileError',
    'Lost',
    'Measured',
    'MemoryRecord',
    'Record',
    'RecordError',
    'Reference',
    'Remeasurement',
    'RunConfig',
    'RunRecord',
    'Summary',
    'Timing',
    'TunerState',
    'VersionError',
    'brief',
    'check_record',
    'final_choice',
    'parse_results',
    'replay_plan',
    'summarize',
    'tally',
    'tally_all',
]
