"""results.jsonl: one typed record per line (:data:`RECORD_TYPES`; docs/tuner.md, "The
run directory", lists their fields), and the exact JSON of each.

A line without ``version`` is format 1 (the field is written only from format 2 on).
``Record.from_json`` checks a line (:func:`check_record`) and ``to_json`` writes it back
byte for byte: the fields in the tuner's order, floats as ``repr``, fields this format
does not know kept in ``extra`` and written after the known ones; a field a line does not
carry reads as None.  Pure.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

#: The results.jsonl format this im_tuner writes (and the newest it reads).
FORMAT_VERSION = 1

KINDS = ('reference', 'eval', 'remeasure')
STATUSES = ('ok', 'aborted', 'lost', 'timing')
#: Record statuses that carry a loss (told to the optimiser); 'lost' and 'timing' do not.
MEASURED = ('ok', 'aborted')

#: The fields of a line in the order the tuner writes them (``version`` and
#: ``extra`` apart: the first is written only when not 1, the second after these).
LINE_ORDER = (
    'kind',
    'eval',
    'attempt',
    'u',
    'gains',
    'time',
    'session',
    'status',
    'loss',
    'terms',
    'aborted',
    'reason',
    'fault',
    'experiment_id',
    'direction',
    'steps',
    'trip_step',
    't_start_ns',
    't_end_ns',
    'sim_s',
    'wall_s',
    'off_timing_loss',
    'periods',
    'gains_step',
    'ripple',
    'motion',
    'best_loss',
)
#: Fields written only when they have a value (the tuner never writes them as null; a
#: line without them reads back as it was).
_WHEN_SET = (
    'attempt',
    'time',
    'session',
    'reason',
    'fault',
    'sim_s',
    'wall_s',
    'periods',
    'gains_step',
    'ripple',
    'motion',
)

#: The keys of a record's ``ripple``: the standstill ripple of isq* [A] (rms about its
#: mean, peak-to-peak) after the move and after the load step (im_controller LossResult).
RIPPLE_KEYS = ('rms_after_move', 'pp_after_move', 'rms_after_load', 'pp_after_load')


def evaluation_name(index: int) -> str:
    """An evaluation as printed for the person at the bench: ``evaluation N`` counts from 1,
    where a record's ``eval`` index counts from 0."""
    return f'evaluation {index + 1}'


def ripple_dict(ripple: tuple[float, ...]) -> dict[str, float | None] | None:
    """A measurement's ripple as a record's (None where a window had no sample; None in
    all: not written)."""
    if len(ripple) != len(RIPPLE_KEYS):
        return None
    out = {
        k: (float(v) if math.isfinite(v) else None)
        for k, v in zip(RIPPLE_KEYS, ripple, strict=True)
    }
    return out if any(v is not None for v in out.values()) else None


