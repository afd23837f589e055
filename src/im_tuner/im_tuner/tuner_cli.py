"""The tuner's run configuration: the checks of a new run's options and of ``run.yaml`` on
``--resume`` (:func:`prepare_run`), and the TuningRun built from them. The options
themselves (the parser, what is read from ``--ros-args``) live in :mod:`.tuner_args`.

Every check of a new run is made here, before anything is created and before anything
heavy is imported: this module imports no rclpy, numba, pycma, optuna or scipy at load
(``im_tuner.optim`` loads an algorithm's module only when one is built), so a refusal is
one line within a fraction of a second. The checks that need more come last, in this
order: the controller's name (rclpy's name rules), ``--drive`` (imports the user's
module), the optimiser (built once: its module, e.g. pycma), the user's hardware class
(built once, kept for the bench).
"""

from __future__ import annotations

import contextlib
import math
import shlex
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from im_drive_sim import host, rt
from im_drive_sim.cli import UsageError

from . import optim
from .bench.spec import recording_options
from .names import DEFAULT_TIMING_TOLERANCE, controller_topics
from .optim.base import OptimizerError, check_options
from .record.live import live_settings
from .rundir import RunDir
from .runlog import RunConfig, evaluation_name
from .space import TunerParams, TunerParamsError, load_params, parse_params
from .tuner_args import RUN_SETTINGS, TunerOptions, default, timing_tolerance

if TYPE_CHECKING:
    from .bench.drive_spec import DriveChoice
    from .progress import Progress
    from .tuning import TuningRun


def check_session(cli: TunerOptions) -> None:
    """The options of this session (new or resumed) that go together: a bag option with
    --no-record would be ignored, so it is refused; sets the default compression; the
    live view's port is checked (bound and released) before anything is created."""
    cli.compression = recording_options(cli.no_record, compression=cli.compression)
    live_settings(cli.live, cli.live_host, cli.live_rate, no_record=cli.no_record)


@contextlib.contextmanager
def _usage(*errors: type[Exception], prefix: str = '') -> Iterator[None]:
    """A check's ``errors`` as a UsageError (its message, after ``prefix``)."""
    try:
        yield
    except errors as exc:
        raise UsageError(f'{prefix}{exc}') from None


# -- the run configuration -------------------------------------------------------------------
#: what the host's check before the run has to say: (the line, a warning) or None
HostSaid = tuple[str, bool] | None


