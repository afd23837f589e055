"""The study's runs: one run (the tuner's TuningRun on the offline bench), the process
pool and the Dask cluster.  The grid and the spec are in ``spec``, the results and their
files in ``results``.  See the package docstring for what a study is.

This module imports the optimisers and the numba kernels (seconds): the command imports
it only once its options are checked.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import multiprocessing
import multiprocessing.forkserver
import os
import signal
import socket
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from itertools import islice
from typing import Any

import numpy as np

from im_controller.config import GAIN_NAMES, ExperimentConfig, Gains
from im_drive_sim import numeric
from im_drive_sim.params import DriveConfig

from .. import optim
from ..identify import FIGURES
from ..offline import OfflineBench
from ..runlog import Evaluation, MemoryRecord, Record, Reference, Remeasurement
from ..runlog.ripple import ripple_summary
from ..space import SearchSpace, TunerParams
from ..tuning import DEFAULT_RETRIES, TuningRun, run_seeds
from .bobyqa import BobyqaRun
from .results import StudyResult, empty_runs
from .spec import REF_EXPERIMENTS, Cell, StudySpec, default_jobs
from .worker import WORKER, init_pool_worker, init_worker


def run_seed(seed: int, r: int) -> int:
    """The tuner ``--seed`` of run ``r`` (0-based) of a study with seed ``seed``."""
    ss = np.random.SeedSequence(seed, spawn_key=(r,))
    return int(ss.generate_state(1)[0]) >> 1


def start_point(kind: str, rseed: int, space: SearchSpace) -> tuple[float, ...]:
    """Start gains of a run: ``'random'`` a uniform random point of the box (third stream
    of the run seed), otherwise the parameter file's (hand-tuned) start: the reference
    experiment measures it whatever the optimiser starts from.  In gains, so that a tuner
    parameter file with these starts reproduces the run exactly."""
    if kind != 'random':
        return tuple(space.start)
    u = np.random.default_rng(np.random.SeedSequence(rseed, spawn_key=(2,))).random(space.dim)
    return space.to_gains(u).as_tuple()


@dataclass
class RunResult:
    """One run (``budget`` evaluations) of one cell.  Losses are raw (not normalised)."""

    cell: int
    run: int
    run_seed: int
    drive_seed: int
    start: tuple[float, ...]  #: start gains (the reference experiment's)
    ref_loss: float  #: the reference experiment's loss (penalised if aborted)
    ref_aborted: bool
    losses: np.ndarray  #: float64[budget], penalised when aborted
    aborted: np.ndarray  #: bool[budget]
    faults: np.ndarray  #: bool[budget] (safety faults, reset as the tuner does)
    iteration: np.ndarray  #: int32[budget]: SPSA iteration / GA generation (1-based)
    best_eval: int  #: smallest non-aborted loss (-1: none)
    best_gains: tuple[float, ...]
    #: the best's re-measured loss (nan: not re-measured); with a ripple limit, that of
    #: the gains the run leaves applied (:func:`applied_loss`: the reference's loss when
    #: the start stays applied)
    remeasured: float
    opt_s: float  #: wall time in ask + tell [s] (timing, not results)
    exp_s: float  #: wall time in experiments [s]
    #: standstill rms of isq* [A] after the move, after the load: the start's, then the
    #: final choice's (the gains the tuner would leave applied); nan: not measured
    ripple: tuple[float, float, float, float] = (math.nan,) * 4
    #: whether the ripple limit kept out a point the run would otherwise have re-measured
    ripple_changed: bool = False
    #: as ``ripple``, peak to peak [A]
    ripple_pp: tuple[float, float, float, float] = (math.nan,) * 4
    #: the drive identified from the start's experiments (``identify.FIGURES``); nan: the
    #: cell does not identify it
    identified: tuple[float, ...] = (math.nan,) * 8


def prepare_run(
    spec: StudySpec, cell_index: int, r: int, params: TunerParams
) -> tuple[SearchSpace, optim.Optimizer, int]:
    """Run ``r`` of cell ``cell_index`` before it starts: its search space (the run's
    start point), its optimiser (seeded from the run seed) and its drive's noise seed."""
    cell = spec.cells[cell_index]
    rseed = run_seed(spec.seed, r)
    opt_ss, drive_seed = run_seeds(rseed)
    kind = cell.start_kind
    space = dataclasses.replace(params.space, start=start_point(kind, rseed, params.space))
    opt: Any
    if cell.algo == 'bobyqa':  # the outside reference row (not a tuner algorithm)
        opt = BobyqaRun(space.dim, opt_ss, space.start_u, spec.budget, **cell.opts)
    else:
        first: Any = None
        if cell.first == 'model':
            # the told drive's file is the model (the tuner's --opt first=model), whatever the
            # plant the run measures on (spec.plant, spec.mismatch)
            from ..prior import model_prior

            setup = spec.setup()
            prior = model_prior(setup.drive, space, setup.experiment)
            first = None if prior is None else prior.u
        elif cell.first == 'identify':  # a point after the start's two measurements
            first = 'identify'
        opt = optim.make_optimizer(
            cell.algo,
            space.dim,
            opt_ss,
            None if kind == 'none' else space.start_u,
            first=first,
            **cell.opts,
        )
    return space, opt, drive_seed


