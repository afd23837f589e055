"""A study's results (:class:`StudyResult`) and their files, study.npz and study.json.

Light at import (numpy and ``spec``), so that ``study --from DIR`` refuses a directory
that is not a study at once.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..rundir import atomic_write_text
from .spec import REF_EXPERIMENTS, Cell, StudySpec

ARRAYS_FILE = 'study.npz'
META_FILE = 'study.json'


@dataclass(kw_only=True)
class StudyResult:
    """All runs of a study, as arrays indexed [cell, run, (evaluation)]; raw losses."""

    #: the arrays save() and load() keep in study.npz (every array field; the rest goes
    #: into study.json)
    ARRAYS: ClassVar[tuple[str, ...]]

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
    #: the numeric baseline its runs ran on (im_drive_sim.numeric.status() of the study's
    #: process; every worker was checked to agree); None: not known (a result made in memory)
    numeric: dict | None = None
    #: the hand-tuned start's L_ref on the told drive, when the plant is another
    #: (``spec.split``; ``l_ref`` is always the plant's); None otherwise
    l_ref_told: float | None = None
    #: float64[cells, runs, 4]: the standstill rms of isq* [A] after the move and after
    #: the load, of the start then of the final choice (nan: not measured)
    ripple: np.ndarray
    #: bool[cells, runs]: the ripple limit kept out a point the run would have re-measured
    ripple_changed: np.ndarray
    #: float64[cells, runs, 4]: as ``ripple``, peak to peak [A]
    ripple_pp: np.ndarray
    #: float64[cells, runs, 8]: the drive identified from the start's experiments
    #: (``identify.FIGURES``: J, Kt, B, Tc, each with its sd; SI); nan: not identified
    identified: np.ndarray

    @property
    def experiments(self) -> int:
        """Experiments run (reference + evaluations + re-measurements)."""
        return int(
            self.losses.size + self.ref_loss.size + np.count_nonzero(np.isfinite(self.remeasured))
        )


StudyResult.ARRAYS = tuple(
    f.name for f in dataclasses.fields(StudyResult) if f.type == 'np.ndarray'
)


def empty_runs(C: int, R: int, B: int, D: int) -> dict[str, np.ndarray]:
    """Every per-run array of ``C`` cells by ``R`` runs of ``B`` evaluations of ``D``
    gains, nothing measured yet (what a study fills run by run)."""
    from ..identify import FIGURES

    return {
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
        'ripple': np.full((C, R, 4), np.nan),
        'ripple_changed': np.zeros((C, R), bool),
        'ripple_pp': np.full((C, R, 4), np.nan),
        'identified': np.full((C, R, len(FIGURES)), np.nan),
    }


def save(res: StudyResult, out: Path | str) -> None:
    """Write ``study.npz`` (every array: nothing is lost) and ``study.json`` (the spec,
    L_ref, timing) into ``out`` (created)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / ARRAYS_FILE, **{k: getattr(res, k) for k in StudyResult.ARRAYS})
    meta = {
        'spec': {
            k: v
            for k, v in dataclasses.asdict(res.spec).items()
            if k not in StudySpec.NEW_FIELDS or v != getattr(StudySpec, k)
        },
        'cells': [dataclasses.asdict(c) for c in res.cells],
        'l_ref': res.l_ref,
        'l_ref_sem': res.l_ref_sem,
        'l_first': res.l_first,
        'ref_experiments': REF_EXPERIMENTS,
        'experiments': res.experiments,
        'wall_s': res.wall_s,
        'jobs': res.jobs,
        'command': res.command,
        'numeric': res.numeric,
    }
    if res.l_ref_told is not None:  # (only a study whose plant is not the told drive)
        meta['l_ref_told'] = res.l_ref_told
    atomic_write_text(out / META_FILE, json.dumps(meta, indent=1) + '\n')


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
        sp['drives'] = tuple(sp.get('drives', ()))
        sp['plant'] = tuple(sp.get('plant', ()))
        sp['mismatch'] = tuple(tuple(kv) for kv in sp.get('mismatch', ()))
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
            command=meta['command'],
            numeric=meta['numeric'],
            l_ref_told=meta.get('l_ref_told'),
            **arrays,
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(
            f'{out}: not a study written by `ros2 run im_tuner study` ({exc!r:.100})'
        ) from None
