"""The report's data: a run's records, its bags, the signals of the experiments the
figures need, and the check of the bags' losses against results.jsonl."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from im_controller import contract as C
from im_controller.layout import INTERNALS_FIELDS

from ..record.reader import BagData, BagReadError, read_bag
from ..rundir import SUMMARY_FILE, RunDir, RunDirError
from ..runlog import (
    Evaluation,
    Measured,
    Record,
    Reference,
    RunConfig,
    Summary,
    Timing,
    summarize,
    tally_all,
)
from .errors import ReportError

INTERNALS_TOPIC = '/' + C.INTERNALS_TOPIC  # the bench's controller, in the root namespace
LOSS_TOPIC = '/' + C.LOSS_TOPIC
FIGURES = ('fig5_trajectory', 'fig8_best_vs_start', 'fig9_loss', 'fig9_gains')


# ------------------------------------------------------------------------------ data
@dataclass
class Experiment:
    """The per-step signals of one experiment, from ``controller/internals``."""

    record: Record  #: its results.jsonl record
    bag: str  #: the bag it was read from
    t: np.ndarray  #: time since the experiment's first step [s]
    k: np.ndarray  #: drive step index
    signals: dict[str, np.ndarray]  #: INTERNALS_FIELDS name -> values

    @property
    def direction(self) -> int:
        return int(self.record.direction or 1)


@dataclass
class RunReport:
    """Everything the report needs about one run."""

    path: Path
    label: str
    run: RunConfig  #: run.yaml
    records: list[Record]
    summary: Summary  #: summary.json (or rebuilt from the records)
    summary_source: str  #: 'summary.json' or 'results.jsonl'
    bags: list[BagData] = field(default_factory=list)
    bag_errors: list[str] = field(default_factory=list)
    record_bag: list[str | None] = field(default_factory=list)  #: session bag per record
    reference: Experiment | None = None  #: the start controller's experiment
    best: Experiment | None = None  #: the best evaluation's experiment
    consecutive: list[Experiment] = field(default_factory=list)  #: two, for Fig. 5
    missing: list[str] = field(default_factory=list)  #: experiments not found in a bag
    loss_check: dict[str, int] = field(default_factory=dict)
    live: str | None = None  #: the tuner working on the run now, if any
    signals_read: bool = False  #: its bags have been read (:func:`load_signals`)
    #: bags beside the run's own (``report --bags``): a drive host's, from its computer
    extra_bags: list[Path] = field(default_factory=list)

    @property
    def evals(self) -> list[Evaluation]:
        """The evaluation records (not lost, not off timing), in order."""
        return [r for r in self.records if isinstance(r, Evaluation)]


def _session_bags(sessions: list[dict[str, Any]], n_records: int) -> list[str | None]:
    """The bag name of each record's session (None when the run did not say)."""
    out: list[str | None] = [None] * n_records
    starts = sorted(
        [(int(s.get('first_record', 0)), s.get('bag')) for s in sessions]
        # a recorder that died mid-session was replaced by one in a new bag
        + [(int(b['first_record']), b['bag']) for s in sessions for b in s.get('more_bags', [])]
    )
    for first, bag in starts:
        for i in range(first, n_records):
            out[i] = bag
    return out


