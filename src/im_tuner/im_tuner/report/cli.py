"""``ros2 run im_tuner report``: the command (checks every run first, then writes; ``load``,
``text``, ``table`` and ``figures`` are imported once the runs are known to be runs)."""

from __future__ import annotations

import datetime as _dt
import json
import multiprocessing
import multiprocessing.process
import os
import shutil
import signal
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from im_drive_sim.cli import EXIT_USAGE, UsageError, held_interrupts, quiet_interrupts

from ..rundir import RUN_FILE, RunDir, RunDirError, is_bag_dir
from ..typed_cli import OptionsParser, option
from .errors import ReportError

if TYPE_CHECKING:
    from ..runlog import RunConfig
    from .load import RunReport


# ------------------------------------------------------------------------- the command
def write_report(
    runs: list[RunReport], out: Path, progress: Callable[[str], None] | None = None
) -> dict[str, Path]:
    """Write summary.txt, evaluations.csv and the PNGs into ``out``; returns name -> path.

    Runs loaded without their signals (``load_run(..., signals=False)``) have their bags
    read here, while a second process draws the figures that need only the records
    (:data:`~.figures.RECORD_FIGURES`): on two cores the bag read and half the drawing
    overlap. If that process fails, its figures are drawn here."""
    from .figures import RECORD_FIGURES, load_matplotlib, save_figures
    from .load import FIGURES, load_signals
    from .table import write_csv
    from .text import summary_text

    made = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    ahead = None
    try:
        pending = [rr for rr in runs if not rr.signals_read]
        load_matplotlib()  # here, once for both processes
        ahead = _draw_ahead(runs, out, RECORD_FIGURES) if pending else None
        for rr in pending:
            load_signals(rr, progress)
        paths = {'summary': out / 'summary.txt', 'csv': out / 'evaluations.csv'}
        paths['summary'].write_text('\n\n'.join(summary_text(rr) for rr in runs) + '\n')
        write_csv(runs, paths['csv'])
        if progress:
            progress('plotting')
        drawn = save_figures(
            runs, out, [n for n in FIGURES if ahead is None or n not in RECORD_FIGURES]
        )
    except BaseException:
        if ahead is not None:  # leaving on an error: the child is ended by its PID
            ahead.terminate()
            ahead.join()
        if made:  # Ctrl-C or an error: no half-written report left where none was
            shutil.rmtree(out, ignore_errors=True)
        raise
    if ahead is not None:
        ahead.join()
        drawn.update(
            {n: out / f'{n}.png' for n in RECORD_FIGURES}
            if ahead.exitcode == 0
            else save_figures(runs, out, RECORD_FIGURES)  # again here: an error says why
        )
    return paths | {n: drawn[n] for n in FIGURES}


def _draw_ahead(
    runs: list[RunReport], out: Path, names: tuple[str, ...]
) -> multiprocessing.process.BaseProcess | None:
    """A forked child drawing ``names`` into ``out`` (None: one core, or no fork)."""
    if len(os.sched_getaffinity(0)) < 2 or 'fork' not in multiprocessing.get_all_start_methods():
        return None
    sys.stdout.flush()  # nothing buffered twice
    sys.stderr.flush()
    proc = multiprocessing.get_context('fork').Process(
        target=_draw_child, args=(runs, out, names), name='report-figures', daemon=True
    )
    with held_interrupts():  # a Ctrl-C on the fork: raised after it, not dropped
        proc.start()
    return proc


def _draw_child(runs: list[RunReport], out: Path, names: tuple[str, ...]) -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # Ctrl-C: the parent reports, this ends
    try:
        from .figures import save_figures

        save_figures(runs, out, names)
    except BaseException:
        os._exit(1)  # quietly: the parent draws these again and reports any error


def _labels(paths: list[Path], runs: list[RunConfig]) -> list[str]:
    """Short names: '<algo> seed <s>', the directory name when that is not unique."""
    short = [f'{r.algo} seed {r.seed}' for r in runs]
    if len(set(short)) == len(short):
        return short
    return (
        [p.name for p in paths]
        if len({p.name for p in paths}) == len(paths)
        else [str(p) for p in paths]
    )


