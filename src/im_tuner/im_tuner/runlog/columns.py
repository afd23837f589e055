"""evaluations.csv, the report's CSV export of the records: its columns and their types
(from the record fields) and one record's cells.  Its own module: it needs numpy."""

from __future__ import annotations

import dataclasses
from typing import Any

from im_controller.config import GAIN_NAMES

from .records import LINE_ORDER, Evaluation, Record

#: Record fields that are one CSV column each, in the CSV's order: the record's identity
#: and loss first, then the controller's outcome as the line has it, the time last.
_CSV_FIELDS = (
    'kind',
    'eval',
    'attempt',
    'status',
    'loss',
    'best_loss',
    *LINE_ORDER[LINE_ORDER.index('aborted') : LINE_ORDER.index('wall_s') + 1],
    'time',
)
_TERMS = ('term1', 'term2', 'term3')  #: ``terms``, one column each
_U = tuple(f'u{i}' for i in range(len(GAIN_NAMES)))  #: ``u``, one column each
#: Columns of evaluations.csv, in order (units in docs/tuner.md): ``run`` (the run's
#: label) and ``bag`` (its session's bag) are the report's, the rest the record's --
#: ``terms``, ``gains`` (by name) and ``u`` spread over a column each.
CSV_COLUMNS: tuple[str, ...] = (
    'run',
    *_CSV_FIELDS[:6],
    *_TERMS,
    *GAIN_NAMES,
    *_U,
    *_CSV_FIELDS[6:],
    'bag',
)


def _field_type(name: str) -> str:
    return str(next(f.type for f in dataclasses.fields(Evaluation) if f.name == name))


#: CSV columns read back as int / float / bool (from the record fields' types).
CSV_INT: tuple[str, ...] = tuple(c for c in _CSV_FIELDS if _field_type(c).startswith('int'))
CSV_FLOAT: tuple[str, ...] = (
    *(c for c in _CSV_FIELDS if _field_type(c).startswith('float')),
    *_TERMS,
    *GAIN_NAMES,
    *_U,
)
CSV_BOOL: tuple[str, ...] = tuple(c for c in _CSV_FIELDS if _field_type(c).startswith('bool'))


def csv_values(rec: Record) -> dict[str, Any]:
    """The record's cells of evaluations.csv by column (the report adds ``run``,
    ``best_loss`` -- its own best so far -- and ``bag``); None: an empty cell."""
    none: list[float | None] = [None] * len(GAIN_NAMES)
    terms: list[float | None] = list(rec.terms) if rec.terms else none[:3]
    u: list[float | None] = list(rec.u) if rec.u else none
    out = {c: getattr(rec, c, None) for c in _CSV_FIELDS}  # (best_loss: evaluations only)
    out.update(zip(_TERMS, terms, strict=True))
    out.update(rec.gains)
    out.update(zip(_U, u, strict=True))
    return out
