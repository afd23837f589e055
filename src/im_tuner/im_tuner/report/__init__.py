"""The report of tuning runs: a summary, plots after the paper's Figs. 5, 8 and 9, a CSV.

``ros2 run im_tuner report RUN_DIR [RUN_DIR2 ...] [--out DIR]`` (docs/report.md). No rclpy
here. Modules by job: ``load`` (records, bags, signals), ``text`` (summary), ``table`` (CSV),
``figures``, ``cli``, ``errors``. The names below are loaded on first use (PEP 562), so
that ``report --help`` and a refusal import nothing heavy (docs/report.md, "Speed").
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the static view of the lazy names below
    from .cli import main, write_report
    from .errors import ReportError
    from .figures import make_figures
    from .load import FIGURES, Experiment, RunReport, load_run
    from .table import CSV_COLUMNS, read_csv, write_csv
    from .text import summary_text

#: public name -> the submodule that defines it
_LAZY = {
    'CSV_COLUMNS': 'table',
    'FIGURES': 'load',
    'Experiment': 'load',
    'ReportError': 'errors',
    'RunReport': 'load',
    'load_run': 'load',
    'main': 'cli',
    'make_figures': 'figures',
    'read_csv': 'table',
    'summary_text': 'text',
    'write_csv': 'table',
    'write_report': 'cli',
}

__all__ = [
    'CSV_COLUMNS',
    'FIGURES',
    'Experiment',
    'ReportError',
    'RunReport',
    'load_run',
    'main',
    'make_figures',
    'read_csv',
    'summary_text',
    'write_csv',
    'write_report',
]


def __getattr__(name: str) -> Any:
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    value = getattr(importlib.import_module(f'.{mod}', __name__), name)
    globals()[name] = value  # found directly next time
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