@dataclass
class ReportOptions:
    """The report's command line, typed (:func:`~..typed_cli.option`)."""

    PROG = 'ros2 run im_tuner report'
    DESCRIPTION = (
        'Summary, plots (paper Figs. 5, 8, 9) and per-evaluation CSV of one or more tuning '
        "runs (docs/report.md); or, with --bag-info, one bag's statistics (docs/report.md, "
        '"Bag statistics").'
    )

    runs: list[Path] = option(
        'run directories made by `ros2 run im_tuner tuner` (several: overlaid)',
        {'nargs': '*', 'type': Path, 'metavar': 'RUN_DIR'},
        flag='runs',
    )
    bags: list[Path] = option(
        "more bags to take the experiments' signals from, beside the run's own: a drive "
        "host's bag copied from the drive's computer (docs/two-computers.md)",
        {'nargs': '+', 'type': Path, 'metavar': 'BAG_DIR'},
    )
    out: Path | None = option(
        'where to write (default: RUN_DIR/report, or for several runs <parent of the '
        'first>/compare_<UTC time>)',
        {'type': Path, 'metavar': 'DIR'},
    )
    bag_info: Path | None = option(
        "print one bag's statistics instead, as `ros2 bag info` does, with the recorder's "
        'recorded / published / lost per topic (any bag, a repaired one too)',
        {'type': Path, 'metavar': 'BAG_DIR'},
    )
    json: bool = option('with --bag-info: the statistics as JSON', {'action': 'store_true'})


def _bag_info(cli: ReportOptions, bag: Path) -> int:
    """``--bag-info``: nothing is written; a bad path is one line and exit 2."""
    if cli.runs or cli.bags or cli.out is not None:
        raise ReportError('--bag-info takes one bag directory and no run, --bags or --out')
    from .baginfo import bag_info, format_info

    info = bag_info(bag)
    print(json.dumps(info, indent=2) if cli.json else format_info(info))
    return 0


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if args is None else args)
    try:
        cli = OptionsParser(ReportOptions).parse_args(argv)
        if cli.bag_info is not None:
            return _bag_info(cli, cli.bag_info)
        if cli.json:
            raise ReportError('--json goes with --bag-info BAG_DIR')
        if not cli.runs:
            raise ReportError(
                'the following arguments are required: RUN_DIR (or --bag-info BAG_DIR)'
            )
        # validate every run before reading any bag or writing anything
        for p in cli.runs:
            try:
                RunDir.open(p).read_config()
                RunDir(p).read_results()  # every record checked: no traceback later
                RunDir(p).read_summary()  # (one of a newer tuner's format: refused)
            except RunDirError as exc:
                raise ReportError(str(exc)) from None
        for bag in cli.bags:
            if not is_bag_dir(bag):
                raise ReportError(f'--bags {bag}: not a bag directory (no metadata.yaml or .mcap)')
        if cli.out is not None and cli.out.exists() and not cli.out.is_dir():
            raise ReportError(f'--out {cli.out}: exists and is not a directory')
        if cli.out is not None and any(is_bag_dir(d) for d in (cli.out, *cli.out.parents)):
            raise ReportError(
                f'--out {cli.out}: a bag folder or in one (it holds metadata.yaml or .mcap '
                'files, perhaps still recording); choose another directory'
            )
        if cli.out is not None and (cli.out / RUN_FILE).exists():
            raise ReportError(
                f'--out {cli.out}: a run directory (the report never writes into one; '
                f'its default place is {cli.out / "report"})'
            )
        default = cli.runs[0] / 'report' if cli.out is None and len(cli.runs) == 1 else None
        if default is not None and default.exists() and not default.is_dir():
            raise ReportError(
                f'{default}: exists and is not a directory (the default place of the '
                'report); give --out DIR'
            )
    except (ReportError, UsageError) as exc:
        print(f'error: report: {exc}', file=sys.stderr)
        return EXIT_USAGE
    with quiet_interrupts('report'):  # numpy, the bag reader: only for a real report
        from .load import load_run

    heads = [RunDir(p).read_config() for p in cli.runs]
    labels = _labels(cli.runs, heads)

    def progress(msg: str) -> None:
        print(f'report: {msg}', file=sys.stderr, flush=True)

    try:
        # the records now, the bags in write_report (beside the figures of the records)
        runs = [
            load_run(p, lab, signals=False, extra_bags=cli.bags)
            for p, lab in zip(cli.runs, labels, strict=True)
        ]
    except ReportError as exc:
        print(f'error: report: {exc}', file=sys.stderr)
        return EXIT_USAGE
    if cli.out is not None:
        out = cli.out
    elif len(runs) == 1:
        out = runs[0].path / 'report'
    else:
        stamp = _dt.datetime.now(_dt.UTC).strftime('%Y%m%dT%H%M%SZ')
        out = runs[0].path.parent / f'compare_{stamp}'
    try:
        paths = write_report(runs, out, progress)
    except OSError as exc:
        print(f'error: report: cannot write {out}: {exc.strerror or exc}', file=sys.stderr)
        return 1
    print(paths['summary'].read_text(), end='')
    print(f'report written to {out}/: ' + ', '.join(p.name for k, p in paths.items()))
    return 0


if __name__ == '__main__':
    sys.exit(main())
