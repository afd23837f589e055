"""The report of tuning runs: a summary, plots after the paper's Figs. 5, 8 and 9, a CSV.

``ros2 run im_tuner report RUN_DIR [RUN_DIR2 ...] [--out DIR]`` reads each run's
``run.yaml``, ``results.jsonl`` and session bags and writes ``summary.txt`` (also
printed), ``fig5_trajectory.png``, ``fig8_best_vs_start.png``, ``fig9_loss.png``,
``fig9_gains.png`` and ``evaluations.csv`` (docs/report.md). Several runs are overlaid;
an interrupted or killed run is reported from what it left; nothing in a run directory is
changed. No rclpy here. Modules by job: ``load`` (records, bags, signals), ``text``
(summary), ``table`` (CSV), ``figures``, ``cli``, ``errors``.

Start-up: the names below are loaded on first use (PEP 562), and ``cli`` imports numpy,
the bag reader and matplotlib only once the command line and the run directories are
checked, so ``report --help`` and a refusal import none of them (test_report_imports).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the static view of the lazy names below
    from .cli import main, write_report
    from .errors import ReportError
    from .figures import make_figures
    from .load import CSV_COLUMNS, FIGURES, Experiment, RunReport, load_run
    from .table import read_csv, write_csv
    from .text import summary_text

#: public name -> the submodule that defines it
_LAZY = {
    'CSV_COLUMNS': 'load',
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
