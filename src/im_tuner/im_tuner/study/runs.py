"""The study's runs: the grid, one run (the tuner's TuningRun on the offline bench), the
process pool, and the results saved and loaded (study.npz, study.json). See the package
docstring for what a study is."""

from __future__ import annotations

import dataclasses
import json
import math
import multiprocessing
import os
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from im_controller.config import GAIN_NAMES, Gains
from im_drive_sim.params import DriveConfig, load_config

from .. import optim
from ..bench.offline import OfflineBench
from ..space import SearchSpace, TunerParams, load_params
from ..tuning import MemoryRecord, TuningRun, run_seeds

__all__ = [
    'ARRAYS_FILE',
    'DEFAULT_SATISFACTORY',
    'DEFAULT_SEED',
    'FACTORS',
    'META_FILE',
    'PAPER_ALGOS',
    'REF_EXPERIMENTS',
    'STUDY_ALGOS',
    'Cell',
    'RunResult',
    'StudyResult',
    'StudySpec',
    'default_jobs',
    'grid',
    'load',
    'reference_loss',
    'run_one',
    'run_seed',
    'run_study',
    'save',
    'start_point',
]

#: The paper's two algorithms: Tables I-III and the paper's conclusions.
PAPER_ALGOS: tuple[str, ...] = ('spsa', 'necga')
#: Algorithms the study has a grid for: every tuner algorithm.
STUDY_ALGOS: tuple[str, ...] = optim.ALGOS
#: Start of a run when its cell does not say: SPSA a random point (as the paper), every
#: other algorithm that takes a start the hand-tuned gains (what a real bench has).
RANDOM_START_DEFAULT: frozenset[str] = frozenset({'spsa'})
#: The grid factors around the paper's configuration (x/5, x, 5x).
FACTORS: tuple[tuple[str, float], ...] = (('/5', 0.2), ('', 1.0), ('*5', 5.0))
#: Experiments of the hand-tuned start that define L_ref.
REF_EXPERIMENTS = 100
DEFAULT_SATISFACTORY = 0.9
DEFAULT_SEED = 2005  # the paper's year: a fixed, documented default


#: The small grids of the algorithms beyond the paper: (label, options); the option
#: 'start' ('random' or 'hand') is the run's start, not an optimiser option.
EXTRA_GRIDS: dict[str, tuple[tuple[str, tuple[tuple[str, Any], ...]], ...]] = {
    'rcga': (
        ('sigma0=10', (('sigma0', 10.0),)),
        ('sigma0=1', (('sigma0', 1.0),)),
        ('sigma0=0.3', (('sigma0', 0.3),)),
    ),
    'cmaes': (
        ('sigma0=0.3 random start', (('sigma0', 0.3), ('start', 'random'))),
        ('sigma0=0.1', (('sigma0', 0.1),)),
        ('sigma0=0.03', (('sigma0', 0.03),)),
    ),
    'safe': (
        ('no model (a plain 1+1-ES)', (('model_every', 0),)),
        ('no trust region (sigma_max=0.5)', (('sigma_max', 0.5),)),
        ('defaults', ()),
    ),
    'tpe': (
        ('defaults, no start', (('start', 'none'),)),
        ('defaults', ()),
        ('n_startup_trials=5', (('n_startup_trials', 5),)),
    ),
}


@dataclass(frozen=True)
class Cell:
    """One configuration of the grid: a cell of the paper's tables.

    ``label`` is the paper's notation ('a=0.0183/5 c=0.03', 'n=25*5 eta=62');
    ``row``/``col`` the cell's place in the paper's table; ``options`` the optimiser
    options (exact floats: a0/5 is what the tuner gets from ``--a`` with repr).
    """

    algo: str
    label: str
    row: int
    col: int
    options: tuple[tuple[str, Any], ...]

    @property
    def opts(self) -> dict[str, Any]:
        """The optimiser's options (without the run's start kind)."""
        return {k: v for k, v in self.options if k != 'start'}

    @property
    def start_kind(self) -> str:
        """'random' (a uniform point, third stream of the run seed), 'hand' (the parameter
        file's start) or 'none' (the optimiser's own, without a start point)."""
        kind = dict(self.options).get('start')
        if kind is not None:
            return str(kind)
        if self.algo not in optim.TAKES_START:
            return 'none'
        return 'random' if self.algo in RANDOM_START_DEFAULT else 'hand'


