"""``ros2 run im_tuner study``: the command (see the package docstring).

The options are parsed and checked with light modules only (``spec``, ``cluster``,
``results``): a refusal comes before the optimisers, the numba kernels, scipy, Dask or
matplotlib are imported (they take seconds).  Then, in order: the Dask scheduler (if
``--cluster``) is checked within bounded times, the study runs, the files are written.
SIGINT and SIGTERM end the study and its worker processes, writing nothing; a killed
study's workers end by themselves (``worker.init_pool_worker``).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import os
import shlex
import signal
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from im_drive_sim.cli import EXIT_INTERRUPTED, EXIT_USAGE, UsageError, int_in
from im_drive_sim.params import REALISM_PROFILES

from ..progress import Line
from ..tuner_args import OptionsParser, option
from . import cluster as K, spec as S
from .drives import FamilyResult, drive_dirs, is_family, load_family, save_family
from .results import META_FILE, StudyResult, load, save
from .spec import StudyError

#: im_tuner.prior.CACHE_ENV (not imported here: it loads the kernels)
PRIOR_CACHE_ENV = 'IM_TUNER_PRIOR_CACHE'

if TYPE_CHECKING:
    from .stats import StudyStats
    from .summary import FamilyStats

#: Exit status after SIGTERM (the shell's 128 + 15).
EXIT_TERMINATED = 143


# -- output ---------------------------------------------------------------------------------------
def write_outputs(st: StudyStats, out: Path, command: str) -> dict[str, Path]:
    from .figures import fig_comparison, fig_convergence, fig_tables
    from .files import write_runs_csv, write_starts, write_tables_csv
    from .markdown import reproduction_md
    from .text import tables_text

    out.mkdir(parents=True, exist_ok=True)
    paths = {'tables': out / 'tables.txt'}
    paths['tables'].write_text(tables_text(st))
    paths['tables_csv'] = write_tables_csv(st, out)
    write_starts(st.res, out)
    paths['runs_csv'] = write_runs_csv(st, out)
    figs = {'convergence': fig_convergence(st), 'comparison': fig_comparison(st)}
    if st.res.spec.paper_tables:
        figs = {'tables': fig_tables(st), **figs}
    for name, fig in figs.items():
        paths[f'{name}_png'] = out / f'{name}.png'
        fig.savefig(paths[f'{name}_png'], dpi=110)
    paths['md'] = out / 'reproduction.md'
    paths['md'].write_text(reproduction_md(st, command, {k: f'{k}.png' for k in figs}))
    return paths


def write_family_outputs(fs: FamilyStats, out: Path, command: str) -> dict[str, Path]:
    """Each drive's files (``write_outputs``) in its directory, then family.txt and
    family.md (every drive's comparison, the summary, the goal lines) in ``out``."""
    from .markdown import family_md
    from .text import family_text

    figures: dict[str, dict[str, str]] = {}
    for (name, st), d in zip(fs.drives, drive_dirs(fs.fam.spec.drives), strict=True):
        sub = write_outputs(st, out / d, command)
        # the comparison only: the write-up links it (each drive's directory has the rest)
        figures[name] = {'comparison': f'{d}/{sub["comparison_png"].name}'}
    paths = {'tables': out / 'family.txt', 'md': out / 'family.md'}
    paths['tables'].write_text(family_text(fs))
    paths['md'].write_text(family_md(fs, command, figures))
    return paths


def _seconds(text: str) -> float:
    """A duration in seconds: a finite number > 0."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'not a number of seconds: {text!r}') from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f'must be a number of seconds > 0, got {text}')
    return v


def max_jobs() -> int:
    """Most worker processes accepted: 4 per core (each is a whole Python process)."""
    return 4 * (os.cpu_count() or 1)


#: the argparse declaration of an option naming a study's directory
_DIR = {'type': Path, 'metavar': 'DIR'}


@dataclass
class StudyOptions:
    """The study's command line, typed (:mod:`..tuner_args`)."""

    PROG = 'ros2 run im_tuner study'
    DESCRIPTION = (
        "The paper's configuration study (Tables I-III) offline, on the numba kernels of "
        'the nodes, in a process pool (docs/reproduction.md).'
    )

    runs: int = option('runs per configuration', {'type': int}, 100)
    budget: int = option('loss evaluations per run', None, 200, like='budget')
    algos: str | None = option(
        'comma-separated algorithms, each with its own small grid: ' + ', '.join(S.STUDY_ALGOS),
        shown="the paper's spsa,necga; with --drives every one",
    )
    drives: str | None = option(
        'a study per drive (packaged names, e.g. paper_750w, or drive files) and a summary '
        'over them; each drive has its own experiment, search box, start and L_ref '
        '(im_tuner.family); one row per algorithm at its recommended configuration, plus '
        'the Py-BOBYQA reference row',
        {'metavar': 'NAME,...'},
    )
    plant: str | None = option(
        'the simulated plant, when it is not the drive the tuner is told (a packaged name '
        'or a drive file, loaded as --drives): the experiment, search box, start and '
        "safe's first step still come from the told drive (--drives, --drive-config); with "
        '--drives one plant per drive or one for all. Its Ts and machine.isq_max must be '
        'the told drive\'s (docs/optimisers.md, "When the drive file is wrong")',
        {'metavar': 'FILE|NAME[,...]'},
    )
    plant_mismatch: str | None = option(
        'change the plant (the told drive without --plant): KEY=xF multiplies a machine '
        'constant of the drive file (J, Rr, Rs, Lm, B, ...), coulomb=P% sets the Coulomb '
        'friction to P % of rated torque, delay=D the command delay (1 or 2 periods); e.g. '
        "'J=x1.5 Rr=x1.3 Lm=x0.85 coulomb=2% delay=2'",
        {'metavar': "'KEY=xF ... coulomb=P% delay=D'"},
    )
    ripple_limit: str | None = option(
        "every row's standstill-ripple limit, as the tuner's --ripple-limit (default: each "
        "row's tuner default: 1.5 for safe, off for the others); e.g. --algos spsa,necga "
        "--ripple-limit 1.5: what the limit costs the paper's algorithms",
        like='ripple_limit',
    )
    realism: str | None = option(
        "the drives' realism profile",
        {'choices': tuple(REALISM_PROFILES)},
        shown="each drive file's own",
    )
    full_grid: bool = option(
        'with --drives: every configuration of each grid, not the recommended ones',
        {'action': 'store_true'},
    )
    model: str = option(
        'drive model (full: voltage-fed with the encoder)', None, 'full', like='model'
    )
    jobs: int | None = option(
        f'worker processes (at most {max_jobs()}, 4 per core); results do not depend on it',
        {'type': int_in(1, max_jobs())},
        shown='every core',
    )
    cluster: str | None = option(
        'run on the Dask cluster whose scheduler listens there (start one with `dask '
        'scheduler --port 8786` and `dask worker tcp://HOST:8786 --nthreads 1` in this '
        "project's venv on each machine); the tables are the same as with --jobs. Checked "
        'first: refused at once if nothing listens there, within --cluster-timeout s if it '
        'is not a Dask scheduler',
        {'metavar': 'tcp://HOST:PORT'},
    )
    cluster_timeout: float | None = option(
        'with --cluster: the connection to the scheduler and each of its answers must come '
        'within S seconds',
        {'type': _seconds, 'metavar': 'S'},
        shown=f'{K.CONNECT_TIMEOUT_S:g}',
    )
    cluster_wait: float | None = option(
        'with --cluster: how long to wait for a first worker when the scheduler has none',
        {'type': _seconds, 'metavar': 'S'},
        shown=f'{K.WORKER_WAIT_S:g} s',
    )
    seed: int = option('study seed', None, S.DEFAULT_SEED, like='seed')
    satisfactory: float | None = option(
        'satisfactory level of the normalised final loss',
        {'type': float},
        shown=f'{S.DEFAULT_SATISFACTORY:g}: 10 % better than the hand-tuned start',
    )
    no_remeasure: bool = option(
        "skip the re-measurement of each run's final controller", {'action': 'store_true'}
    )
    params: Path | None = option(
        'tuner parameter file (search box)', shown='the packaged one', like='params'
    )
    drive_config: Path | None = option(
        'drive parameter file', shown="the paper's motor", like='drive_config'
    )
    out: Path | None = option('output directory', shown='bags/study_<model>_<UTC time>', like='out')
    source: Path | None = option(
        're-tabulate an existing study (no new experiments; with --satisfactory); writes '
        'into DIR unless --out',
        _DIR,
        flag='--from',
    )
    beside: Path | None = option(
        "also write beside.md: this study's Tables I-III beside those of the study in DIR "
        "(the same grid, e.g. on another --realism) and the paper's, and the paper's "
        'conclusions on both',
        _DIR,
    )
    quiet: bool = option('no progress line', like='quiet')


def _build_parser() -> OptionsParser:
    return OptionsParser(StudyOptions)


class Progress(Line):
    """The study's line: runs done, experiments/s and ETA (a line every 10 % off a terminal)."""

    def __init__(self, total_exp_per_run: int, quiet: bool, stream=sys.stderr) -> None:
        super().__init__(quiet, 10, stream)
        self.per_run = total_exp_per_run

    def __call__(self, done: int, total: int, elapsed: float) -> None:
        exp = done * self.per_run
        rate = exp / elapsed if elapsed > 0 else 0.0
        self.update(
            done,
            total,
            f'study {self.bar(done, total)} {done}/{total} runs  {exp} experiments  '
            f'{rate:.0f}/s  {self.eta(done, total)}',
        )


def _spec(cli: StudyOptions) -> S.StudySpec:
    drives: tuple[str, ...] = ()
    if cli.drives is not None:
        drives = tuple(d.strip() for d in cli.drives.split(',') if d.strip())
        if not drives:
            raise StudyError('--drives: no drive named')
        if cli.drive_config is not None:
            raise StudyError('--drives and --drive-config exclude each other')
    elif cli.full_grid:
        raise StudyError('--full-grid needs --drives (a study of one drive is the full grid)')
    from ..runlog.ripple import parse_ripple_limit
    from .plant import plant_options

    try:  # (the messages name the option)
        plant, mismatch = plant_options(cli.plant, cli.plant_mismatch, drives)
        limit = cli.ripple_limit
        ripple_limit = 'default' if limit is None else parse_ripple_limit(limit)
    except ValueError as exc:
        raise StudyError(str(exc)) from None
    if cli.algos is None:
        algos = S.STUDY_ALGOS if drives else S.PAPER_ALGOS
    else:
        algos = tuple(a.strip() for a in cli.algos.split(',') if a.strip())
    if cli.cluster is not None:
        if cli.jobs is not None:
            raise StudyError(
                '--cluster and --jobs exclude each other (the cluster has its workers)'
            )
        try:
            K.check_address(cli.cluster)
        except ValueError as exc:
            raise StudyError(f'--cluster {exc}') from None
    for name in ('cluster_timeout', 'cluster_wait'):
        if getattr(cli, name) is not None and cli.cluster is None:
            raise StudyError(f'--{name.replace("_", "-")} needs --cluster')
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
            drive_config=None if cli.drive_config is None else str(cli.drive_config),
            params_file=None if cli.params is None else str(cli.params),
            drives=drives,
            realism=cli.realism,
            full_grid=not drives or cli.full_grid,
            plant=plant,
            mismatch=mismatch,
            ripple_limit=ripple_limit,
        )
    except ValueError as exc:
        raise StudyError(f'--{exc}') from None  # the messages start with the option's name
    from ..space import TunerParamsError  # (the parameter files: once the options are good)

    for one in [spec.for_drive(d) for d in drives] or [spec]:
        try:
            one.params()
            told = one.drive()
        except (TunerParamsError, ValueError) as exc:
            raise StudyError(('--drives: ' if drives else '') + str(exc)) from None
        try:
            one.plant_drive(told)  # (plant.PlantError: its message names the option)
        except ValueError as exc:
            where = f' (told {one.drives[0]})' if len(drives) > 1 else ''
            raise StudyError(f'{exc}{where}') from None
    return spec