def load_run(
    path: Path | str,
    label: str | None = None,
    signals: bool = True,
    progress: Callable[[str], None] | None = None,
    extra_bags: list[Path] | tuple[Path, ...] = (),
) -> RunReport:
    """Read one run directory (and, with ``signals``, its bags: else
    :func:`load_signals` reads them later). ``extra_bags``: more bags the experiments'
    signals may be in -- a drive host's bag, recorded on the drive's computer, holds the
    5 kHz topics a two-computer run's own bag leaves out (docs/two-computers.md).

    Raises :class:`ReportError` when ``path`` is not a tuning run."""
    try:
        rd = RunDir.open(path)
        run = rd.read_config()
        records = rd.read_results(repair=False)  # a torn last line is left alone
        saved = rd.read_summary()  # (a newer tuner's format: refused, not "killed")
    except RunDirError as exc:
        raise ReportError(str(exc)) from None
    try:
        ck = rd.read_checkpoint()
    except RunDirError:
        ck = None  # only its session list is read; the records are the truth
    live = rd.holder()  # a tuner is working on it now (its lock)
    sat = float(run.satisfactory_loss or 0.0)
    st = tally_all(records, sat)
    if saved is not None and saved.evaluations == st.evals and saved.experiments == st.experiments:
        summary, source = saved, 'summary.json'
    else:
        # killed (no summary, or the one of an earlier session): rebuild from the records
        sessions = (ck or {}).get('tuner', {}).get('sessions') or (saved and saved.sessions) or []
        st.sessions = sessions
        if live:
            outcome = f'running (a tuner has it: {live}); a snapshot of the records so far'
        elif saved is not None:  # a killed later session kept an earlier one's summary
            outcome = (
                f'interrupted (killed: summary.json counts {saved.evaluations} evaluations '
                f'and {saved.experiments} experiments, results.jsonl {st.evals} and '
                f'{st.experiments})'
            )
        elif (rd.path / SUMMARY_FILE).exists():  # written atomically: not by a kill
            outcome = 'not known (summary.json is not a summary; rebuilt from results.jsonl)'
        else:
            outcome = 'interrupted (killed: no final summary)'
        rebuilt = summarize(
            st,
            records,
            budget=int(run.budget or 0),
            satisfactory_loss=sat,
            outcome=outcome,
            wall_s=None,
            ripple_limit=run.ripple_limit if isinstance(run.ripple_limit, (int, float)) else None,
            remeasure=int(run.remeasure or 0),
        )
        loop = rebuilt.loop_wall_s = sum(float(r.wall_s or 0.0) for r in records)
        rebuilt.real_time_factor = (rebuilt.sim_s or 0.0) / loop if loop > 0 else None
        summary = rebuilt
        source = 'results.jsonl'
    rr = RunReport(
        rd.path,
        label or rd.path.name,
        run,
        records,
        summary,
        source,
        live=live,
        extra_bags=[Path(b) for b in extra_bags],
    )
    rr.record_bag = _session_bags(summary.sessions or [], len(records))
    if signals:
        load_signals(rr, progress)
    return rr


def _ts_ns(rec: Record) -> int | None:
    steps = int(rec.steps or 0)
    if steps <= 0 or rec.t_start_ns is None or rec.t_end_ns is None:
        return None
    return round((int(rec.t_end_ns) - int(rec.t_start_ns)) / steps)


def _window(rec: Record) -> tuple[int, int] | None:
    ts = _ts_ns(rec)
    if not ts:
        return None
    k0 = int(rec.t_start_ns or 0) // ts
    return (k0, k0 + int(rec.steps or 0))


def _wanted(rr: RunReport) -> dict[str, int]:
    """Which records' signals the figures need: name -> record index."""
    want: dict[str, int] = {}
    ran = [
        i for i, r in enumerate(rr.records) if isinstance(r, Measured) and _window(r) is not None
    ]
    for i in ran:
        if isinstance(rr.records[i], Reference):
            want['reference'] = i
            break
    best = rr.summary.best
    if best is not None:
        for i in ran:
            r = rr.records[i]
            if isinstance(r, Evaluation) and r.eval == best['eval']:
                want['best'] = i
                break
    # Fig. 5: the first two consecutive experiments on one session's drive timeline (the
    # controller's ids follow each other; between them the hold and the next one's settle,
    # however long the bench held: lock-step, real time or a real drive)
    for a, b in itertools.pairwise(ran):
        ra, rb = rr.records[a], rr.records[b]
        if (
            rr.record_bag[a] == rr.record_bag[b]
            and rb.experiment_id == (ra.experiment_id or 0) + 1
            and (rb.t_start_ns or 0) >= (ra.t_end_ns or 0)
        ):
            want['consecutive0'], want['consecutive1'] = a, b
            break
    return want


