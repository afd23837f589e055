"""evaluations.csv: one row per experiment of every run; floats as ``repr`` (exact)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

from im_controller.config import GAIN_NAMES

from .load import (
    _BOOL_COLS,
    _FLOAT_COLS,
    _INT_COLS,
    CSV_COLUMNS,
    RunReport,
)


# ------------------------------------------------------------------------------- CSV
def _best_so_far(records: list[dict[str, Any]]) -> list[float | None]:
    best, out = None, []
    for r in records:
        if (
            r['kind'] == 'eval'
            and r['status'] == 'ok'
            and not r['aborted']
            and (best is None or r['loss'] < best)
        ):
            best = r['loss']
        out.append(best if r['kind'] == 'eval' else None)
    return out


def _csv_row(rr: RunReport, rec: dict[str, Any], best: float | None, bag: str | None) -> list[str]:
    def f(v: Any) -> str:
        if v is None:
            return ''
        if isinstance(v, bool):
            return 'true' if v else 'false'
        if isinstance(v, float):
            return repr(v)
        return str(v)

    terms = rec.get('terms') or [None] * 3
    u = rec.get('u') or [None] * len(GAIN_NAMES)
    vals = {
        'run': rr.label,
        'best_loss': best,
        'term1': terms[0],
        'term2': terms[1],
        'term3': terms[2],
        **(rec.get('gains') or {}),
        **{f'u{i}': x for i, x in enumerate(u)},
        'bag': bag,
    }
    return [f(vals[c]) if c in vals else f(rec.get(c)) for c in CSV_COLUMNS]


def write_csv(runs: list[RunReport], path: Path) -> int:
    """One row per experiment of every run (CSV_COLUMNS); returns the rows written."""
    n = 0
    with open(path, 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for rr in runs:
            for rec, best, bag in zip(
                rr.records, _best_so_far(rr.records), rr.record_bag, strict=True
            ):
                w.writerow(_csv_row(rr, rec, best, bag))
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
                elif k in _INT_COLS:
                    r[k] = int(v)
                elif k in _FLOAT_COLS:
                    r[k] = float(v)
                elif k in _BOOL_COLS:
                    r[k] = v == 'true'
                else:
                    r[k] = v
            out.append(r)
    return out