def grid(algos: tuple[str, ...] = PAPER_ALGOS) -> list[Cell]:
    """The paper's grid, SPSA cells row-major (a down, c across), then neCGA (n across)."""
    cells: list[Cell] = []
    for algo in algos:
        if algo == 'spsa':
            a0 = optim.OPTIONS['spsa']['a'].default
            c0 = optim.OPTIONS['spsa']['c'].default
            for i, (sa, fa) in enumerate(FACTORS):
                for j, (sc, fc) in enumerate(FACTORS):
                    cells.append(
                        Cell(
                            'spsa',
                            f'a={a0:g}{sa} c={c0:g}{sc}',
                            i,
                            j,
                            (('a', a0 * fa), ('c', c0 * fc)),
                        )
                    )
        elif algo in ('necga', 'cga', 'pecga'):
            n0 = optim.OPTIONS[algo]['n'].default
            for j, (sn, fn) in enumerate(FACTORS):
                n = round(n0 * fn)
                if algo == 'necga':
                    cells.append(
                        Cell(algo, f'n={n0}{sn} eta={n // 2}', 0, j, (('n', n), ('eta', n // 2)))
                    )
                else:
                    cells.append(Cell(algo, f'n={n0}{sn}', 0, j, (('n', n),)))
        else:
            for j, (label, opts) in enumerate(EXTRA_GRIDS[algo]):
                cells.append(Cell(algo, label, 0, j, opts))
    return cells


@dataclass(frozen=True)
class StudySpec:
    """What a study computes; equal specs give bit-identical results."""

    runs: int = 100
    budget: int = 200
    algos: tuple[str, ...] = PAPER_ALGOS
    model: str = 'full'
    seed: int = DEFAULT_SEED
    satisfactory: float = DEFAULT_SATISFACTORY
    remeasure: bool = True
    drive_config: str | None = None  #: drive parameter file (None: packaged)
    params_file: str | None = None  #: tuner parameter file (None: packaged)

    def __post_init__(self) -> None:
        for name, lo in (('runs', 1), ('budget', 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f'{name} must be an integer >= {lo}, got {v!r}')
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f'seed must be an integer >= 0, got {self.seed!r}')
        if self.model not in ('full', 'reduced'):
            raise ValueError(f"model must be 'full' or 'reduced', got {self.model!r}")
        if not (
            isinstance(self.satisfactory, float)
            and self.satisfactory > 0.0
            and math.isfinite(self.satisfactory)
        ):
            raise ValueError(
                f'satisfactory must be a normalised loss > 0, got {self.satisfactory!r}'
            )
        if not self.algos or len(set(self.algos)) != len(self.algos):
            raise ValueError(f'algos must be distinct names, got {self.algos!r}')
        grid(self.algos)  # raises on an unknown algo

    @property
    def cells(self) -> list[Cell]:
        return grid(self.algos)

    def drive(self) -> DriveConfig:
        return load_config(self.drive_config, overrides={'model': self.model})

    def params(self) -> TunerParams:
        return load_params(self.params_file)


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
    remeasured: float  #: the best's re-measured loss (nan: not re-measured)
    opt_s: float  #: wall time in ask + tell [s] (timing, not results)
    exp_s: float  #: wall time in experiments [s]


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
    opt = optim.make_optimizer(
        cell.algo, space.dim, opt_ss, None if kind == 'none' else space.start_u, **cell.opts
    )
    return space, opt, drive_seed


def run_one(
    spec: StudySpec,
    cell_index: int,
    r: int,
    drive: DriveConfig | None = None,
    params: TunerParams | None = None,
) -> RunResult:
    """Run ``r`` of cell ``cell_index``: the tuner's own :class:`TuningRun` (reference,
    budget, best, re-measurement) on the offline bench, its records kept in memory."""
    cell = spec.cells[cell_index]
    drive = spec.drive() if drive is None else drive
    params = spec.params() if params is None else params
    space, opt, drive_seed = prepare_run(spec, cell_index, r, params)
    B = spec.budget
    iteration = np.empty(B, dtype=np.int32)
    # The paper's iteration each evaluation belongs to (Table III): the optimiser's,
    # 1-based, as it stood when the evaluation was asked (after the previous tell).
    nxt = [opt.iterations + 1]

    def progress(kind: str, rec: dict[str, Any], _run: TuningRun) -> None:
        if kind == 'eval':
            iteration[rec['eval']] = nxt[0]
            nxt[0] = opt.iterations + 1

    t0 = time.perf_counter()
    tuning = TuningRun(
        MemoryRecord(),
        space,
        opt,
        budget=B,
        satisfactory_loss=params.satisfactory_loss,
        remeasure=1 if spec.remeasure else 0,
        retries=0,
        reference=True,
        progress=progress,
    )
    outcome = tuning.run(OfflineBench(drive, drive_seed))
    wall = time.perf_counter() - t0
    if outcome != 'done':
        raise RuntimeError(f'study run {cell.label} #{r}: {outcome}')
    recs = tuning.records
    ref = next(x for x in recs if x['kind'] == 'reference')
    evals = [x for x in recs if x['kind'] == 'eval']
    rem = [x for x in recs if x['kind'] == 'remeasure']
    best = tuning.state.best
    exp_s = sum(x['wall_s'] for x in recs)
    return RunResult(
        cell=cell_index,
        run=r,
        run_seed=run_seed(spec.seed, r),
        drive_seed=drive_seed,
        start=space.start,
        ref_loss=ref['loss'],
        ref_aborted=ref['aborted'],
        losses=np.array([x['loss'] for x in evals]),
        aborted=np.array([x['aborted'] for x in evals], dtype=bool),
        faults=np.array([x['fault'] for x in evals], dtype=bool),
        iteration=iteration,
        best_eval=-1 if best is None else int(best['eval']),
        best_gains=(
            tuple(math.nan for _ in GAIN_NAMES)
            if best is None
            else tuple(float(best['gains'][n]) for n in GAIN_NAMES)
        ),
        remeasured=rem[0]['loss'] if rem else math.nan,
        opt_s=wall - exp_s,
        exp_s=exp_s,
    )


def reference_loss(
    drive: DriveConfig, experiments: int = REF_EXPERIMENTS
) -> tuple[float, float, float]:
    """L_ref: (mean, standard error of the mean) of the hand-tuned start's loss over
    ``experiments`` consecutive experiments after the first from rest (drive file seed),
    and that first one's loss.  Deterministic for a drive file and model."""
    bench = OfflineBench(drive, drive.seed)
    g = Gains()
    first = bench.measure(g).loss
    x = np.array([bench.measure(g).loss for _ in range(experiments)])
    return float(x.mean()), float(x.std(ddof=1) / math.sqrt(len(x))), float(first)


# -- the pool ---------------------------------------------------------------------------------
_WORKER: dict[str, Any] = {}


def _init_worker(spec: StudySpec) -> None:
    _WORKER['spec'] = spec
    _WORKER['drive'] = spec.drive()
    _WORKER['params'] = spec.params()


def _work(task: tuple[int, int]) -> RunResult:
    return run_one(_WORKER['spec'], task[0], task[1], _WORKER['drive'], _WORKER['params'])


def run_task(spec: StudySpec, c: int, r: int) -> RunResult:
    """Run ``r`` of cell ``c`` in a worker of a Dask cluster: the drive and parameter
    files are loaded once per worker process and spec."""
    if _WORKER.get('spec') != spec:
        _init_worker(spec)
    return _work((c, r))


def _run_on_cluster(
    address: str,
    spec: StudySpec,
    tasks: list[tuple[int, int]],
    store: Callable[[RunResult], None],
) -> int:
    """Every task on the Dask cluster whose scheduler is at ``address`` (``tcp://HOST:PORT``);
    ``store`` gets each result as it completes.  Returns the workers' thread count.

    Runs are independent and seeded by their index, so the results do not depend on
    which worker ran what (the same tables as the local pool, byte for byte)."""
    from distributed import Client, as_completed

    with Client(address, timeout='30s') as client:
        nthreads = sum(client.nthreads().values())
        futures = [
            client.submit(
                run_task, spec, c, r, key=f'im_tuner-study-{spec.seed}-{c}-{r}', pure=False
            )
            for c, r in tasks
        ]
        for fut in as_completed(futures):
            store(fut.result())
            fut.release()
    return nthreads


@dataclass
class StudyResult:
    """All runs of a study, as arrays indexed [cell, run, (evaluation)]; raw losses."""

    spec: StudySpec
    cells: list[Cell]
    l_ref: float
    l_ref_sem: float
    l_first: float
    run_seed: np.ndarray  #: int64[runs]
    drive_seed: np.ndarray  #: int64[runs]
    start: np.ndarray  #: float64[cells, runs, 5]
    ref_loss: np.ndarray  #: float64[cells, runs]
    ref_aborted: np.ndarray  #: bool[cells, runs]
    losses: np.ndarray  #: float64[cells, runs, budget]
    aborted: np.ndarray  #: bool[cells, runs, budget]
    faults: np.ndarray  #: bool[cells, runs, budget]
    iteration: np.ndarray  #: int32[cells, runs, budget]
    best_eval: np.ndarray  #: int32[cells, runs]
    best_gains: np.ndarray  #: float64[cells, runs, 5]
    remeasured: np.ndarray  #: float64[cells, runs]
    opt_s: np.ndarray  #: float64[cells, runs] (timing)
    exp_s: np.ndarray  #: float64[cells, runs] (timing)
    wall_s: float = 0.0
    jobs: int = 1
    command: str = ''  #: the command that ran the study (for the write-up)

    @property
    def experiments(self) -> int:
        """Experiments run (reference + evaluations + re-measurements)."""
        return int(
            self.losses.size + self.ref_loss.size + np.count_nonzero(np.isfinite(self.remeasured))
        )

    # arrays saved by save()/load() (the rest goes into study.json)
    ARRAYS = (
        'run_seed',
        'drive_seed',
        'start',
        'ref_loss',
        'ref_aborted',
        'losses',
        'aborted',
        'faults',
        'iteration',
        'best_eval',
        'best_gains',
        'remeasured',
        'opt_s',
        'exp_s',
    )


def _allocate(spec: StudySpec, cells: list[Cell]) -> dict[str, Any]:
    C, R, B, D = len(cells), spec.runs, spec.budget, len(GAIN_NAMES)
    return {
        'run_seed': np.array([run_seed(spec.seed, r) for r in range(R)], dtype=np.int64),
        'drive_seed': np.array(
            [run_seeds(run_seed(spec.seed, r))[1] for r in range(R)], dtype=np.int64
        ),
        'start': np.full((C, R, D), np.nan),
        'ref_loss': np.full((C, R), np.nan),
        'ref_aborted': np.zeros((C, R), bool),
        'losses': np.full((C, R, B), np.nan),
        'aborted': np.zeros((C, R, B), bool),
        'faults': np.zeros((C, R, B), bool),
        'iteration': np.zeros((C, R, B), np.int32),
        'best_eval': np.full((C, R), -1, np.int32),
        'best_gains': np.full((C, R, D), np.nan),
        'remeasured': np.full((C, R), np.nan),
        'opt_s': np.zeros((C, R)),
        'exp_s': np.zeros((C, R)),
    }


#: RunResult fields stored at [cell, run] of the StudyResult arrays.
_PER_RUN = tuple(a for a in StudyResult.ARRAYS if a not in ('run_seed', 'drive_seed'))


def _store(a: dict[str, np.ndarray], res: RunResult) -> None:
    for name in _PER_RUN:
        a[name][res.cell, res.run] = getattr(res, name)


def default_jobs() -> int:
    """Every core this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def run_study(
    spec: StudySpec,
    jobs: int | None = None,
    progress: Callable[[int, int, float], None] | None = None,
    cluster: str | None = None,
) -> StudyResult:
    """Run the whole grid on ``jobs`` processes (None: every core; 1: in this process), or
    on the Dask cluster whose scheduler is at ``cluster`` (``tcp://HOST:PORT``).

    ``progress(done_runs, total_runs, elapsed_s)`` is called after every run.  The result
    does not depend on ``jobs`` or the cluster (runs are independent and seeded by their
    index).
    """
    jobs = default_jobs() if jobs is None else int(jobs)
    if jobs < 1:
        raise ValueError(f'jobs must be >= 1, got {jobs}')
    cells = spec.cells
    drive, params = spec.drive(), spec.params()
    t0 = time.perf_counter()
    # L_ref first: it also loads (or compiles and caches) the kernels before workers start,
    # so they do not all compile at once.
    l_ref, l_sem, l_first = reference_loss(drive)
    arrays = _allocate(spec, cells)
    # run-major order: early progress covers every cell
    tasks = [(c, r) for r in range(spec.runs) for c in range(len(cells))]
    total, done = len(tasks), [0]

    def store(res: RunResult) -> None:
        _store(arrays, res)
        done[0] += 1
        if progress is not None:
            progress(done[0], total, time.perf_counter() - t0)

    if cluster is not None:
        jobs = _run_on_cluster(cluster, spec, tasks, store)
    elif jobs == 1:
        for c, r in tasks:
            store(run_one(spec, c, r, drive, params))
    else:
        # forkserver: workers start from a clean interpreter (no inherited threads or ROS)
        ctx = multiprocessing.get_context('forkserver')
        with ProcessPoolExecutor(
            max_workers=jobs, mp_context=ctx, initializer=_init_worker, initargs=(spec,)
        ) as pool:
            # a bounded window of pending tasks keeps memory flat and progress honest
            it = iter(tasks)
            pending = {pool.submit(_work, t) for t in _take(it, 4 * jobs)}
            while pending:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in finished:
                    store(f.result())
                pending |= {pool.submit(_work, t) for t in _take(it, len(finished))}
    return StudyResult(
        spec=spec,
        cells=cells,
        l_ref=l_ref,
        l_ref_sem=l_sem,
        l_first=l_first,
        wall_s=time.perf_counter() - t0,
        jobs=jobs,
        **arrays,
    )


def _take(it, k: int) -> list:
    out = []
    for _ in range(k):
        try:
            out.append(next(it))
        except StopIteration:
            break
    return out


# -- files ------------------------------------------------------------------------------------
ARRAYS_FILE = 'study.npz'
META_FILE = 'study.json'


def save(res: StudyResult, out: Path | str) -> None:
    """Write ``study.npz`` (every array: nothing is lost) and ``study.json`` (the spec,
    L_ref, timing) into ``out`` (created)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / ARRAYS_FILE, **{k: getattr(res, k) for k in StudyResult.ARRAYS})
    meta = {
        'spec': dataclasses.asdict(res.spec),
        'cells': [dataclasses.asdict(c) for c in res.cells],
        'l_ref': res.l_ref,
        'l_ref_sem': res.l_ref_sem,
        'l_first': res.l_first,
        'ref_experiments': REF_EXPERIMENTS,
        'experiments': res.experiments,
        'wall_s': res.wall_s,
        'jobs': res.jobs,
        'command': res.command,
    }
    tmp = out / (META_FILE + '.tmp')
    tmp.write_text(json.dumps(meta, indent=1) + '\n')
    os.replace(tmp, out / META_FILE)


def load(out: Path | str) -> StudyResult:
    """Read a study written by :func:`save` (ValueError with the reason if it is not one)."""
    out = Path(out)
    try:
        meta = json.loads((out / META_FILE).read_text())
        with np.load(out / ARRAYS_FILE) as z:
            arrays = {k: z[k] for k in StudyResult.ARRAYS}
    except FileNotFoundError as exc:
        raise ValueError(
            f'{out}: not a study directory ({Path(exc.filename).name} missing)'
        ) from None
    except (OSError, KeyError, ValueError) as exc:  # ValueError: bad JSON, a bad npz
        raise ValueError(f'{out}: unreadable study ({exc})') from None
    try:
        sp = dict(meta['spec'])
        sp['algos'] = tuple(sp['algos'])
        spec = StudySpec(**sp)
        cells = [
            Cell(c['algo'], c['label'], c['row'], c['col'], tuple(tuple(o) for o in c['options']))
            for c in meta['cells']
        ]
        return StudyResult(
            spec=spec,
            cells=cells,
            l_ref=meta['l_ref'],
            l_ref_sem=meta['l_ref_sem'],
            l_first=meta['l_first'],
            wall_s=meta['wall_s'],
            jobs=meta['jobs'],
            command=meta.get('command', ''),
            **arrays,
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(
            f'{out}: not a study written by `ros2 run im_tuner study` ({exc!r:.100})'
        ) from None
