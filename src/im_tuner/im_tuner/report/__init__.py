"""The report of tuning runs: a summary, plots after the paper's Figs. 5, 8 and 9, a CSV.

``ros2 run im_tuner report RUN_DIR [RUN_DIR2 ...] [--out DIR]`` reads each run's
``run.yaml``, ``results.jsonl`` (the truth: one line per experiment) and its session
bags, and writes into ``DIR`` (default ``RUN_DIR/report/`` for one run,
``<parent of RUN_DIR>/compare_<UTC time>/`` for several):

* ``summary.txt``  -- also printed: per run the algorithm and configuration, outcome,
  best and start loss, best gains, evaluations to a satisfactory loss, aborted
  experiments; per bag the topics with message counts and rates, duration, the recorder's
  recorded-vs-published check, and the losses in the bag checked against results.jsonl;
* ``fig5_trajectory.png`` -- position reference and load torque of two consecutive
  experiments (the paper's Fig. 5);
* ``fig8_best_vs_start.png`` -- position error, speed error and current reference of the
  best evaluation's experiment and of the start controller's (Fig. 8);
* ``fig9_loss.png`` -- loss per evaluation with the best-so-far line (Fig. 9 a, b);
* ``fig9_gains.png`` -- each gain's path over the evaluations (Fig. 9 c, d);
* ``evaluations.csv`` -- one row per experiment of every run (:data:`CSV_COLUMNS`);
  floats written with ``repr``, so :func:`read_csv` gives back the exact values.

With several runs the figures overlay them (for example SPSA against neCGA). A run that
was interrupted or killed is reported from what it left: the records written so far and
the complete chunks of a bag the recorder could not close. Nothing in a run directory is
changed. The signals of an experiment come from ``controller/internals`` in the bag: the
rows whose step index k lies in ``[t_start_ns / Ts, t_start_ns / Ts + steps)`` of its
results record (docs/interfaces.md: state k is at sim time k Ts).

No rclpy here: the report runs without a ROS graph. Modules by job: ``load`` (records,
bags, signals), ``text`` (summary), ``table`` (CSV), ``figures``, ``cli``, ``errors``.

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