def _new_run_config(cli: TunerOptions, argv: list[str]) -> PreparedSession:
    """Check everything of a new run before anything is created, in the module
    docstring's order."""
    # (each option's range is its parser's type: tuner_args.OPTIONS)
    algo = cli.algo or default('algo')
    budget = default('budget') if cli.budget is None else cli.budget
    remeasure = default('remeasure') if cli.remeasure is None else cli.remeasure
    retries = default('retries') if cli.retries is None else cli.retries
    tolerance = timing_tolerance(cli, argv)
    tolerance = DEFAULT_TIMING_TOLERANCE if tolerance is None else tolerance
    ripple_limit = _ripple_limit(cli, algo)
    with _usage(OptimizerError):  # an option of another algorithm too (else ignored)
        options, policies = optim.split_policies(algo, optim.read_options(algo, cli.opt))
        check_options(algo, optim.OPTIONS[algo], options)  # (ranges: no module needed)
    if policies.get('first') == 'identify' and cli.no_reference:
        raise UsageError(
            '--opt first=identify identifies the drive from the reference experiment (the '
            "start's two measurements): not with --no-reference; give --opt first=model or none"
        )
    if rt.RtOptions.from_cli(cli).requested and cli.bench_asked != 'realtime':
        raise UsageError(
            '--thread-priority/--cpu-affinity/--lock-memory set up the composed real-time '
            'loop: give --bench realtime (a drive or controller in its own process takes '
            'them on its own command line)'
        )
    if cli.drive is not None and cli.bench_asked != 'realtime':
        raise UsageError(
            f'--drive {cli.drive}: a drive is plugged into the composed real-time bench '
            'only (--bench realtime)'
        )
    if cli.drive_config is not None:
        from im_drive_sim.drive_file import load_config
        from im_drive_sim.params import ConfigError

        with _usage(ConfigError):
            load_config(cli.drive_config)
    with _usage(TunerParamsError):
        params = load_params(cli.params)
    if cli.params is None:  # a packaged drive's own box and start (docs/drive-family.md)
        from . import family

        setup = family.tuner_setup(cli.drive_config)
        params = params if setup is None else setup.params
    out = cli.out
    if out is not None and out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UsageError(
            f'--out {out}: already exists; choose a new directory'
            + (' (or continue that run with --resume)' if (out / 'run.yaml').exists() else '')
        )
    # -- the checks that import more: rclpy's name rules, the user's drive module, the
    # optimiser's module (pycma for cmaes); the hardware class is built last (it may open
    # a bus), and the run's seeds are drawn once everything passed
    _check_controller_name(cli.controller)
    from .bench import drive_spec

    drive = None
    if cli.drive is not None:
        with _usage(drive_spec.DriveSpecError):
            drive = drive_spec.resolve(cli.drive, cli.drive_config, build=False)
    entropy = np.random.SeedSequence().entropy  # a fresh SeedSequence draws an int
    assert isinstance(entropy, int)
    seed = cli.seed if cli.seed is not None else entropy % 2**31
    if 'first' in policies:  # (model: an offline tuning, seconds)
        policies['first'] = _first_point(cli, policies['first'], params)
    options.update(policies)  # (run.yaml keeps the run's policies with the options)
    with _usage(OptimizerError):  # the cross-option checks (eta < n ...): any seed will do
        optim.make_optimizer(algo, params.space.dim, seed, **_optimizer_args(algo, options, params))
    if drive is not None:
        with _usage(drive_spec.DriveSpecError):
            drive = drive_spec.resolve(cli.drive, cli.drive_config)
    from .tuning import run_seeds

    _opt_ss, drive_seed = run_seeds(seed)
    tolerance, host_record, host_said = _check_host(cli, tolerance)
    run = RunConfig.from_dict(
        {
            'algo': algo,
            'options': options,
            'budget': budget,
            'seed': seed,
            'drive_seed': drive_seed,
            'remeasure': remeasure,
            'reference': not cli.no_reference,
            'retries': retries,
            'timing_tolerance': tolerance,
            'host_check': host_record,
            'ripple_limit': ripple_limit,
            'drive': cli.drive or 'sim',
            'satisfactory_loss': params.satisfactory_loss,
            'params_file': params.source,
            'search_box': params.space.as_dict(),
            'command': ' '.join(shlex.quote(a) for a in argv),
        }
    )
    from .progress import Progress
    from .record.run_info import default_out_dir

    run.put(bench_requested=cli.bench_asked)
    out = out or default_out_dir(prefix=f'tuner_{algo}')
    return PreparedSession(
        run, params, drive, Progress(algo, budget, cli.quiet), out=out, host_said=host_said
    )


def _check_host(
    cli: TunerOptions,
    tolerance: int | str,
    bench: str | None = None,
    least: int = DEFAULT_TIMING_TOLERANCE,
) -> tuple[int, dict | None, HostSaid]:
    """On the composed real-time bench (``bench``: the one asked for, default
    ``--bench``), the host's check before the first experiment (``host.check_before_run``).
    Returns the tolerance to run with, the check's record (None: not a real-time bench)
    and its line, said by the session once its bench is up. ``least``: the tolerance
    ``auto`` never goes below (a resumed run's)."""
    if (bench or cli.bench_asked) != 'realtime':
        return (least if tolerance == host.AUTO else int(tolerance)), None, None
    chosen, record, line = host.check_before_run(
        tolerance, least, rt.RtOptions.from_cli(cli, rt.DEFAULT_PRIORITY)
    )
    return chosen, record, (None if line is None else (line, not record['auto']))