def _beside(cli: StudyOptions, res: StudyResult | FamilyResult | None) -> StudyResult:
    """The study of ``--beside DIR``, checked: a single study with Tables I-III."""
    if cli.drives or isinstance(res, FamilyResult):
        raise StudyError('--beside compares the Tables I-III of two single-drive studies')
    try:
        assert cli.beside is not None
        other = load(cli.beside)
    except ValueError as exc:
        raise StudyError(f'--beside {exc}') from None
    if not other.spec.paper_tables:
        raise StudyError(f"--beside {cli.beside}: has no Tables I-III (the paper's grids)")
    return other


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if args is None else args)
    command = ' '.join(['ros2 run im_tuner study', *(shlex.quote(a) for a in argv)])
    spec: S.StudySpec | None = None  # a new study, or
    res: StudyResult | FamilyResult | None = None  # an existing one (--from)
    beside = None  # the study of --beside
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
                res = load_family(cli.source)[0] if is_family(cli.source) else load(cli.source)
            except ValueError as exc:
                raise StudyError(str(exc)) from None
            out = cli.out or cli.source
        else:
            spec = _spec(cli)
            stamp = _dt.datetime.now(_dt.UTC).strftime('%Y_%m_%d-%H_%M_%S')
            out = cli.out or Path('bags') / f'study_{spec.model}_{stamp}'
        if cli.beside is not None:
            beside = _beside(cli, res)
        if out.exists() and not out.is_dir():
            raise StudyError(f'--out {out}: exists and is not a directory')
        if cli.source is None and out.is_dir() and (out / META_FILE).exists():
            raise StudyError(
                f'--out {out}: already holds a study (use --from to re-tabulate '
                'it, or another --out)'
            )
        if (
            out.is_dir()
            and any(out.iterdir())
            and (cli.source is None or out.resolve() != cli.source.resolve())
        ):
            raise StudyError(
                f'--out {out}: already exists and is not empty; choose a new directory'
            )
        from ..rundir import check_creatable  # (hours of runs not lost to an unmakeable --out)

        check_creatable(out, StudyError)
        if cli.source is not None and (cli.drives or cli.realism or cli.full_grid):
            raise StudyError('--from re-tabulates: it takes no --drives, --realism or --full-grid')
        if cli.source is not None and {cli.plant, cli.plant_mismatch, cli.ripple_limit} != {None}:
            raise StudyError(
                '--from re-tabulates: its plant and limit are the ones it ran with '
                '(no --plant, --plant-mismatch or --ripple-limit)'
            )
    except (StudyError, UsageError) as exc:
        print(f'error: study: {exc}', file=sys.stderr)
        return EXIT_USAGE
    return _run(cli, spec, res, out, command, beside)


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread (a BaseException: no ``except Exception`` takes
    it for a failure)."""


def _on_sigterm(_signum: int, _frame: Any) -> None:
    raise _Terminated


def _run(
    cli: StudyOptions,
    spec: S.StudySpec | None,
    res: StudyResult | FamilyResult | None,
    out: Path,
    command: str,
    beside: StudyResult | None = None,
) -> int:
    """Everything after the checks: the cluster, the runs, the files.  SIGTERM and Ctrl-C
    end it (and the workers: ``runs.run_study``) with one line and 143 or 130."""
    writing = False  # (files are being written: an interruption leaves them incomplete)
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if main_thread else None
    # The workers share the first steps they compute (a study's runs on one drive share a
    # few models: each computed once, not once per worker): a directory for this study,
    # unless the caller names one.
    cache = None
    if spec is not None and not os.environ.get(PRIOR_CACHE_ENV):
        cache = tempfile.TemporaryDirectory(prefix='im_tuner_priors_')
        os.environ[PRIOR_CACHE_ENV] = cache.name
    try:
        if spec is not None:
            res = _study_drives(cli, spec, out, command) if spec.drives else _study(cli, spec, out)
            writing = True
            if isinstance(res, FamilyResult):
                save_family(res, out)
            else:
                res.command = command
                save(res, out)
        assert res is not None
        if isinstance(res, FamilyResult):
            from .summary import compute_family

            fs = compute_family(res, cli.satisfactory)
            writing = True
            paths = write_family_outputs(fs, out, command)
        else:
            from .stats import compute

            st = compute(res, cli.satisfactory)
            writing = True
            paths = write_outputs(st, out, command)
            if beside is not None:
                from .markdown import beside_md

                paths['beside'] = out / 'beside.md'
                paths['beside'].write_text(beside_md(st, compute(beside, cli.satisfactory)))
    except StudyError as exc:  # (the cluster's, or a worker's numeric baseline)
        print(f'error: study: {exc}', file=sys.stderr)
        return EXIT_USAGE
    except (KeyboardInterrupt, _Terminated) as exc:
        what = 'terminated' if isinstance(exc, _Terminated) else 'interrupted'
        if writing:
            print(f'study: {what} while writing {out}/; its files are incomplete', file=sys.stderr)
        else:
            print(f'study: {what}; nothing written', file=sys.stderr)
        return EXIT_TERMINATED if isinstance(exc, _Terminated) else EXIT_INTERRUPTED
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if cache is not None:
            os.environ.pop(PRIOR_CACHE_ENV, None)
            cache.cleanup()
    print(paths['tables'].read_text(), end='')
    print(
        f'study written to {out}/: '
        + ', '.join(p.name for p in paths.values())
        + (
            ' and a study directory per drive'
            if isinstance(res, FamilyResult)
            else (', study.npz, study.json, starts/' if spec is not None else '')
        )
    )
    return 0


def _study_drives(cli: StudyOptions, spec: S.StudySpec, out: Path, command: str) -> FamilyResult:
    """Each drive's study in turn (``_study``)."""
    results = []
    for i, (d, sub) in enumerate(zip(spec.drives, drive_dirs(spec.drives), strict=True)):
        if not cli.quiet:
            print(f'study: drive {i + 1}/{len(spec.drives)}: {d}', file=sys.stderr)
        results.append(_study(cli, spec.for_drive(d), out / sub, check_cluster=i == 0))
    return FamilyResult(spec, results, command)


