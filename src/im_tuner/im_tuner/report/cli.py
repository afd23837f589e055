"""``ros2 run im_tuner report``: the command (checks every run first, then writes)."""

from __future__ import annotations

import argparse
import datetime as _dt
import sys
from pathlib import Path
from typing import Any

from im_drive_sim.cli import Parser, UsageError

from ..rundir import RunDir, RunDirError
from .figures import (
    make_figures,
)
from .load import (
    EXIT_USAGE,
    ReportError,
    RunReport,
    load_run,
)
from .table import (
    write_csv,
)
from .text import (
    summary_text,
)


# ------------------------------------------------------------------------- the command
def write_report(runs: list[RunReport], out: Path) -> dict[str, Path]:
    """Write summary.txt, the PNGs and evaluations.csv into ``out``; returns name -> path."""
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    text = '\n\n'.join(summary_text(rr) for rr in runs) + '\n'
    paths['summary'] = out / 'summary.txt'
    paths['summary'].write_text(text)
    paths['csv'] = out / 'evaluations.csv'
    write_csv(runs, paths['csv'])
    for name, fig in make_figures(runs).items():
        paths[name] = out / f'{name}.png'
        fig.savefig(paths[name], dpi=110)
    return paths


def _labels(paths: list[Path], runs: list[dict[str, Any]]) -> list[str]:
    """Short names: '<algo> seed <s>', the directory name when that is not unique."""
    short = [f'{r.get("algo")} seed {r.get("seed")}' for r in runs]
    if len(set(short)) == len(short):
        return short
    return (
        [p.name for p in paths]
        if len({p.name for p in paths}) == len(paths)
        else [str(p) for p in paths]
    )


def _build_parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog='ros2 run im_tuner report',
        description='Summary, plots (paper Figs. 5, 8, 9) and per-evaluation CSV of '
        'one or more tuning runs (docs/tuner.md, "The report").',
    )
    ap.add_argument(
        'runs',
        nargs='+',
        type=Path,
        metavar='RUN_DIR',
        help='run directories made by `ros2 run im_tuner tuner` (several: overlaid)',
    )
    ap.add_argument(
        '--out',
        type=Path,
        metavar='DIR',
        help='where to write (default: RUN_DIR/report, or for several runs '
        '<parent of the first>/compare_<UTC time>)',
    )
    return ap


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if args is None else args)
    try:
        cli = _build_parser().parse_args(argv)
        # validate every run before reading any bag or writing anything
        for p in cli.runs:
            try:
                RunDir.open(p).read_run()
                RunDir(p).read_results()  # every record checked: no traceback later
            except RunDirError as exc:
                raise ReportError(str(exc)) from None
        if cli.out is not None and cli.out.exists() and not cli.out.is_dir():
            raise ReportError(f'--out {cli.out}: exists and is not a directory')
    except (ReportError, UsageError) as exc:
        print(f'error: report: {exc}', file=sys.stderr)
        return EXIT_USAGE
    heads = [RunDir(p).read_run() for p in cli.runs]
    labels = _labels(cli.runs, heads)

    def progress(msg: str) -> None:
        print(f'report: {msg}', file=sys.stderr, flush=True)

    try:
        runs = [
            load_run(p, lab, progress=progress) for p, lab in zip(cli.runs, labels, strict=True)
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
    progress('plotting')
    try:
        paths = write_report(runs, out)
    except OSError as exc:
        print(f'error: report: cannot write {out}: {exc.strerror or exc}', file=sys.stderr)
        return 1
    print(paths['summary'].read_text(), end='')
    print(f'report written to {out}/: ' + ', '.join(p.name for k, p in paths.items()))
    return 0


if __name__ == '__main__':
    sys.exit(main())