@dataclass
class PreparedSession:
    """A session whose every check passed (new or resumed), nothing created yet: the
    run's settings, its tuner parameters, the checked ``--drive`` (None: the simulator
    or the example), the progress printer; a resumed run's directory (locked) and its
    TuningRun restored with ``n_restored`` records (None for a new run, made once its
    bench is decided); ``out``: a new run's directory to create."""

    run: RunConfig
    params: TunerParams
    drive: DriveChoice | None
    progress: Any
    rundir: RunDir | None = None
    tuning: TuningRun | None = None
    n_restored: int = 0
    out: Path | None = None
    host_said: HostSaid = None  #: the host check's line (_check_host)


def prepare_run(cli: TunerOptions, argv: list[str]) -> PreparedSession:
    """Check everything of this session before anything is created (UsageError): a new
    run's options (:func:`_new_run_config`), or a resumed run's run.yaml, checkpoint and
    records (``--resume``, which takes the run's settings from run.yaml only)."""
    from .progress import Progress

    if cli.resume is None:
        return _new_run_config(cli, argv)
    if timing_tolerance(cli, argv) is not None:
        cli.timing_tolerance = True  # (given: refused below, with the other settings)
    given = [k for k in RUN_SETTINGS if getattr(cli, k) not in (None, False)]
    given += ['opt'] if cli.opt else []
    if cli.out is not None:
        given.append('out')
    if given:
        raise UsageError(
            "--resume takes the run's settings from RUN_DIR/run.yaml; do not "
            'also give ' + ', '.join('--' + g.replace('_', '-') for g in given)
        )
    from .rundir import RunDirError

    with _usage(RunDirError, TunerParamsError, prefix='--resume: '):
        rundir = RunDir.open(cli.resume)
        rundir.lock()  # one tuner per run, from here to the end of the process
        run = rundir.read_config()
        summary = rundir.read_summary()  # one of a newer tuner's format: refused
        _check_run(run, str(rundir.path / 'run.yaml'))
        box = {n: {k: v[k] for k in ('lo', 'hi', 'start')} for n, v in run.search_box.items()}
        params = parse_params(
            {'search_box': box, 'satisfactory_loss': run.satisfactory_loss},
            f'run.yaml ({run.params_file})',
        )
    if summary is not None and summary.outcome == 'done':
        a = summary.applied or {}
        applied = (
            'the start gains applied'
            if a.get('source') == 'reference'
            else f'the gains of {evaluation_name(a["eval"])} applied'
            if isinstance(a.get('eval'), int)
            else 'its gains applied'
        )
        raise RunFinished(
            f'{rundir.path}: the run is finished ({summary.evaluations} of {run.budget} '
            f'evaluations, {applied}): nothing to resume; '
            f'its plots: ros2 run im_tuner report {rundir.path}'
        )
    _check_controller_name(cli.controller)
    # everything of the run is checked before anything starts (a refusal changes
    # nothing; the torn tail of results.jsonl is cut only once the run goes on)
    from .tuning import ResumeError

    assert run.budget is not None  # (checked)
    progress = Progress(run.algo, run.budget, cli.quiet)
    try:
        tuning = make_tuning(rundir, run, params, progress)
        n_restored = tuning.restore()
    except (OptimizerError, ValueError, TypeError) as exc:
        raise UsageError(f'--resume: {rundir.path}/run.yaml: {exc}') from None
    except ResumeError as exc:
        raise UsageError(f'--resume: {exc}') from None
    drive = None
    if (run.drive or 'sim') != 'sim':
        from .bench import drive_spec

        # the run's drive: checked (and a hardware class built) as for a new run
        with _usage(drive_spec.DriveSpecError, prefix='--resume: '):
            drive = drive_spec.resolve(str(run.drive), run.drive_config)
    said = _check_resumed_host(cli, run)
    return PreparedSession(run, params, drive, progress, rundir, tuning, n_restored, None, said)


class RunFinished(Exception):
    """``--resume`` of a run that finished: nothing to do, nothing created (exit 0)."""


def _check_resumed_host(cli: TunerOptions, run: RunConfig) -> HostSaid:
    """A resumed run's check of its host (at the run's tolerance; recorded with its loop
    in ``run.host_check``): a run begun with ``--timing-tolerance auto`` goes on with it,
    from its tolerance up (``run``'s tolerance raised when the host now needs more)."""
    auto = bool((run.host_check or {}).get('auto'))
    tol = int(run.timing_tolerance or 0)  # (checked: an integer >= 0)
    tolerance, run.host_check, said = _check_host(
        cli, host.AUTO if auto else tol, run.bench_requested, tol
    )
    if auto:
        run.put(timing_tolerance=tolerance)
    return said


