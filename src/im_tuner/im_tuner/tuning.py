"""The tuning loop: ask, measure, tell -- with a budget, best tracking, checkpoints and resume.

Pure (no rclpy): the loop talks to the bench through a :class:`Measurer` (the tuner node
over the controller's services and loss topic; tests and studies on the pure core).
An evaluation asks u, measures ``space.to_gains(u)`` (a lost or off-timing result is
re-run with the same gains, at most ``retries`` times, never told), appends the record to
results.jsonl, tells the optimiser and writes checkpoint.json.  Around the search: a
``reference`` experiment of the start first (not in the budget, not told), and
``remeasure`` re-measurements of the best distinct evaluations at the end, which pick the
controller applied (the smallest measured loss is biased low).  Resume: results.jsonl is
the truth; records after the checkpoint are applied on top, checking that the optimiser
asks exactly the recorded candidates (docs/tuner.md, "Resume").
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from im_controller.config import GAIN_NAMES, Gains
from im_controller.layout import SAFETY_REASONS
from im_controller.result import LossResult

from .optim.base import Optimizer
from .rundir import RunDir, RunDirError
from .runlog import Summary
from .runlog.records import (
    LINE_ORDER,
    MEASURED,
    Evaluation,
    Lost,
    Record,
    Reference,
    Remeasurement,
    Timing,
    evaluation_name,
    ripple_dict,
)
from .runlog.ripple import ripple_bound, told_loss, top_evals
from .runlog.tally import (
    RunRecord,
    TunerState,
    evaluation,
    final_choice,
    replay_plan,
    summarize,
    tally,
)
from .space import SearchSpace

CHECKPOINT_VERSION = 1


def _ordinal(kind: str, index: int) -> str:
    """A record as the person at the bench counts it: the reference, evaluation N (1 is
    the first; results.jsonl's ``eval`` index is N - 1), its re-measurement."""
    if kind == 'reference':
        return 'the reference'
    return evaluation_name(index) + (' re-measured' if kind == 'remeasure' else '')


@dataclass(frozen=True)
class Measurement:
    """One experiment's outcome as the tuner sees it (SI units, sim time in ns)."""

    loss: float
    terms: tuple[float, float, float]
    aborted: bool
    reason: str
    fault: bool  #: a safety fault (the controller went to FAULT)
    experiment_id: int
    direction: int
    steps: int
    trip_step: int
    t_start_ns: int
    t_end_ns: int
    wall_s: float  #: set gains -> loss received [s]
    gains: tuple[float, ...]  #: the gains the controller reports it ran
    #: drive periods driven by a fresh / held / late answer (fresh + held + late = steps)
    fresh: int = 0
    held: int = 0
    late: int = 0
    timing: bool = False  #: held + late beyond the controller's tolerance: not a loss
    gains_step: int = 0  #: drive step from which the experiment's gains acted
    #: standstill ripple of isq* [A]: rms, peak-to-peak after the move, after the load
    ripple: tuple[float, ...] = ()
    motion: tuple[float, ...] = ()  #: the motion sums (im_tuner.identify)

    @classmethod
    def of(cls, r: LossResult, wall_s: float) -> Measurement:
        """The controller's result as the tuner records it (a safety reason is a fault)."""
        return cls(
            **{k: getattr(r, k) for k in _AS_IN_RESULT},
            fault=r.reason in SAFETY_REASONS,
            t_start_ns=r.t_start,
            t_end_ns=r.t_end,
            wall_s=wall_s,
            gains=r.gains.as_tuple(),
        )


#: The fields of a Measurement that are the controller's LossResult's, by the same name
#: (the gains are converted).
_AS_IN_RESULT = tuple(
    f.name
    for f in dataclasses.fields(Measurement)
    if f.name in {r.name for r in dataclasses.fields(LossResult)} and f.name != 'gains'
)

#: The fields of a Measurement its record carries as they are (the record's own names):
#: reason .. t_end_ns of the line, its wall time and the step its gains acted from.
_RECORDED = (
    *LINE_ORDER[LINE_ORDER.index('reason') : LINE_ORDER.index('t_end_ns') + 1],
    'wall_s',
    'gains_step',
)

#: Re-runs of a lost or off-timing measurement with the same gains (the tuner's --retries;
#: the study's runs use it too, so a study run is the tuner's run bit for bit).
DEFAULT_RETRIES = 3


class LostEvaluation(Exception):
    """No result within the timeout.  ``experiment_id``: set if the experiment started."""

    def __init__(self, message: str, experiment_id: int | None = None) -> None:
        super().__init__(message)
        self.experiment_id = experiment_id


class BenchFailure(Exception):
    """The bench cannot go on (unreachable controller, fault with policy 'stop', ...)."""


class StopRequested(Exception):
    """The user asked to stop (SIGINT/SIGTERM) while waiting on the bench."""


class ResumeError(Exception):
    """The run directory cannot be resumed as it is (the message says why)."""


class Measurer(Protocol):
    def measure(self, gains: Gains) -> Measurement: ...
    def apply(self, gains: Gains) -> None: ...


def run_seeds(seed: int) -> tuple[np.random.SeedSequence, int]:
    """Independent streams from a run seed (int >= 0): the optimiser's SeedSequence and the
    simulated drive's noise seed (int32 >= 0).  The tuner and the offline study both use
    it, so a study run is reproduced by a tuner run with the same ``--seed``."""
    opt_ss, drive_ss = np.random.SeedSequence(seed).spawn(2)
    return opt_ss, int(drive_ss.generate_state(1)[0]) >> 1


def _gains_of(gains: dict[str, float]) -> Gains:
    """The Gains of a record's ``gains`` (or of the state's brief of one)."""
    return Gains(*(float(gains[n]) for n in GAIN_NAMES))


class TuningRun:
    """One tuning run in ``rundir`` (see the module docstring)."""

    def __init__(
        self,
        rundir: RunDir | RunRecord,
        space: SearchSpace,
        optimizer: Optimizer,
        *,
        budget: int,
        satisfactory_loss: float,
        remeasure: int = 3,
        retries: int = DEFAULT_RETRIES,
        reference: bool = True,
        progress: Callable[[str, Record, TuningRun], None] | None = None,
        first_step: Any = None,
        ripple_limit: float | None = None,
    ) -> None:
        """``ripple_limit``: the standstill-ripple limit of the final choice, a ratio to the
        start's rms (None: off; ``runlog.ripple``).  ``first_step``: the
        ``IdentifiedFirstStep`` giving the optimiser the point it ``wants_first``; its
        ``identified(records)`` goes into the summary."""
        if budget < 1:
            raise ValueError(f'budget must be >= 1, got {budget}')
        self.rundir = rundir
        self.space = space
        self.opt = optimizer
        self.budget = int(budget)
        self.satisfactory = float(satisfactory_loss)
        self.remeasure = int(remeasure)
        self.retries = int(retries)
        #: the run's timing tolerance [periods] (run.yaml; for the summary)
        self.timing_tolerance: int | None = None
        #: called after an attempt off the paper's timing (a ``timing`` record), before
        #: the next: the tolerance the controller now judges by (None: unchanged); the
        #: tuner's ``--timing-tolerance auto`` checks its host again there
        self.off_timing: Callable[[], int | None] | None = None
        self.with_reference = bool(reference)
        self.progress = progress
        self.first_step = first_step
        if ripple_limit is not None and not (ripple_limit > 0 and np.isfinite(ripple_limit)):
            raise ValueError(f'ripple_limit must be a ratio > 0, got {ripple_limit!r}')
        self.ripple_limit = None if ripple_limit is None else float(ripple_limit)
        #: the drive's rated torque's q current [A] (rated torque / Kt of its drive file),
        #: for the summary's ripple in % of it; None: the tuner does not know the drive
        self.rated_isq_a: float | None = None
        self.state = TunerState()
        self.records: list[Record] = []
        self._t_mark = time.perf_counter()
        self._ask_us = 0.0
        #: whether the final gains reached the controller (None: not tried yet)
        self.applied: bool | None = None
        #: called with every record as it is appended to results.jsonl (not the ones a
        #: resume reads back): the tuner node publishes it (im_tuner.result_msg)
        self.on_record: Callable[[Record], None] | None = None
        #: this session's number in the run (0-based), written into every record as
        #: ``session`` (None: no sessions, e.g. the study's runs; nothing written)
        self.session: int | None = None

    def restore(self) -> int:
        """Load the run's results and checkpoint; returns the number of records
        (ResumeError: they disagree, or a record is malformed).  Nothing is written.  An
        unreadable checkpoint is rebuilt by replaying every record through a fresh
        optimiser; ``self.rebuilt`` says why."""
        try:
            records = self.rundir.read_results()
        except RunDirError as exc:
            raise ResumeError(str(exc)) from None
        fresh = self.opt
        self.rebuilt: str | None = None
        try:
            ck = self.rundir.read_checkpoint()
        except RunDirError as exc:
            ck, self.rebuilt = None, str(exc)
        done = 0
        if ck is not None:
            if ck.get('version') != CHECKPOINT_VERSION:
                raise ResumeError(
                    f'{self.rundir.path}: checkpoint version '
                    f'{ck.get("version")!r}, expected {CHECKPOINT_VERSION}'
                )
            done = int(ck['records'])
            if done > len(records):
                raise ResumeError(
                    f'{self.rundir.path}: the checkpoint counts {done} records '
                    f'but results.jsonl has {len(records)}'
                )
            try:
                self.opt = Optimizer.from_state(ck['optimizer'])
                self.state = TunerState(**ck['tuner'])
            except Exception as exc:  # any malformed field: the checkpoint is unusable
                self.opt, self.state, done = fresh, TunerState(), 0
                self.rebuilt = f'checkpoint.json: not a usable checkpoint ({exc!r:.120})'
        self.records = records[:done]
        for rec in records[done:]:
            self._apply(rec, live=False)
            self.records.append(rec)
        return len(self.records)

    def _apply(self, rec: Record, live: bool) -> None:
        """Update the counters (and, for an evaluation, the optimiser) from one record."""
        if isinstance(rec, Evaluation):
            u = np.asarray(rec.u, dtype=float)
            if not live:
                self._give_first()
                asked = self.opt.ask()
                if not np.array_equal(asked, u):
                    raise ResumeError(
                        f'{self.rundir.path}: evaluation {rec.eval} in results.jsonl is not '
                        'what the checkpointed optimiser asks; the files do not belong together'
                    )
            # above the ripple limit: what the search is told (runlog.ripple.told_loss)
            told = told_loss(self.records, rec, self.ripple_limit)
            t0 = time.perf_counter()
            self.opt.tell_measurement(u, told, bool(rec.aborted))
            if live:
                self.state.opt_us.append(self._ask_us + 1e6 * (time.perf_counter() - t0))
        tally(self.state, rec, self.satisfactory)

    def _give_first(self) -> None:
        """safe's first step from the start's measurements, when it wants one now, and
        then the abort screen of the drive they identify."""
        if self.first_step is None:
            return
        if self.opt.wants_first:
            self.opt.set_first(self.first_step(self.records))
        if self.opt.wants_screen:
            self.opt.screen = self.first_step.screen(self.records)

    def checkpoint(self) -> None:
        """Write checkpoint.json: the optimiser and the counters after the records so far
        (atomic; nothing for a record that is not durable, e.g. the study's runs)."""
        if not self.rundir.durable:
            return  # (the study's: research/NOTES.md, "From the source of im_tuner/tuning.py")
        self.rundir.write_checkpoint(
            {
                'version': CHECKPOINT_VERSION,
                'records': len(self.records),
                'optimizer': self.opt.state_dict(),
                'tuner': vars(self.state),
            }
        )

    def _record(
        self,
        kind: str,
        index: int,
        attempt: int,
        u: np.ndarray | None,
        gains: Gains,
        m: Measurement | None,
        lost: LostEvaluation | None,
        wall_s: float,
    ) -> Record:
        """The results.jsonl record of one attempt (``m``: its measurement, None: lost)."""
        common: dict[str, Any] = {
            'kind': kind,
            'eval': index,
            'attempt': attempt,
            'u': None if u is None else [float(x) for x in u],
            'gains': {n: float(v) for n, v in zip(GAIN_NAMES, gains.as_tuple(), strict=True)},
            'time': _dt.datetime.now(_dt.UTC).isoformat(timespec='milliseconds'),
            'session': self.session,
        }
        if m is None:
            return Lost(
                **common,
                reason=str(lost),
                fault=False,
                experiment_id=lost.experiment_id if lost else None,
                sim_s=0.0,
                wall_s=wall_s,
            )
        common.update(
            {k: getattr(m, k) for k in _RECORDED},
            sim_s=(m.t_end_ns - m.t_start_ns) * 1e-9,
            periods={'fresh': m.fresh, 'held': m.held, 'late': m.late},
            ripple=ripple_dict(m.ripple),
            motion=[float(x) for x in m.motion] if m.motion else None,
        )
        if m.timing:
            # measured, but not the paper's loss: kept under another name, never a loss
            common['reason'] = (
                f'timing: {m.held} held and {m.late} late of {m.steps} drive periods'
                + (f' (and {m.reason})' if m.aborted else '')
            )
            return Timing(**common, off_timing_loss=m.loss)
        if m.aborted and m.steps == 0:
            # stopped in its standstill settle (a safety fault while the fallback gains
            # held): not one step of these gains was measured
            common['reason'] = (
                f'ended in its settle, before step 0 ({m.reason}): no step of these gains measured'
            )
            return Lost(**common)
        status = 'aborted' if m.aborted else 'ok'
        measured: dict[str, Any] = {
            'status': status,
            'loss': m.loss,
            'terms': list(m.terms),
            'aborted': m.aborted,
        }
        if kind == 'eval':
            # best-so-far after this evaluation, for the results table
            b = self.state.best
            best = (
                m.loss
                if not m.aborted and (b is None or m.loss < b['loss'])
                else (b['loss'] if b else None)
            )
            return Evaluation(**common, **measured, best_loss=best)
        cls = Reference if kind == 'reference' else Remeasurement
        return cls(**common, **measured)

    def _measure(
        self, measurer: Measurer, kind: str, index: int, u: np.ndarray | None, gains: Gains
    ) -> Record:
        """Measure ``gains`` (re-running lost and off-timing results), recording every attempt."""
        for attempt in range(1, self.retries + 2):
            t0 = time.perf_counter()
            m: Measurement | None = None
            lost = None
            try:
                m = measurer.measure(gains)
            except LostEvaluation as exc:
                lost = exc
            rec = self._record(kind, index, attempt, u, gains, m, lost, time.perf_counter() - t0)
            # loop wall time: everything since the previous record (optimiser, files,
            # parameter calls, experiment), so the real-time factor is honest
            now = time.perf_counter()
            self.state.loop_wall_s += now - self._t_mark
            self._t_mark = now
            self.rundir.append_result(rec)
            if self.on_record is not None:
                self.on_record(rec)
            self._apply(rec, live=True)
            self.records.append(rec)
            self.checkpoint()
            if self.progress is not None:
                self.progress(kind, rec, self)
            if rec.status in MEASURED:
                return rec
            if rec.status == 'timing' and self.off_timing is not None:
                tolerance = self.off_timing()
                if tolerance is not None:
                    self.timing_tolerance = tolerance
        raise BenchFailure(
            f'{_ordinal(kind, index)}: no result after {self.retries + 1} attempts '
            f'with the same gains ({rec.reason})'
        )

    def run(self, measurer: Measurer, should_stop: Callable[[], bool] = lambda: False) -> str:
        """Run (or continue) until the budget is spent; returns 'done', 'interrupted' or
        'failed: <reason>'.  The best gains are applied at the end in every case."""
        st = self.state
        outcome = 'done'
        self._t_mark = time.perf_counter()
        try:
            if self.with_reference and st.reference is None and st.evals == 0:
                self._measure(measurer, 'reference', -1, None, Gains(*self.space.start))
            while st.evals < self.budget:
                if should_stop():
                    raise StopRequested()
                self._give_first()
                t0 = time.perf_counter()
                u = self.opt.ask()
                self._ask_us = 1e6 * (time.perf_counter() - t0)
                self._measure(measurer, 'eval', st.evals, u, self.space.to_gains(u))
            if self.remeasure > 0:
                if st.remeasure_plan is None:
                    bound = ripple_bound(self.records, self.ripple_limit)
                    st.remeasure_plan = top_evals(self.records, self.remeasure, bound)
                    self.checkpoint()
                done = {r['eval'] for r in st.remeasured}
                for i in st.remeasure_plan:
                    if i in done:
                        continue
                    if should_stop():
                        raise StopRequested()
                    gains = _gains_of(evaluation(self.records, i).gains)
                    self._measure(measurer, 'remeasure', i, None, gains)
        except StopRequested:
            outcome = 'interrupted'
        except BenchFailure as exc:
            outcome = f'failed: {exc}'
        final = self.final_choice()
        if final is not None:
            try:
                measurer.apply(_gains_of(final['gains']))
                self.applied = True
            except (BenchFailure, LostEvaluation, StopRequested) as exc:
                self.applied = False
                what = f'could not apply the best gains ({exc or type(exc).__name__})'
                if outcome == 'done':
                    outcome = f'failed: {what}'
                elif outcome.startswith('failed'):
                    outcome = f'{outcome}; {what}'
        return outcome

    def final_choice(self) -> dict[str, Any] | None:
        """See ``runlog.tally.final_choice``."""
        return final_choice(self.state, self.records, self.ripple_limit)

    def summary(self, *, outcome: str, wall_s: float) -> Summary:
        """summary.json (``runlog.summarize``; ``applied.on_controller``: whether the final
        gains reached the controller)."""
        s = summarize(
            self.state,
            self.records,
            budget=self.budget,
            satisfactory_loss=self.satisfactory,
            outcome=outcome,
            wall_s=wall_s,
            timing_tolerance=self.timing_tolerance,
            ripple_limit=self.ripple_limit,
            remeasure=self.remeasure,
        )
        if s.applied is not None:
            s.applied['on_controller'] = self.applied
        rated = self.rated_isq_a
        if self.first_step is not None:
            idf = self.first_step.identified(self.records)
            s.identification = None if idf is None else dataclasses.asdict(idf)
            if self.opt.screen is not None:
                s.screened = self.opt.screened
            m = self.first_step.drive.machine
            rated = m.rated_torque / m.Kt
        if s.ripple is not None and rated is not None:  # for a percentage
            s.ripple['rated_isq_a'] = rated
        return s


def replay(
    measurer: Measurer,
    records: list[Record],
    progress: Callable[[int, int], None] | None = None,
) -> int:
    """Re-run the experiments of ``records`` with their gains, in order, to bring a fresh
    deterministic (simulated, lock-step) bench to the state the killed run left it in.
    Each replayed loss must equal the recorded one bit for bit.  Returns the count."""
    plan = replay_plan(records)
    for k, rec in enumerate(plan):
        try:
            m = measurer.measure(_gains_of(rec.gains))
        except LostEvaluation as exc:
            raise ResumeError(f'replay: experiment {k} lost ({exc})') from None
        if rec.status in MEASURED and not (
            m.loss == rec.loss and m.experiment_id == rec.experiment_id
        ):
            raise ResumeError(
                f'replay: experiment {rec.experiment_id} gave loss {m.loss!r} '
                f'(id {m.experiment_id}), the run recorded {rec.loss!r}: this bench is not '
                'the one of the run (drive file, model or seed changed?)'
            )
        if progress is not None:
            progress(k + 1, len(plan))
    return len(plan)