def first_step_of(
    spec: StudySpec, first: str, space: SearchSpace, ripple_limit: float | None = None
) -> Any:
    """The run's ``IdentifiedFirstStep`` for a cell with first 'identify' (the study's
    drive file is what the tuner is told; ``ripple_limit``: the cell's), else None."""
    if first != 'identify':
        return None
    from ..first_step import IdentifiedFirstStep

    setup = spec.setup()
    return IdentifiedFirstStep(setup.drive, space, setup.experiment, None, ripple_limit)


def run_one(
    spec: StudySpec,
    cell_index: int,
    r: int,
    drive: DriveConfig | None = None,
    params: TunerParams | None = None,
    experiment: ExperimentConfig | None = None,
) -> RunResult:
    """Run ``r`` of cell ``cell_index``: the tuner's own :class:`TuningRun` (reference,
    budget, best, re-measurement) on the offline bench of ``drive`` (None: the spec's
    plant), its records kept in memory."""
    cell = spec.cells[cell_index]
    drive = spec.plant_drive() if drive is None else drive
    params = spec.params() if params is None else params
    experiment = spec.experiment() if experiment is None else experiment
    space, opt, drive_seed = prepare_run(spec, cell_index, r, params)
    B = spec.budget
    iteration = np.empty(B, dtype=np.int32)
    # The paper's iteration each evaluation belongs to (Table III): the optimiser's,
    # 1-based, as it stood when the evaluation was asked (after the previous tell).
    nxt = [opt.iterations + 1]

    def progress(kind: str, rec: Record, _run: TuningRun) -> None:
        if kind == 'eval':
            iteration[rec.eval] = nxt[0]
            nxt[0] = opt.iterations + 1

    t0 = time.perf_counter()
    tuning = TuningRun(
        MemoryRecord(),
        space,
        opt,
        budget=B,
        satisfactory_loss=params.satisfactory_loss,
        remeasure=1 if spec.remeasure else 0,
        retries=DEFAULT_RETRIES,  # as the tuner: a fault in a settle is re-run
        reference=True,
        progress=progress,
        first_step=first_step_of(spec, cell.first, space, spec.limit_of(cell)),
        ripple_limit=spec.limit_of(cell),
    )
    bench = OfflineBench(drive, drive_seed, experiment)
    try:
        outcome = tuning.run(bench)
    finally:
        if isinstance(opt, BobyqaRun):
            opt.close()  # its solver thread
    wall = time.perf_counter() - t0
    if outcome != 'done':
        raise RuntimeError(f'study run {cell.label} #{r}: {outcome}')
    # the measured records: an attempt lost in its settle (a fault while the fallback
    # gains held, e.g. after an unstable candidate) was re-run, as the tuner does
    ref = next(x for x in tuning.records if isinstance(x, Reference))
    evals = [x for x in tuning.records if isinstance(x, Evaluation)]
    rem = [x for x in tuning.records if isinstance(x, Remeasurement)]
    best = tuning.state.best
    exp_s = sum(x.wall_s or 0.0 for x in tuning.records)  # every attempt's bench time
    final = tuning.final_choice()
    rip = ripple_summary(tuning.records, final, tuning.ripple_limit, 1) or {}
    limited = rip.get('bound') is not None
    again = None
    # applied gains with no loss for the column (the re-measured point failed the limit
    # on its mean, the next best within it is applied): one more experiment of them, a
    # fresh measurement of what is applied, not its least (picked) one
    if limited and rem and final is not None and math.isnan(applied_loss(final, ref, rem, True)):
        again = bench.measure(Gains(**final['gains'])).loss

    def ripple(d: dict[str, Any] | None, measure: str) -> tuple[float, float]:
        d = d or {}
        return tuple(  # type: ignore[return-value]
            math.nan if d.get(k) is None else float(d[k])
            for k in (f'{measure}_after_move', f'{measure}_after_load')
        )

    idf = None if tuning.first_step is None else tuning.first_step.identified(tuning.records)

    return RunResult(
        cell=cell_index,
        run=r,
        run_seed=run_seed(spec.seed, r),
        drive_seed=drive_seed,
        start=space.start,
        ref_loss=ref.loss,
        ref_aborted=ref.aborted,
        losses=np.array([x.loss for x in evals]),
        aborted=np.array([x.aborted for x in evals], dtype=bool),
        faults=np.array([x.fault for x in evals], dtype=bool),
        iteration=iteration,
        best_eval=-1 if best is None else int(best['eval']),
        best_gains=(
            tuple(math.nan for _ in GAIN_NAMES)
            if best is None
            else tuple(float(best['gains'][n]) for n in GAIN_NAMES)
        ),
        remeasured=applied_loss(final, ref, rem, limited, again),
        opt_s=wall - exp_s,
        exp_s=exp_s,
        ripple=(*ripple(rip.get('start'), 'rms'), *ripple(rip.get('applied'), 'rms')),
        ripple_changed=bool(rip.get('changed')),
        ripple_pp=(*ripple(rip.get('start'), 'pp'), *ripple(rip.get('applied'), 'pp')),
        identified=(
            tuple(math.nan for _ in FIGURES)
            if idf is None
            else tuple(float(getattr(idf, f)) for f in FIGURES)
        ),
    )