class RecordError(ValueError):
    """A results.jsonl line that is not a record of this format; the message says why."""


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _integer(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def check_record(rec: dict[str, Any]) -> str | None:
    """What is wrong with one results.jsonl record (None: nothing) -- the fields that the
    tuner's resume, the summary and the report read."""
    version = rec.get('version', 1)
    if not _integer(version) or not 1 <= version <= FORMAT_VERSION:
        return (
            f'record format version {version!r}: this im_tuner reads versions 1 to '
            f'{FORMAT_VERSION} (a newer im_tuner wrote it?)'
        )
    kind, status = rec.get('kind'), rec.get('status')
    if kind not in KINDS:
        return f'record kind {kind!r} is not one of {", ".join(KINDS)}'
    if status not in STATUSES:
        return f'record status {status!r} is not one of {", ".join(STATUSES)}'
    if not _integer(rec.get('eval')):
        return "record without an integer 'eval'"
    if not isinstance(rec.get('gains'), dict) or not all(_number(v) for v in rec['gains'].values()):
        return "record without 'gains' (name: value)"
    if (
        kind == 'eval'
        and status in MEASURED
        and not (isinstance(rec.get('u'), list) and all(_number(x) for x in rec['u']))
    ):
        return "evaluation record without 'u' (a list of numbers)"
    periods = rec.get('periods')
    if periods is not None and not (
        isinstance(periods, dict)
        and all(_integer(periods.get(k)) for k in ('fresh', 'held', 'late'))
    ):
        return "record with 'periods' that are not {fresh, held, late} (integers)"
    ripple = rec.get('ripple')
    if ripple is not None and not (
        isinstance(ripple, dict)
        and set(ripple) == set(RIPPLE_KEYS)
        and all(v is None or _number(v) for v in ripple.values())
    ):
        return f"record with a 'ripple' that is not {{{', '.join(RIPPLE_KEYS)}}} (A or null)"
    motion = rec.get('motion')
    if motion is not None and not (isinstance(motion, list) and all(_number(x) for x in motion)):
        return "record with a 'motion' that is not a list of numbers"
    if status == 'lost':
        return None
    if status == 'timing':
        if not _number(rec.get('off_timing_loss')):
            return "timing record without 'off_timing_loss' (a number)"
        return None
    if not _number(rec.get('loss')):
        return "record without 'loss' (a number)"
    if not (isinstance(rec.get('terms'), list) and all(_number(x) for x in rec['terms'])):
        return "record without 'terms' (a list of numbers)"
    if not isinstance(rec.get('aborted'), bool):
        return "record without 'aborted' (true/false)"
    for key in ('sim_s', 'wall_s'):
        if key in rec and not _number(rec[key]):
            return f'record with a non-numeric {key!r}'
    for key in ('experiment_id', 'steps', 't_start_ns', 't_end_ns'):
        if rec.get(key) is not None and not isinstance(rec[key], int):
            return f'record with a non-integer {key!r}'
    return None


@dataclass(frozen=True, kw_only=True)
class Record:
    """The fields every results.jsonl line has (SI units, sim time in ns; None: the line
    has no value, e.g. a lost attempt's ``steps``)."""

    STATUSES: ClassVar[tuple[str, ...]] = STATUSES  #: the statuses of this record kind

    kind: str  #: 'reference', 'eval' or 'remeasure'
    eval: int  #: evaluation index (0-based); -1 the reference; re-measured evaluation's
    status: str  #: 'ok', 'aborted', 'lost' or 'timing'
    gains: dict[str, float]  #: the gains set on the controller, by name
    attempt: int | None = None  #: 1, or more after lost / off-timing attempts
    u: list[float] | None = None  #: normalised candidate in [0, 1]^5 (evaluations)
    time: str | None = None  #: UTC wall-clock time of the record (ISO 8601)
    session: int | None = None  #: the tuner session that measured it (None: not written)
    loss: float | None = None  #: the loss (penalised if aborted); None: not measured
    terms: list[float] | None = None  #: its three unpenalised terms
    aborted: bool | None = None  #: supervisor or safety stop
    reason: str | None = None  #: why it stopped / was lost / was off timing ('' completed)
    fault: bool | None = None  #: a safety fault (the controller went to FAULT)
    experiment_id: int | None = None  #: the controller's experiment id (None: not started)
    direction: int | None = None  #: +1 / -1
    steps: int | None = None  #: drive periods run
    trip_step: int | None = None  #: local step that stopped it, -1 none
    t_start_ns: int | None = None  #: sim time of the first step's state [ns]
    t_end_ns: int | None = None  #: sim time at the end of the last step [ns]
    sim_s: float | None = None  #: its length [s] (0 for a lost one)
    wall_s: float | None = None  #: set gains -> loss received [s]
    periods: dict[str, int] | None = None  #: {fresh, held, late} drive periods
    gains_step: int | None = None  #: drive step from which its gains acted
    #: standstill ripple of isq* [A] (``RIPPLE_KEYS``; None: not measured)
    ripple: dict[str, float | None] | None = None
    motion: list[float] | None = None  #: the motion sums (im_tuner.identify; None: none)
    version: int = FORMAT_VERSION  #: the line's format version (absent in a line: 1)
    extra: dict[str, Any] = field(default_factory=dict)  #: fields this format does not know

    def to_dict(self) -> dict[str, Any]:
        """The line as a dict (the fields in the order the tuner writes them)."""
        own = {f.name for f in dataclasses.fields(self)}
        keys = [
            k for k in LINE_ORDER if k in own and not (k in _WHEN_SET and getattr(self, k) is None)
        ]
        if self.version != 1:
            keys.insert(0, 'version')
        return {k: getattr(self, k) for k in keys} | self.extra

    def to_json(self) -> str:
        """The line, without its newline (floats round-trip exactly; no NaN/inf)."""
        return json.dumps(self.to_dict(), allow_nan=False, separators=(',', ':'))

    @staticmethod
    def from_dict(rec: dict[str, Any]) -> Record:
        """The record of a parsed line; :class:`RecordError` if it is not one."""
        problem = check_record(rec)
        if problem:
            raise RecordError(problem)
        if rec['status'] == 'lost':
            cls: type[Record] = Lost
        elif rec['status'] == 'timing':
            cls = Timing
        else:
            cls = _MEASURED_KINDS[rec['kind']]
        names = {f.name for f in dataclasses.fields(cls)} - {'extra'}
        known = {k: v for k, v in rec.items() if k in names}
        extra = {k: v for k, v in rec.items() if k not in names}
        return cls(**known, extra=extra)

    @staticmethod
    def from_json(line: str | bytes) -> Record:
        """The record of one results.jsonl line; :class:`RecordError` if it is not one."""
        try:
            rec = json.loads(line)
        except ValueError:
            rec = None
        if not isinstance(rec, dict):
            raise RecordError('is not a JSON record')
        return Record.from_dict(rec)


@dataclass(frozen=True, kw_only=True)
class Measured(Record):
    """A measured experiment: its loss is the paper's (told to the optimiser, if an
    evaluation)."""

    STATUSES: ClassVar[tuple[str, ...]] = MEASURED
    loss: float
    terms: list[float]
    aborted: bool


@dataclass(frozen=True, kw_only=True)
class Evaluation(Measured):
    """One candidate of the optimiser measured (``kind: eval``)."""

    kind: str = 'eval'
    u: list[float]
    best_loss: float | None = None  #: best non-aborted evaluation loss so far, this one in


@dataclass(frozen=True, kw_only=True)
class Reference(Measured):
    """The start gains measured before the search (``kind: reference``, ``eval`` -1)."""

    kind: str = 'reference'


@dataclass(frozen=True, kw_only=True)
class Remeasurement(Measured):
    """Evaluation ``eval`` measured again after the search (``kind: remeasure``)."""

    kind: str = 'remeasure'


@dataclass(frozen=True, kw_only=True)
class Timing(Record):
    """An experiment that did not run on the paper's timing (more held + late drive
    periods than the controller tolerates): ``loss``, ``terms``, ``aborted`` are null,
    its number is ``off_timing_loss``; re-run with the same gains, never told."""

    STATUSES: ClassVar[tuple[str, ...]] = ('timing',)
    status: str = 'timing'
    off_timing_loss: float  #: the controller's number for it (not the paper's loss)


@dataclass(frozen=True, kw_only=True)
class Lost(Record):
    """An attempt with no measured step (no result in time, or stopped in its settle):
    ``loss``, ``terms``, ``aborted`` are null; re-run with the same gains."""

    STATUSES: ClassVar[tuple[str, ...]] = ('lost',)
    status: str = 'lost'


_MEASURED_KINDS: dict[str, type[Measured]] = {
    'eval': Evaluation,
    'reference': Reference,
    'remeasure': Remeasurement,
}
#: Every record kind (docs/tuner.md lists each with its fields).
RECORD_TYPES: tuple[type[Record], ...] = (Evaluation, Reference, Remeasurement, Timing, Lost)


def parse_results(raw: bytes) -> tuple[list[Record], int]:
    """The records of results.jsonl's bytes and the end of its last complete line (bytes
    after it: a record written in part, not read).  :class:`RecordError` ('line N ...')
    for a line that is not a record or is out of the tuner's order (:class:`_Order`)."""
    end = raw.rfind(b'\n') + 1
    out: list[Record] = []
    order = _Order()
    for i, line in enumerate(raw[:end].split(b'\n')[:-1]):
        try:
            rec = Record.from_json(line)
        except RecordError as exc:
            sep = ' ' if str(exc) == 'is not a JSON record' else ': '
            raise RecordError(f'line {i + 1}{sep}{exc}') from None
        problem = order.take(rec, i + 1)
        if problem:
            raise RecordError(f'line {i + 1}: {problem}')
        out.append(rec)
    return out, end


class _Order:
    """The order the tuner writes records in, checked line by line: one reference (eval
    -1), evaluations 0, 1, 2, ... each measured once (after its lost and off-timing
    attempts), then re-measurements, each once, of a completed evaluation before it."""

    def __init__(self) -> None:
        self.next_eval = 0  #: the evaluation the next eval record is (an attempt of)
        self.eval_line: dict[int, int] = {}  #: measured evaluation -> its line
        self.completed: set[int] = set()  #: evaluations with status ok
        self.reference_line = 0  #: the measured reference's line (0: none yet)
        self.remeasured: dict[int, int] = {}  #: re-measured evaluation -> its line

    def take(self, rec: Record, line: int) -> str | None:
        """What is wrong with ``rec`` (on ``line``) after the records before it, or None
        (then it is counted)."""
        measured = rec.status in MEASURED
        e = rec.eval
        if rec.kind == 'reference':
            if e != -1:
                return f'a reference record with eval {e} (the reference is eval -1)'
            if measured and self.reference_line:
                return f'a second measured reference (the first is line {self.reference_line})'
            if measured:
                self.reference_line = line
            return None
        if rec.kind == 'eval':
            if e < self.next_eval:
                return f'evaluation {e} again (it was measured on line {self.eval_line[e]})'
            if e > self.next_eval:
                return (
                    f'evaluation {e}, but evaluation {self.next_eval} is missing (each '
                    'evaluation follows the one before)'
                )
            if measured:
                self.eval_line[e] = line
                self.next_eval += 1
                if rec.status == 'ok':
                    self.completed.add(e)
            return None
        if e not in self.completed:  # a re-measurement
            return (
                f're-measurement of evaluation {e}, which is not a completed evaluation before it'
            )
        if measured and e in self.remeasured:
            return f'evaluation {e} re-measured again (first on line {self.remeasured[e]})'
        if measured:
            self.remeasured[e] = line
        return None