def _study(
    cli: StudyOptions, spec: S.StudySpec, out: Path, check_cluster: bool = True
) -> StudyResult:
    """Check the cluster (if any) and run the study; StudyError (one line) if the cluster
    fails or a worker is off the study's numeric baseline."""
    where = '' if cli.cluster is None else f'--cluster {cli.cluster}: '
    if cli.cluster is not None and check_cluster:
        try:
            K.wait_for_scheduler(
                cli.cluster,
                K.CONNECT_TIMEOUT_S if cli.cluster_timeout is None else cli.cluster_timeout,
                K.WORKER_WAIT_S if cli.cluster_wait is None else cli.cluster_wait,
                say=lambda text: print(text, file=sys.stderr, flush=True),
            )
        except K.ClusterError as exc:
            raise StudyError(f'{where}{exc}') from None
    from . import runs  # the optimisers and the numba kernels: seconds

    per_run = spec.budget + 1 + int(spec.remeasure)
    cells = len(spec.cells)
    n = cells * spec.runs
    if not cli.quiet:
        print(
            f'study: {cells} configurations x {spec.runs} runs x {spec.budget} '
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
        return runs.run_study(
            spec,
            cli.jobs,
            Progress(per_run, cli.quiet),
            cluster=cli.cluster,
            cluster_timeout=cli.cluster_timeout or K.CONNECT_TIMEOUT_S,
        )
    except OSError as exc:
        if cli.cluster is None:
            raise
        # the scheduler went away after the check (distributed raises OSError)
        raise StudyError(f'{where}{exc}'.splitlines()[0]) from None
    except runs.NumericMismatch as exc:  # a worker off the study's numeric baseline
        at = f'--cluster {cli.cluster} ' if cli.cluster else ''
        raise StudyError(f'{at}{exc}'.splitlines()[0]) from None


if __name__ == '__main__':
    sys.exit(main())