def _ripple_limit(cli: TunerOptions, algo: str) -> float | None:
    """The run's standstill-ripple limit (None: off): ``--ripple-limit``, else the
    algorithm's default (``runlog.ripple.default_ripple_limit``); off without a reference
    experiment (the start's ripple is what it is a ratio to), refused if given then."""
    from .runlog.ripple import default_ripple_limit, parse_ripple_limit

    if cli.ripple_limit is None:
        return None if cli.no_reference else default_ripple_limit(algo)
    with _usage(ValueError):
        limit = parse_ripple_limit(cli.ripple_limit)
    if limit is not None and cli.no_reference:
        raise UsageError(
            f"--ripple-limit {cli.ripple_limit} is a ratio to the start's ripple, which the "
            'reference experiment measures: not with --no-reference'
        )
    return limit


def _first_point(cli: TunerOptions, first: str | None, params: TunerParams) -> Any:
    """safe's ``first`` policy as run.yaml keeps it, from ``--opt first`` (None: not given,
    'identify' where the tuner knows the drive, else 'none'): 'identify' (the point comes
    after the start's two measurements, from the drive they identify:
    ``im_tuner.first_step``), the point of the drive file's nominal model computed now
    ('model', ``im_tuner.prior``; 'none' when it finds nothing better than the start), or
    'none'; None: ``--bench auto`` decides once the bench is (:func:`first_on_bench`).
    A resumed run continues with it."""
    from .benches import is_simulated

    bench = cli.bench_asked
    known = cli.drive_config is not None or (bench != 'auto' and is_simulated(bench, cli.drive))
    if first is None and not known and bench == 'auto' and not cli.no_reference:
        return None
    # (identify needs the reference experiment: without it, the default is none)
    first = first or ('identify' if known and not cli.no_reference else 'none')
    if first != 'model':
        return first
    from .prior import model_prior

    prior = model_prior(*_drive_of(cli.drive_config, cli.model, params))
    return 'none' if prior is None else list(prior.u)


def first_on_bench(cli: TunerOptions, mode: str) -> str:
    """``--bench auto``'s first step once the bench is decided: 'identify' when the tuner
    started the simulated drive (it knows that drive), 'none' when it found a controller
    on the graph (it may drive another motor: the tuner knows it only from
    ``--drive-config``)."""
    from .benches import is_simulated

    return 'identify' if is_simulated(mode, cli.drive) else 'none'


def _optimizer_args(algo: str, options: dict[str, Any], params: TunerParams) -> dict[str, Any]:
    """``make_optimizer``'s start, first and options from run.yaml's ``options`` (the
    options given and the run's policies, ``optim.POLICIES``): the file's start point
    unless ``start: none``; safe's first step unless ``first: none``.  OptimizerError
    (one line) for a key ``algo`` does not take or a policy's value it does not declare."""
    specs = optim.option_specs(algo)
    unknown = [k for k in options if k not in specs]
    if unknown:
        raise OptimizerError(
            f'unknown option {unknown[0]!r} for {algo} (allowed: {", ".join(specs)})'
        )
    opts = dict(options)
    start = opts.pop('start', 'hand')
    first = opts.pop('first', 'none')
    if start != 'hand':
        check_options(algo, {'start': specs['start']}, {'start': start})
    if first not in ('none', None):  # (None: decided with the bench, first_on_bench)
        opts['first'] = first  # ('identify', or the model's point: the optimiser checks it)
    take = algo in optim.TAKES_START and start == 'hand'
    return {'start': params.space.start_u if take else None, **opts}


def _drive_of(drive_config: Any, model: str | None, params: TunerParams) -> tuple[Any, ...]:
    """The drive file (the packaged default without one; ``model``: its model overridden),
    the search space and the drive's own experiment (None: the default one)."""
    from im_drive_sim.drive_file import load_config

    from . import family

    drive = load_config(drive_config, overrides={'model': model} if model else None)
    setup = family.tuner_setup(drive_config)  # a packaged drive's own experiment
    return drive, params.space, None if setup is None else setup.experiment