def applied_loss(
    final: dict[str, Any] | None,
    ref: Reference,
    rem: list[Remeasurement],
    limited: bool,
    again: float | None = None,
) -> float:
    """The study's ``re-measured`` figure of a run: the best's re-measurement (nan: none);
    with a ripple limit (``limited``), the loss of the gains the run leaves applied
    (``final``: ``TuningRun.final_choice()``) when they are not the re-measured point:
    the reference's when the start stays, else their re-measurement, or ``again``, one
    more experiment of them (:func:`run_one`: their loss from the search is the least of
    many, biased low); nan without it."""
    if rem and (not limited or final is None or final['eval'] == rem[0].eval):
        return rem[0].loss
    if not limited or final is None:
        return math.nan
    if final['eval'] < 0:
        return ref.loss
    same = [x.loss for x in rem if x.eval == final['eval']]
    if same:
        return same[0]
    return math.nan if again is None else again


def reference_loss(
    drive: DriveConfig,
    experiments: int = REF_EXPERIMENTS,
    experiment: ExperimentConfig | None = None,
    start: Gains | None = None,
) -> tuple[float, float, float]:
    """L_ref: (mean, standard error of the mean) of the hand-tuned start's loss (``start``;
    None: the default gains) over ``experiments`` consecutive experiments after the first
    from rest (drive file seed), and that first one's loss.  Deterministic for a drive
    file and model."""
    bench = OfflineBench(drive, drive.seed, experiment)
    g = Gains() if start is None else start
    first = bench.measure(g).loss
    x = np.array([bench.measure(g).loss for _ in range(experiments)])
    return float(x.mean()), float(x.std(ddof=1) / math.sqrt(len(x))), float(first)


# -- the pool ---------------------------------------------------------------------------------
#: How long the study waits for its terminated workers to end [s].
_END_GRACE_S = 5.0


