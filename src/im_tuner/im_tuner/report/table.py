"""evaluations.csv: one row per experiment of every run; floats as ``repr`` (exact)."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..runlog import Evaluation, Record
from ..runlog.columns import CSV_BOOL, CSV_COLUMNS, CSV_FLOAT, CSV_INT, csv_values
from .load import RunReport


# ------------------------------------------------------------------------------- CSV
def best_so_far(records: Sequence[Record]) -> list[float | None]:
    best: float | None = None
    out: list[float | None] = []
    for r in records:
        if (
            isinstance(r, Evaluation)
            and r.status == 'ok'
            and not r.aborted
            and (best is None or r.loss < best)
        ):
            best = r.loss
        out.append(best if r.kind == 'eval' else None)
    return out


def _cell(v: Any) -> str:
    if v is None:
        return ''
    if isinstance(v, bool):
        return 'true' if v else 'false'
    if isinstance(v, float):
        return repr(v)
    return str(v)


def write_csv(runs: list[RunReport], path: Path) -> int:
    """One row per experiment of every run (CSV_COLUMNS); returns the rows written."""
    n = 0
    with open(path, 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for rr in runs:
            for rec, best, bag in zip(
                rr.records, best_so_far(rr.records), rr.record_bag, strict=True
            ):
                # the record's cells (the run log's ``csv_values``) and the report's own three
                vals = csv_values(rec) | {'run': rr.label, 'best_loss': best, 'bag': bag}
                w.writerow([_cell(vals.get(c)) for c in CSV_COLUMNS])
                n += 1
    return n


def read_csv(path: Path | str) -> list[dict[str, Any]]:
    """evaluations.csv back as typed rows (None for empty cells); floats are exact."""
    out = []
    with open(path, newline='') as f:
        for row in csv.DictReader(f):
            r: dict[str, Any] = {}
            for k, v in row.items():
                if v == '':
                    r[k] = None
                elif k in CSV_INT:
                    r[k] = int(v)
                elif k in CSV_FLOAT:
                    r[k] = float(v)
                elif k in CSV_BOOL:
                    r[k] = v == 'true'
                else:
                    r[k] = v
            out.append(r)
    return out
