"""What a run's records add up to (counters, the controller left applied, the summary),
shared by the tuning loop and the report; and where the records go (:class:`RunRecord`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from .files import Summary
from .records import Evaluation, Measured, Record, Reference, Remeasurement
from .ripple import ripple_bound, ripple_summary, top_evals, within_limit


@dataclass
class TunerState:
    """Counters and bests (JSON-serialisable via ``vars``: the checkpoint's ``tuner``)."""

    evals: int = 0
    experiments: int = 0
    aborted: int = 0
    faults: int = 0
    lost: int = 0
    timing: int = 0  #: experiments re-run because they did not run on the paper's timing
    sim_s: float = 0.0
    loop_wall_s: float = 0.0
    opt_us: list[float] = field(default_factory=list)  #: ask + tell [us] per live evaluation
    reference: dict[str, Any] | None = None
    best: dict[str, Any] | None = None
    first_satisfactory: int | None = None  #: evaluations it took (1-based count)
    remeasured: list[dict[str, Any]] = field(default_factory=list)
    remeasure_plan: list[int] | None = None
    sessions: list[dict[str, Any]] = field(default_factory=list)


class RunRecord(Protocol):
    """Where a run's records go: a run directory (``RunDir``, durable) or memory."""

    path: Path
    durable: bool  #: False: no checkpoints are written (nothing could resume from them)

    def append_result(self, record: Record) -> None: ...
    def read_results(self) -> list[Record]: ...
    def write_checkpoint(self, state: dict[str, Any]) -> None: ...
    def read_checkpoint(self) -> dict[str, Any] | None: ...


class MemoryRecord:
    """The records in a list, no checkpoints (the study's runs repeat from their seed)."""

    durable = False

    def __init__(self) -> None:
        self.path = Path('<memory>')
        self.results: list[Record] = []

    def append_result(self, record: Record) -> None:
        self.results.append(record)

    def read_results(self) -> list[Record]:
        return list(self.results)

    def write_checkpoint(self, state: dict[str, Any]) -> None:
        pass

    def read_checkpoint(self) -> dict[str, Any] | None:
        return None


def brief(rec: Measured) -> dict[str, Any]:
    """A measured record as the state keeps it (``reference``, ``best``)."""
    return {
        'eval': rec.eval,
        'u': rec.u,
        'gains': rec.gains,
        'loss': rec.loss,
        'terms': rec.terms,
        'experiment_id': rec.experiment_id,
    }


def tally(st: TunerState, rec: Record, satisfactory_loss: float) -> None:
    """Update counters and bests of ``st`` from one results.jsonl record (no optimiser)."""
    if rec.experiment_id is not None:  # it ran on the bench (a lost one too)
        st.experiments += 1
        st.sim_s += rec.sim_s or 0.0  # 0 for a lost one: its length is unknown
    # a safety fault counts whatever became of the record (one in an experiment's settle
    # is a lost record: no step of its gains ran, but the drive tripped)
    st.faults += bool(rec.fault)
    if rec.status == 'lost':
        st.lost += 1
        return
    if rec.status == 'timing':
        st.timing += 1
        return
    if isinstance(rec, Reference):
        st.reference = brief(rec) | {'aborted': rec.aborted}
    elif isinstance(rec, Remeasurement):
        st.remeasured.append({'eval': rec.eval, 'loss': rec.loss, 'aborted': rec.aborted})
    elif isinstance(rec, Evaluation):
        st.evals += 1
        st.aborted += bool(rec.aborted)
        if not rec.aborted and (st.best is None or rec.loss < st.best['loss']):
            st.best = brief(rec)
        if st.first_satisfactory is None and not rec.aborted and rec.loss <= satisfactory_loss:
            st.first_satisfactory = st.evals


def tally_all(records: list[Record], satisfactory_loss: float) -> TunerState:
    """The counters and bests of a run rebuilt from its records alone (the report)."""
    st = TunerState()
    for rec in records:
        tally(st, rec, satisfactory_loss)
    return st


def final_choice(
    st: TunerState, records: list[Record], ripple_limit: float | None = None
) -> dict[str, Any] | None:
    """The record of the controller to leave applied (docs/tuner.md, "Which controller is
    left applied"): the smallest re-measured loss, else the smallest measured, among the
    gains within the ripple limit's bound (if any); the reference if nothing beat it;
    None before any successful measurement."""
    bound = ripple_bound(records, ripple_limit)
    cand = st.best
    if bound is not None:
        cand = None
        best = top_evals(records, 1, bound)
        if best:
            cand = brief(evaluation(records, best[0]))
    if st.remeasured:
        ok = [
            r
            for r in st.remeasured
            if not r['aborted']
            and within_limit(records, evaluation(records, r['eval']).gains, bound)
        ]
        if ok:
            cand = brief(evaluation(records, min(ok, key=lambda r: (r['loss'], r['eval']))['eval']))
    ref = st.reference
    if ref is not None and not ref['aborted'] and (cand is None or ref['loss'] <= cand['loss']):
        return ref
    return cand


def evaluation(records: list[Record], i: int) -> Evaluation:
    """The measured record of evaluation ``i`` (one per index: lost and off-timing attempts
    are other record types)."""
    return next(r for r in records if isinstance(r, Evaluation) and r.eval == i)


def summarize(
    st: TunerState,
    records: list[Record],
    *,
    budget: int,
    satisfactory_loss: float,
    outcome: str,
    wall_s: float | None,
    timing_tolerance: int | None = None,
    ripple_limit: float | None = None,
    remeasure: int = 0,
) -> Summary:
    """summary.json from the counters and the records (``ripple_limit``, ``remeasure``:
    the run's)."""
    import numpy as np  # (here: reading the run's files needs no numpy, a report's --help)

    final = final_choice(st, records, ripple_limit)
    rem = {r['eval']: r['loss'] for r in st.remeasured}
    return Summary.from_dict(
        {
            'outcome': outcome,
            'evaluations': st.evals,
            'budget': budget,
            'experiments': st.experiments,
            'aborted': st.aborted,
            'safety_faults': st.faults,
            'lost': st.lost,
            'timing': st.timing,
            'timing_tolerance': timing_tolerance,
            'held_periods': held_periods(records),
            'reference': None
            if st.reference is None
            else {k: st.reference[k] for k in ('gains', 'loss', 'aborted')},
            'best': None
            if st.best is None
            else {
                **{k: st.best[k] for k in ('eval', 'gains', 'loss', 'terms')},
                'remeasured_loss': rem.get(st.best['eval']),
            },
            'applied': None
            if final is None
            else {
                'eval': final['eval'],
                'gains': final['gains'],
                'loss': final['loss'],
                'remeasured_loss': rem.get(final['eval']) if final['eval'] >= 0 else None,
                'source': 'reference' if final['eval'] < 0 else 'evaluation',
            },
            'remeasured': st.remeasured,
            'satisfactory_loss': satisfactory_loss,
            'evaluations_to_satisfactory': st.first_satisfactory,
            'wall_s': wall_s,
            'loop_wall_s': st.loop_wall_s,
            'sim_s': st.sim_s,
            'real_time_factor': st.sim_s / st.loop_wall_s if st.loop_wall_s > 0 else None,
            # median: the first calls pay for cold caches and imports
            'optimizer_us_per_eval': float(np.median(st.opt_us)) if st.opt_us else None,
            'sessions': st.sessions,
            'ripple': ripple_summary(records, final, ripple_limit, remeasure),
        }
    )


def held_periods(records: list[Record]) -> dict[str, int]:
    """Held + late drive periods of the experiments that counted: how many counted, how
    many had any, their sum and the most in one."""
    n = [
        int(r.periods.get('held', 0)) + int(r.periods.get('late', 0))
        for r in records
        if r.status in ('ok', 'aborted') and r.periods is not None
    ]
    return {
        'counted': len(n),
        'with_held': sum(1 for x in n if x > 0),
        'total': sum(n),
        'max': max(n, default=0),
    }


def replay_plan(records: list[Record]) -> list[Record]:
    """Records of the experiments that ran on the bench, in order (the plant history)."""
    return [r for r in records if r.experiment_id is not None]