def _kill_starting_workers() -> None:
    """SIGKILL every child of the forkserver (Linux ``/proc``; nothing elsewhere): a worker
    still starting when the signal lands is not in the executor's table yet, and would
    otherwise start after the study ended and print a traceback.  A child of the
    forkserver can only be a worker of this study's pools, whose results are no longer
    wanted."""
    server = getattr(multiprocessing.forkserver, '_forkserver', None)
    fs_pid = getattr(server, '_forkserver_pid', None)
    if not fs_pid:
        return
    try:
        entries = os.listdir('/proc')
    except OSError:
        return
    for d in entries:
        if not d.isdigit():
            continue
        try:
            with open(f'/proc/{d}/stat') as f:
                stat = f.read()
        except OSError:
            continue
        if int(stat.rsplit(')', 1)[1].split()[1]) == fs_pid:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(int(d), signal.SIGKILL)


def _end_pool(pool: ProcessPoolExecutor) -> None:
    """Stop the pool now: pending runs cancelled, running ones killed (their results are
    not wanted: the study is being interrupted or failed)."""
    terminate = getattr(pool, 'terminate_workers', None)  # Python >= 3.14
    if terminate is not None:
        terminate()
        _kill_starting_workers()
        return
    # before 3.14: the executor's own table of its worker processes (killed first: the
    # manager thread then finds the pool broken and ends); shutdown() forgets both
    procs = list((getattr(pool, '_processes', None) or {}).values())
    manager = getattr(pool, '_executor_manager_thread', None)
    for p in procs:
        p.terminate()
    _kill_starting_workers()
    pool.shutdown(wait=False, cancel_futures=True)
    deadline = time.monotonic() + _END_GRACE_S
    for p in procs:
        p.join(max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            p.kill()
    # Wait for the executor's manager thread to see the broken pool and close its wakeup
    # pipe.  Otherwise the interpreter's exit hook (concurrent.futures' _python_exit, which
    # takes no lock) can pass the pipe's "not closed" check just before the manager closes
    # it and print an OSError traceback (EBADF) after the study's one line (CPython < 3.14).
    if manager is not None:
        manager.join(max(0.0, deadline - time.monotonic()) + 1.0)


class NumericMismatch(RuntimeError):
    """A worker runs on another numeric baseline than the study (one line: which, and how
    to start it on the study's)."""


def check_numeric(expected: dict[str, Any] | None) -> None:
    """Refuse to run in a worker whose numeric baseline (:mod:`im_drive_sim.numeric`)
    would give other bits than the study's process: its runs would make the tables depend
    on which worker ran which run.  Checked once per worker process."""
    if expected is None:
        return
    if 'numeric' not in WORKER:
        WORKER['numeric'] = numeric.status()
    differs = numeric.differs(expected, WORKER['numeric'])
    if differs:
        where = f'worker {socket.gethostname()} pid {os.getpid()}'
        raise NumericMismatch(
            f'{where}: {differs.replace("the run", "the study")}; start it with '
            '`env $(python -m im_drive_sim.numeric_main --env) dask worker ...`'
        )


def run_task(spec: StudySpec, c: int, r: int, expected: dict[str, Any] | None = None) -> RunResult:
    """Run ``r`` of cell ``c`` in a worker (of the local pool or a Dask cluster): the drive
    and parameter files are loaded once per worker process and spec (thread-safe: a Dask
    worker may run several tasks at once); refused where the worker's numeric baseline
    differs from ``expected`` (the study's)."""
    check_numeric(expected)
    drive, params, experiment = init_worker(spec)
    return run_one(spec, c, r, drive, params, experiment)


def _run_on_cluster(
    address: str,
    spec: StudySpec,
    tasks: list[tuple[int, int]],
    store: Callable[[RunResult], None],
    timeout: float = 30.0,
    expected: dict[str, Any] | None = None,
) -> int:
    """Every task on the Dask cluster whose scheduler is at ``address`` (``tcp://HOST:PORT``);
    ``store`` gets each result as it completes.  Returns the workers' thread count.

    Runs are independent and seeded by their index, so the results do not depend on
    which worker ran what (the same tables as the local pool, byte for byte)."""
    from distributed import Client, as_completed

    with Client(address, timeout=f'{timeout}s') as client:
        nthreads = sum(client.nthreads().values())
        futures = [
            client.submit(
                run_task,
                spec,
                c,
                r,
                expected,
                key=f'im_tuner-study-{spec.seed}-{c}-{r}',
                pure=False,
            )
            for c, r in tasks
        ]
        for fut in as_completed(futures):
            store(fut.result())
            fut.release()
    return nthreads


def _allocate(spec: StudySpec, cells: list[Cell]) -> dict[str, Any]:
    C, R, B, D = len(cells), spec.runs, spec.budget, len(GAIN_NAMES)
    return {
        'run_seed': np.array([run_seed(spec.seed, r) for r in range(R)], dtype=np.int64),
        'drive_seed': np.array(
            [run_seeds(run_seed(spec.seed, r))[1] for r in range(R)], dtype=np.int64
        ),
        **empty_runs(C, R, B, D),
    }


#: RunResult fields stored at [cell, run] of the StudyResult arrays.
_PER_RUN = tuple(a for a in StudyResult.ARRAYS if a not in ('run_seed', 'drive_seed'))


def run_study(
    spec: StudySpec,
    jobs: int | None = None,
    progress: Callable[[int, int, float], None] | None = None,
    cluster: str | None = None,
    cluster_timeout: float = 30.0,
) -> StudyResult:
    """Run the whole grid on ``jobs`` processes (None: every core; 1: in this process), or
    on the Dask cluster whose scheduler is at ``cluster`` (``tcp://HOST:PORT``; the
    command checks it first, ``cluster.wait_for_scheduler``: Dask's client bounds only
    the TCP connection by ``cluster_timeout`` s).

    ``progress(done_runs, total_runs, elapsed_s)`` is called after every run.  The result
    does not depend on ``jobs`` or the cluster (runs are independent and seeded by their
    index).
    """
    jobs = default_jobs() if jobs is None else int(jobs)
    if jobs < 1:
        raise ValueError(f'jobs must be >= 1, got {jobs}')
    cells = spec.cells
    drive, params, experiment = spec.loaded()  # drive: the plant
    expected = numeric.status()  # every worker must agree (check_numeric)
    t0 = time.perf_counter()
    # L_ref first: it also loads (or compiles and caches) the kernels before workers start,
    # so they do not all compile at once.  Per drive: its own hand-tuned start, measured on
    # the plant (study.plant says why); beside it, on the told drive when that is another.
    start = Gains(*params.space.start) if spec.drives else None
    l_ref, l_sem, l_first = reference_loss(drive, experiment=experiment, start=start)
    l_ref_told = None
    if spec.split:
        l_ref_told = reference_loss(spec.drive(), experiment=experiment, start=start)[0]
    arrays = _allocate(spec, cells)
    # run-major order: early progress covers every cell
    tasks = [(c, r) for r in range(spec.runs) for c in range(len(cells))]
    total, done = len(tasks), [0]

    def store(res: RunResult) -> None:
        for name in _PER_RUN:
            arrays[name][res.cell, res.run] = getattr(res, name)
        done[0] += 1
        if progress is not None:
            progress(done[0], total, time.perf_counter() - t0)

    if cluster is not None:
        jobs = _run_on_cluster(cluster, spec, tasks, store, cluster_timeout, expected)
    elif jobs == 1:
        for c, r in tasks:
            store(run_one(spec, c, r, drive, params, experiment))
    else:
        # forkserver: workers start from a clean interpreter (no inherited threads or ROS)
        ctx = multiprocessing.get_context('forkserver')
        pool = ProcessPoolExecutor(
            max_workers=jobs,
            mp_context=ctx,
            initializer=init_pool_worker,
            initargs=(spec, os.getpid()),
        )
        try:
            # a bounded window of pending tasks keeps memory flat and progress honest
            it = iter(tasks)
            pending = {pool.submit(run_task, spec, *t, expected) for t in islice(it, 4 * jobs)}
            while pending:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in finished:
                    store(f.result())
                more = islice(it, len(finished))
                pending |= {pool.submit(run_task, spec, *t, expected) for t in more}
        except BaseException:  # Ctrl-C, SIGTERM (the command raises), a failed run
            _end_pool(pool)
            raise
        pool.shutdown(wait=True)
    return StudyResult(
        spec=spec,
        cells=cells,
        l_ref=l_ref,
        l_ref_sem=l_sem,
        l_first=l_first,
        wall_s=time.perf_counter() - t0,
        jobs=jobs,
        numeric=expected,
        l_ref_told=l_ref_told,
        **arrays,
    )
