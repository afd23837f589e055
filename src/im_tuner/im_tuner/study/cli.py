"""``ros2 run im_tuner study``: the command (see the package docstring)."""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import os
import re
import shlex
import sys
from pathlib import Path

from im_drive_sim.cli import Parser, UsageError, int_in

from ..space import TunerParamsError
from . import runs as S
from .figures import (
    fig_comparison,
    fig_convergence,
    fig_tables,
)
from .files import (
    tuner_command,
    write_runs_csv,
    write_starts,
    write_tables_csv,
)
from .markdown import (
    reproduction_md,
)
from .stats import (
    StudyStats,
    compute,
)
from .text import (
    EXIT_USAGE,
    StudyError,
    tables_text,
)

__all__ = ['main', 'reproduction_md', 'tables_text', 'tuner_command', 'write_outputs']


# -- output ---------------------------------------------------------------------------------------
def write_outputs(st: StudyStats, out: Path, command: str) -> dict[str, Path]:
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    text = tables_text(st)
    paths['tables'] = out / 'tables.txt'
    paths['tables'].write_text(text)
    paths['tables_csv'] = write_tables_csv(st, out)
    write_starts(st.res, out)
    paths['runs_csv'] = write_runs_csv(st, out)
    figs = {'convergence': fig_convergence(st), 'comparison': fig_comparison(st)}
    if any(a in S.PAPER_ALGOS for a in st.res.spec.algos):
        figs = {'tables': fig_tables(st), **figs}
    for name, fig in figs.items():
        paths[f'{name}_png'] = out / f'{name}.png'
        fig.savefig(paths[f'{name}_png'], dpi=110)
    paths['md'] = out / 'reproduction.md'
    paths['md'].write_text(reproduction_md(st, command, {k: f'{k}.png' for k in figs}))
    return paths


def _build_parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog='ros2 run im_tuner study',
        description="The paper's configuration study (Tables I-III) offline, on the "
        'numba kernels of the nodes, in a process pool '
        '(docs/reproduction.md).',
    )
    ap.add_argument('--runs', type=int, default=100, help='runs per configuration (default 100)')
    ap.add_argument(
        '--budget', type=int, default=200, help='loss evaluations per run (default 200)'
    )
    ap.add_argument(
        '--algos',
        default=','.join(S.PAPER_ALGOS),
        help='comma-separated algorithms, each with its own small grid: '
        + ', '.join(S.STUDY_ALGOS)
        + " (default: the paper's spsa,necga)",
    )
    ap.add_argument(
        '--model',
        choices=('full', 'reduced'),
        default='full',
        help='drive model (default full: voltage-fed with the encoder)',
    )
    ap.add_argument(
        '--jobs',
        type=int_in(1, max_jobs()),
        default=None,
        help='worker processes (default: every core; at most '
        f'{max_jobs()}, 4 per core); results do not depend on it',
    )
    ap.add_argument(
        '--cluster',
        metavar='tcp://HOST:PORT',
        default=None,
        help='run on the Dask cluster whose scheduler listens there (start one with '
        '`dask scheduler --port 8786` and `dask worker tcp://HOST:8786 --nthreads 1` in '
        "this project's venv on each machine); the tables are the same as with --jobs",
    )
    ap.add_argument(
        '--seed', type=int, default=S.DEFAULT_SEED, help=f'study seed (default {S.DEFAULT_SEED})'
    )
    ap.add_argument(
        '--satisfactory',
        type=float,
        default=None,
        help='satisfactory level of the normalised final loss (default '
        f'{S.DEFAULT_SATISFACTORY:g}: 10 %% better than the hand-tuned start)',
    )
    ap.add_argument(
        '--no-remeasure',
        action='store_true',
        help="skip the re-measurement of each run's final controller",
    )
    ap.add_argument(
        '--params',
        metavar='FILE',
        help='tuner parameter file (search box; default the packaged one)',
    )
    ap.add_argument(
        '--drive-config', metavar='FILE', help="drive parameter file (default the paper's motor)"
    )
    ap.add_argument(
        '--out',
        type=Path,
        metavar='DIR',
        help='output directory (default bags/study_<model>_<UTC time>)',
    )
    ap.add_argument(
        '--from',
        dest='source',
        type=Path,
        metavar='DIR',
        help='re-tabulate an existing study (no new experiments; with '
        '--satisfactory); writes into DIR unless --out',
    )
    ap.add_argument('--quiet', action='store_true', help='no progress line')
    return ap


class Progress:
    """Runs done, experiments/s and ETA: an updating line on a terminal, else a line every
    10 %."""

    def __init__(self, total_exp_per_run: int, quiet: bool, stream=sys.stderr) -> None:
        self.per_run, self.quiet, self.stream = total_exp_per_run, quiet, stream
        self.tty = stream.isatty()
        self.last_pct = -1

    def __call__(self, done: int, total: int, elapsed: float) -> None:
        if self.quiet:
            return
        pct = 100 * done // total
        if not self.tty and pct // 10 == self.last_pct // 10 and done != total:
            return
        self.last_pct = pct
        rate = done * self.per_run / elapsed if elapsed > 0 else 0.0
        eta = int(elapsed / done * (total - done)) if done else 0
        fill = 24 * done // total
        text = (
            f'study [{"#" * fill}{"." * (24 - fill)}] {done}/{total} runs  '
            f'{done * self.per_run} experiments  {rate:.0f}/s  ETA {eta // 60}:{eta % 60:02d}'
        )
        if self.tty:
            self.stream.write('\r' + text + ('\n' if done == total else ''))
        else:
            self.stream.write(text + '\n')
        self.stream.flush()