def _first_step_hook(run: RunConfig, params: TunerParams, progress: Progress | None = None) -> Any:
    """The run's ``IdentifiedFirstStep`` (safe with first: identify), else None: the
    drive file it names (the packaged default without one) and its experiment."""
    if (run.options or {}).get('first') != 'identify':
        return None
    from .first_step import IdentifiedFirstStep

    return IdentifiedFirstStep(
        *_drive_of(run.drive_config, run.model, params),
        None if progress is None else progress.note,
        run.ripple_limit,  # (the first step within the limit the run applies)
    )


def _check_controller_name(name: str) -> None:
    """The controller's node name must make valid ROS names for its services and topics."""
    from rclpy.exceptions import InvalidServiceNameException, InvalidTopicNameException
    from rclpy.validate_full_topic_name import validate_full_topic_name

    try:
        for topic in controller_topics(name).values():
            validate_full_topic_name(topic)
    except (InvalidTopicNameException, InvalidServiceNameException) as exc:
        raise UsageError(
            f'--controller {name!r}: not a valid node name ({str(exc).splitlines()[0]})'
        ) from None


def _check_run(run: RunConfig, where: str) -> None:
    """run.yaml of a run to resume: the settings the tuner reads, with their types."""

    def bad(key: str, what: str) -> UsageError:
        return UsageError(f'{where}: {key} must be {what}, got {getattr(run, key)!r}')

    if run.algo not in optim.ALGOS:
        raise bad('algo', 'one of ' + ', '.join(optim.ALGOS))
    for key in ('budget', 'seed', 'drive_seed', 'remeasure', 'retries', 'timing_tolerance'):
        v, least = getattr(run, key), 1 if key == 'budget' else 0
        if not isinstance(v, int) or isinstance(v, bool) or v < least:
            raise bad(key, f'an integer >= {least}')
    if not isinstance(run.options, dict):
        raise bad('options', 'a mapping of algorithm options')
    if not isinstance(run.reference, bool):
        raise bad('reference', 'true or false')
    if not isinstance(run.search_box, dict):
        raise bad('search_box', 'a mapping (the search box)')
    rl = run.ripple_limit
    if rl is not None and not (
        isinstance(rl, (int, float)) and not isinstance(rl, bool) and 1.0 <= rl < math.inf
    ):
        raise bad('ripple_limit', 'a ratio >= 1 or null (off)')


def make_tuning(
    rundir: RunDir, run: RunConfig, params: TunerParams, progress: Progress | None
) -> TuningRun:
    """The TuningRun of a checked run configuration (a new run's, or run.yaml's)."""
    from .tuning import TuningRun, run_seeds

    assert run.seed is not None and run.budget is not None  # (checked)
    opt_ss, _ = run_seeds(run.seed)
    opt = optim.make_optimizer(
        run.algo, params.space.dim, opt_ss, **_optimizer_args(run.algo, run.options or {}, params)
    )
    tuning = TuningRun(
        rundir,
        params.space,
        opt,
        budget=run.budget,
        satisfactory_loss=params.satisfactory_loss,
        remeasure=run.remeasure,
        retries=run.retries,
        reference=run.reference,
        progress=progress,
        first_step=_first_step_hook(run, params, progress),
        ripple_limit=run.ripple_limit,  # (None: off)
    )
    tuning.timing_tolerance = run.timing_tolerance
    tuning.rated_isq_a = _rated_isq(run)
    return tuning


def _rated_isq(run: RunConfig) -> float | None:
    """The rated torque's q current [A] of the drive the tuner knows (``--drive-config``,
    or the simulated bench's drive file), for the summary's ripple in % of it; None when
    the controller found may drive another motor."""
    from .benches import is_simulated

    if run.drive_config is None and not is_simulated(run.bench, run.drive):
        return None
    from im_drive_sim.drive_file import load_config
    from im_drive_sim.params import ConfigError

    try:
        m = load_config(run.drive_config).machine
    except ConfigError:
        return None
    return m.rated_torque / m.Kt if m.Kt > 0 else None
