"""What a study is (its grid and :class:`StudySpec`), light enough to check a command line.

Nothing here imports scipy, numba, an optimiser's algorithm module, Dask or matplotlib:
``ros2 run im_tuner study`` parses and checks its options with this module alone, so that
a refusal comes at once (the heavy modules take seconds to import).  ``im_tuner.optim``
itself is light (its algorithms load when one is built): the grid's names and option
values are the optimisers' own.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

from .. import optim

if TYPE_CHECKING:  # the types only; the modules are imported where they are used
    from im_controller.config import ExperimentConfig
    from im_drive_sim.params import DriveConfig

    from ..family import DriveSetup
    from ..space import TunerParams


class StudyError(Exception):
    """Bad input: one line, exit 2, nothing written."""


#: The paper's two algorithms: Tables I-III and the paper's conclusions.
PAPER_ALGOS: tuple[str, ...] = ('spsa', 'necga')
#: The small grids of the algorithms beyond the paper: (label, options); 'start' and
#: 'first' are the run's policies (``optim.POLICIES``, the tuner's ``--opt start``/``first``;
#: :attr:`Cell.start_kind`, :attr:`Cell.first`), not optimiser options.
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
        ('first step from the drive model', (('first', 'model'),)),
        ('first step from the identified drive', (('first', 'identify'),)),
    ),
    'tpe': (
        ('defaults, no start', (('start', 'none'),)),
        ('defaults', ()),
        ('n_startup_trials=5', (('n_startup_trials', 5),)),
    ),
    # the outside reference (not a tuner algorithm: study/bobyqa.py): trust-region radius
    # 0.08 of the [0, 1]-normalised box, from the hand-tuned start
    'bobyqa': (('rhobeg=0.08', (('rhobeg', 0.08), ('start', 'hand'))),),
}
#: Study rows that are not tuner algorithms: an outside reference (Py-BOBYQA).
REFERENCE_ALGOS: tuple[str, ...] = ('bobyqa',)
#: The compact GAs: a grid over their population size n.
CGA_ALGOS: tuple[str, ...] = ('necga', 'cga', 'pecga')
#: Algorithms the study has a grid for: every tuner algorithm and the reference rows.
STUDY_ALGOS: tuple[str, ...] = optim.ALGOS + REFERENCE_ALGOS
#: The recommended configurations of each algorithm (the per-drive study's rows): the
#: labels of its grid cells.  SPSA and the compact GAs: the paper's centre (n=25 is also
#: the best of cGA's and peCGA's grids in docs/reproduction.md).  ``safe``: blind (what the
#: tuner does on a drive it does not know) and with the first step from the drive model
#: (the tuner's default where it knows the drive: ``DEFAULT_ROW``).
RECOMMENDED: dict[str, tuple[str, ...]] = {
    'spsa': ('a=0.0183 c=0.03',),
    'necga': ('n=25 eta=12',),
    'cga': ('n=25',),
    'pecga': ('n=25',),
    'rcga': ('sigma0=0.3',),
    'cmaes': ('sigma0=0.1',),
    'tpe': ('n_startup_trials=5',),
    'safe': ('defaults', 'first step from the drive model', 'first step from the identified drive'),
    'bobyqa': ('rhobeg=0.08',),
}
#: The tuner's default on a drive it knows (``optim.DEFAULT_ALGO`` with ``--opt
#: first=identify``, the default with ``--drive-config`` or a simulated bench): the row the
#: default's goals (``summary.GOAL``, the plant-mismatch grid) are for.
DEFAULT_ROW: tuple[str, str] = (optim.DEFAULT_ALGO, 'first step from the identified drive')
#: Start of a run when its cell does not say: SPSA a random point (as the paper), every
#: other algorithm that takes a start the hand-tuned gains (what a real bench has).
RANDOM_START_DEFAULT: frozenset[str] = frozenset({'spsa'})
#: The grid factors around the paper's configuration (x/5, x, 5x).
FACTORS: tuple[tuple[str, float], ...] = (('/5', 0.2), ('', 1.0), ('*5', 5.0))
#: Experiments of the hand-tuned start that define L_ref.
REF_EXPERIMENTS = 100
DEFAULT_SATISFACTORY = 0.9
DEFAULT_SEED = 2005  # the paper's year: a fixed, documented default
#: Runs per configuration a bootstrap interval needs (a resample of one run is that run);
#: a study of fewer runs reports its means without intervals.
MIN_RUNS_FOR_INTERVALS = 2


#: the names of the run's policies (``optim.POLICIES``) a cell's options may hold
_POLICY_NAMES: frozenset[str] = frozenset(k for p in optim.POLICIES.values() for k in p)


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
        """The optimiser's options (without the run's policies: start, first step)."""
        return {k: v for k, v in self.options if k not in _POLICY_NAMES}

    @property
    def first(self) -> str:
        """'model' (safe's first step from the study's drive file as a nominal model,
        ``im_tuner.prior``), 'identify' (from that model with the mechanics the start's
        experiments identify, ``im_tuner.first_step``) or 'none'."""
        return str(dict(self.options).get('first', 'none'))

    @property
    def start_kind(self) -> str:
        """'random' (a uniform point, third stream of the run seed, given to the tuner as a
        parameter file), 'hand' (the parameter file's start) or 'none' (the optimiser's
        own, without a start point)."""
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
        elif algo in CGA_ALGOS:
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


def recommended(algos: tuple[str, ...]) -> list[Cell]:
    """One cell per algorithm: its recommended configuration (``RECOMMENDED``), as it
    stands in the full grid (same label, place and options)."""
    return [c for c in grid(algos) if c.label in RECOMMENDED.get(c.algo, ())]


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
    params_file: str | None = None  #: tuner parameter file (None: the drive's)
    #: the drives (packaged names or drive files; ``im_tuner.family``): () the single
    #: drive of ``drive_config``; one name: that drive's study; several: a family study,
    #: one study per drive (:meth:`for_drive`)
    drives: tuple[str, ...] = ()
    realism: str | None = None  #: realism profile (None: the drive file's own)
    full_grid: bool = True  #: every cell of the grid, else the recommended ones
    #: the simulated plant, when it is not the drive the tuner is told (``study.plant``):
    #: () the told drive; one name (packaged or a file) for every drive; or one per drive
    plant: tuple[str, ...] = ()
    #: the mismatch applied to the plant (``plant.parse_mismatch``): (key, value) pairs
    mismatch: tuple[tuple[str, float], ...] = ()
    #: the final choice's standstill-ripple limit of every row (``--ripple-limit``): a
    #: ratio to the start's rms, None (off), or 'default': each row's tuner default
    #: (``runlog.ripple.default_ripple_limit``: on for safe, off for the others)
    ripple_limit: float | str | None = 'default'

    #: fields written to study.json only when they differ from their defaults (a study
    #: that uses none of them writes the same file as one of the paper's)
    NEW_FIELDS: ClassVar[tuple[str, ...]] = (
        'drives',
        'realism',
        'full_grid',
        'plant',
        'mismatch',
        'ripple_limit',
    )

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
        if len(set(self.drives)) != len(self.drives):
            dup = next(d for d in self.drives if self.drives.count(d) > 1)
            raise ValueError(f'drives: {dup!r} given twice')
        if self.drives and self.drive_config is not None:
            raise ValueError('drives and drive-config exclude each other')
        if self.realism is not None and not isinstance(self.realism, str):
            raise ValueError(f'realism must be a profile name, got {self.realism!r}')
        if not all(isinstance(p, str) and p for p in self.plant):
            raise ValueError(f'plant: drive names or files expected, got {self.plant!r}')
        if len(self.plant) > 1 and len(self.plant) != len(self.drives):
            n = max(len(self.drives), 1)
            raise ValueError(
                f'plant: {len(self.plant)} plants for {n} drive{"s" if n > 1 else ""} '
                '(give one per drive, or one for all)'
            )
        if self.mismatch:
            from .plant import check_mismatch

            check_mismatch(self.mismatch)
        rl = self.ripple_limit
        if not (
            rl is None
            or rl == 'default'
            or (isinstance(rl, float) and rl >= 1.0 and math.isfinite(rl))
        ):
            raise ValueError(f"ripple_limit: a ratio >= 1, None or 'default', got {rl!r}")
        if not self.algos or len(set(self.algos)) != len(self.algos):
            raise ValueError(f'algos must be distinct names, got {self.algos!r}')
        for a in self.algos:
            if a not in STUDY_ALGOS:
                raise ValueError(
                    f'algos: no study grid for {a!r} (allowed: {", ".join(STUDY_ALGOS)})'
                )

    def limit_of(self, cell: Cell) -> float | None:
        """The ripple limit of ``cell``'s runs (None: off): :attr:`ripple_limit`, or the
        tuner's default for the cell's algorithm (a reference row: off)."""
        if self.ripple_limit != 'default':
            return None if self.ripple_limit is None else float(self.ripple_limit)
        from ..runlog.ripple import default_ripple_limit

        return default_ripple_limit(cell.algo)

    @property
    def cells(self) -> list[Cell]:
        return grid(self.algos) if self.full_grid else recommended(self.algos)

    @property
    def paper_tables(self) -> bool:
        """Whether Tables I-III (the paper's grids) can be made: the full grid of SPSA
        or neCGA."""
        return self.full_grid and any(a in PAPER_ALGOS for a in self.algos)

    def for_drive(self, name: str) -> StudySpec:
        """The study of drive ``name`` (one of :attr:`drives`), with its plant."""
        plant = self.plant
        if len(plant) > 1:
            plant = (plant[self.drives.index(name)],)
        return dataclasses.replace(self, drives=(name,), plant=plant)

    def setup(self) -> DriveSetup:
        """The drive's set-up (``im_tuner.family.drive_setup``): drive, experiment,
        tuner parameters.  ValueError for an unknown drive or a bad file."""
        if len(self.drives) > 1:
            raise ValueError('a study of several drives has a set-up per drive (for_drive)')
        from ..family import drive_setup

        name = self.drives[0] if self.drives else self.drive_config
        return drive_setup(name, self.realism, self.model)

    def loaded(self) -> tuple[DriveConfig, TunerParams, ExperimentConfig]:
        """(the plant, tuner parameters, experiment), the files read once: what a run
        measures on, and what the tuner knows (the told drive's box and experiment)."""
        s = self.setup()
        return self.plant_drive(s.drive), self.params(s), s.experiment

    @property
    def split(self) -> bool:
        """Whether the plant is not the told drive (``--plant`` or ``--plant-mismatch``)."""
        return bool(self.plant or self.mismatch)

    def drive(self) -> DriveConfig:
        """The drive the tuner is told (its model gives ``safe``'s first step)."""
        return self.setup().drive

    def plant_drive(self, told: DriveConfig | None = None) -> DriveConfig:
        """The simulated plant the runs measure on (``study.plant``): the told drive
        (``told``, else :meth:`drive`) itself unless :attr:`plant` or :attr:`mismatch`
        says otherwise.  ``plant.PlantError`` (a ValueError, one line) for a plant that
        cannot run the told drive's experiment."""
        told = self.drive() if told is None else told
        if not self.split:
            return told
        if len(self.plant) > 1:
            raise ValueError('a study of several drives has a plant per drive (for_drive)')
        from .plant import make_plant

        name = self.plant[0] if self.plant else None
        return make_plant(told, name, self.mismatch, self.realism, self.model)

    def experiment(self) -> ExperimentConfig:
        return self.setup().experiment

    def params(self, setup: DriveSetup | None = None) -> TunerParams:
        """The tuner parameters: :attr:`params_file`'s, else the drive's (``setup``: the
        drive's set-up when already made)."""
        from ..space import load_params

        if self.params_file:
            return load_params(self.params_file)
        return (self.setup() if setup is None else setup).params


def default_jobs() -> int:
    """Every core this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1