def max_jobs() -> int:
    """Most worker processes accepted: 4 per core (each is a whole Python process)."""
    return 4 * (os.cpu_count() or 1)


def _spec(cli: argparse.Namespace) -> S.StudySpec:
    algos = tuple(a.strip() for a in cli.algos.split(',') if a.strip())
    for a in algos:
        if a not in S.STUDY_ALGOS:
            raise StudyError(
                f'--algos: no study grid for {a!r} (allowed: {", ".join(S.STUDY_ALGOS)})'
            )
    if cli.jobs is not None and cli.jobs < 1:
        raise StudyError(f'--jobs must be >= 1, got {cli.jobs}')
    if cli.cluster is not None:
        if cli.jobs is not None:
            raise StudyError(
                '--cluster and --jobs exclude each other (the cluster has its workers)'
            )
        if not re.fullmatch(r'(tcp|tls)://[A-Za-z0-9_.\-\[\]:]+:[0-9]{1,5}', cli.cluster):
            raise StudyError(
                f'--cluster must be a Dask scheduler address tcp://HOST:PORT, got {cli.cluster!r}'
            )
    try:
        spec = S.StudySpec(
            runs=cli.runs,
            budget=cli.budget,
            algos=algos,
            model=cli.model,
            seed=cli.seed,
            satisfactory=float(
                S.DEFAULT_SATISFACTORY if cli.satisfactory is None else cli.satisfactory
            ),
            remeasure=not cli.no_remeasure,
            drive_config=cli.drive_config,
            params_file=cli.params,
        )
    except ValueError as exc:
        raise StudyError(f'--{exc}') from None  # the messages start with the option's name
    try:
        spec.params()
        spec.drive()
    except (TunerParamsError, ValueError) as exc:
        raise StudyError(str(exc)) from None
    return spec


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if args is None else args)
    command = ' '.join(['ros2 run im_tuner study', *(shlex.quote(a) for a in argv)])
    try:
        cli = _build_parser().parse_args(argv)
        if cli.satisfactory is not None and not (
            cli.satisfactory > 0 and math.isfinite(cli.satisfactory)
        ):
            raise StudyError(
                f'--satisfactory must be a normalised loss > 0, got {cli.satisfactory}'
            )
        if cli.source is not None:
            try:
                res = S.load(cli.source)
            except ValueError as exc:
                raise StudyError(str(exc)) from None
            out = cli.out or cli.source
        else:
            spec = _spec(cli)
            stamp = _dt.datetime.now(_dt.UTC).strftime('%Y_%m_%d-%H_%M_%S')
            out = cli.out or Path('bags') / f'study_{spec.model}_{stamp}'
        if out.exists() and not out.is_dir():
            raise StudyError(f'--out {out}: exists and is not a directory')
        if cli.source is None and out.is_dir() and (out / S.META_FILE).exists():
            raise StudyError(
                f'--out {out}: already holds a study (use --from to re-tabulate '
                'it, or another --out)'
            )
        if cli.source is None and out.is_dir() and any(out.iterdir()):
            raise StudyError(
                f'--out {out}: already exists and is not empty; choose a new directory'
            )
        if (
            cli.source is not None
            and cli.out is not None
            and cli.out.is_dir()
            and any(cli.out.iterdir())
            and cli.out.resolve() != cli.source.resolve()
        ):
            raise StudyError(
                f'--out {out}: already exists and is not empty; choose a new directory'
            )
    except (StudyError, UsageError) as exc:
        print(f'error: study: {exc}', file=sys.stderr)
        return EXIT_USAGE
    if cli.source is None:
        per_run = spec.budget + 1 + int(spec.remeasure)
        n = len(spec.cells) * spec.runs
        if not cli.quiet:
            print(
                f'study: {len(spec.cells)} configurations x {spec.runs} runs x {spec.budget} '
                f'evaluations = {n * per_run} experiments ({spec.model} model) on '
                + (
                    f'the Dask cluster at {cli.cluster}'
                    if cli.cluster
                    else f'{cli.jobs or S.default_jobs()} worker(s)'
                )
                + f' -> {out}',
                file=sys.stderr,
            )
        try:
            res = S.run_study(spec, cli.jobs, Progress(per_run, cli.quiet), cluster=cli.cluster)
            res.command = command
        except OSError as exc:  # no scheduler at --cluster (distributed raises OSError)
            print(f'error: study: --cluster {cli.cluster}: {exc}'.splitlines()[0], file=sys.stderr)
            return EXIT_USAGE
        except KeyboardInterrupt:
            print('study: interrupted; nothing written', file=sys.stderr)
            return 130
        S.save(res, out)
    st = compute(res, cli.satisfactory)
    paths = write_outputs(st, out, command)
    print(paths['tables'].read_text(), end='')
    print(
        f'study written to {out}/: '
        + ', '.join(p.name for p in paths.values())
        + (', study.npz, study.json, starts/' if cli.source is None else '')
    )
    return 0


if __name__ == '__main__':
    sys.exit(main())