def load_signals(rr: RunReport, progress: Callable[[str], None] | None = None) -> None:
    """Read the run's bags: the experiments the figures need (``reference``, ``best``,
    ``consecutive``, ``missing``), the bags' topics, and the loss check. A bag that cannot
    be read is named in ``bag_errors``."""
    want = _wanted(rr)
    windows = [w for i in set(want.values()) if (w := _window(rr.records[i])) is not None]
    for bag_dir in [*RunDir(rr.path).bag_dirs(), *rr.extra_bags]:
        if progress:
            size = sum(p.stat().st_size for p in bag_dir.glob('*.mcap'))
            progress(f'reading {rr.label}/{bag_dir.name} ({size / 1e6:.0f} MB)')
        try:
            rr.bags.append(read_bag(bag_dir, {INTERNALS_TOPIC: windows}, LOSS_TOPIC))
        except (BagReadError, OSError) as exc:
            rr.bag_errors.append(f'{bag_dir.name}: {exc}')
    fields = tuple((rr.run.controller_parameters or {}).get('internals_fields') or INTERNALS_FIELDS)
    found: dict[str, Experiment] = {}
    for name, i in want.items():
        exp = _experiment(rr, i, fields)
        if exp is None:
            r = rr.records[i]
            what = f'{r.kind} {r.eval} (experiment {r.experiment_id})'
            if what not in rr.missing:  # one record may be wanted for two figures
                rr.missing.append(what)
        else:
            found[name] = exp
    rr.reference = found.get('reference')
    rr.best = found.get('best')
    rr.consecutive = [found[n] for n in ('consecutive0', 'consecutive1') if n in found]
    rr.loss_check = _check_losses(rr)
    rr.signals_read = True


def _experiment(rr: RunReport, i: int, fields: tuple[str, ...]) -> Experiment | None:
    """Record ``i``'s signals from its session's bag (else any bag that has them all)."""
    rec = rr.records[i]
    win, ts_ns = _window(rec), _ts_ns(rec)
    if win is None or ts_ns is None:  # no drive timeline in the record
        return None
    k0, k1 = win
    ts = ts_ns * 1e-9
    own = rr.record_bag[i]
    for bag in sorted(rr.bags, key=lambda b: b.path.name != own):
        a = bag.arrays.get(INTERNALS_TOPIC)
        if a is None or a.size == 0 or a.shape[1] != len(fields):
            continue
        rows = a[(a[:, 0] >= k0) & (a[:, 0] < k1)]
        if not len(rows):
            continue
        rows = rows[np.argsort(rows[:, 0], kind='stable')]
        sig = {n: rows[:, j] for j, n in enumerate(fields)}
        if 'exp_step' in sig and np.any(sig['exp_step'] < 0):
            continue  # hold rows: not this experiment
        return Experiment(rec, bag.path.name, (rows[:, 0] - k0) * ts, rows[:, 0], sig)
    return None


def _check_losses(rr: RunReport) -> dict[str, int]:
    """Each record's loss against the controller's loss message in its session's bag, else
    in another session's bag (a resumed simulated run replays the killed session's
    experiments, bit for bit, so a message the kill cut off is found in the replay)."""
    by_bag: dict[str, dict[tuple[str, str], str]] = {}
    for bag in rr.bags:
        by_bag[bag.path.name] = {
            (m.get('experiment_id', ''), m.get('t_start_ns', '')): m.get('loss', '')
            for m in bag.losses
        }
    out = {'matched': 0, 'differ': 0, 'missing': 0, 'elsewhere': 0}
    for rec, bag_name in zip(rr.records, rr.record_bag, strict=True):
        if rec.status == 'lost' or rec.experiment_id is None:
            continue
        key = (str(rec.experiment_id), str(rec.t_start_ns))
        got = by_bag.get(bag_name, {}).get(key) if bag_name is not None else None
        if got is None:
            got = next(
                (c[key] for name, c in by_bag.items() if key in c and name != bag_name), None
            )
            out['elsewhere'] += got is not None and bag_name is not None
        if got is None:
            out['missing'] += 1
        elif float(got) == (rec.off_timing_loss if isinstance(rec, Timing) else rec.loss):
            out['matched'] += 1
        else:
            out['differ'] += 1
    return out
