"""The report of tuning runs: a summary, plots after the paper's Figs. 5, 8 and 9, a CSV.

``ros2 run im_tuner report RUN_DIR [RUN_DIR2 ...] [--out DIR]`` reads each run's
``run.yaml``, ``results.jsonl`` (the truth: one line per experiment) and its session
bags, and writes into ``DIR`` (default ``RUN_DIR/report/`` for one run,
``<parent of RUN_DIR>/compare_<UTC time>/`` for several):

* ``summary.txt``  -- also printed: per run the algorithm and configuration, outcome,
  best and start loss, best gains, evaluations to a satisfactory loss, aborted
  experiments; per bag the topics with message counts and rates, duration, the recorder's
  recorded-vs-published check, and the losses in the bag checked against results.jsonl;
* ``fig5_trajectory.png`` -- position reference and load torque of two consecutive
  experiments (the paper's Fig. 5);
* ``fig8_best_vs_start.png`` -- position error, speed error and current reference of the
  best evaluation's experiment and of the start controller's (Fig. 8);
* ``fig9_loss.png`` -- loss per evaluation with the best-so-far line (Fig. 9 a, b);
* ``fig9_gains.png`` -- each gain's path over the evaluations (Fig. 9 c, d);
* ``evaluations.csv`` -- one row per experiment of every run (:data:`CSV_COLUMNS`);
  floats written with ``repr``, so :func:`read_csv` gives back the exact values.

With several runs the figures overlay them (for example SPSA against neCGA). A run that
was interrupted or killed is reported from what it left: the records written so far and
the complete chunks of a bag the recorder could not close. Nothing in a run directory is
changed. The signals of an experiment come from ``controller/internals`` in the bag: the
rows whose step index k lies in ``[t_start_ns / Ts, t_start_ns / Ts + steps)`` of its
results record (docs/interfaces.md: state k is at sim time k Ts).

No rclpy here: the report runs without a ROS graph.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import datetime as _dt
import itertools
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from im_controller.config import GAIN_NAMES, GAIN_UNITS
from im_controller.experiment import INTERNALS_FIELDS

from .bagread import BagData, BagReadError, read_bag
from .rundir import RunDir, RunDirError
from .tuning import summarize, tally_all

__all__ = [
    'CSV_COLUMNS',
    'Experiment',
    'ReportError',
    'RunReport',
    'load_run',
    'main',
    'make_figures',
    'read_csv',
    'summary_text',
    'write_csv',
    'write_report',
]

EXIT_USAGE = 2
INTERNALS_TOPIC = '/controller/internals'
LOSS_TOPIC = '/controller/loss'
#: Columns of evaluations.csv, in order (units in docs/tuner.md).
CSV_COLUMNS: tuple[str, ...] = (
    'run',
    'kind',
    'eval',
    'attempt',
    'status',
    'loss',
    'best_loss',
    'term1',
    'term2',
    'term3',
    *GAIN_NAMES,
    *(f'u{i}' for i in range(len(GAIN_NAMES))),
    'aborted',
    'reason',
    'fault',
    'experiment_id',
    'direction',
    'steps',
    'trip_step',
    't_start_ns',
    't_end_ns',
    'sim_s',
    'wall_s',
    'time',
    'bag',
)
_INT_COLS = (
    'eval',
    'attempt',
    'experiment_id',
    'direction',
    'steps',
    'trip_step',
    't_start_ns',
    't_end_ns',
)
_FLOAT_COLS = (
    'loss',
    'best_loss',
    'term1',
    'term2',
    'term3',
    *GAIN_NAMES,
    *(f'u{i}' for i in range(len(GAIN_NAMES))),
    'sim_s',
    'wall_s',
)
_BOOL_COLS = ('aborted', 'fault')
FIGURES = ('fig5_trajectory', 'fig8_best_vs_start', 'fig9_loss', 'fig9_gains')


class ReportError(Exception):
    """The report cannot be made (message says why, in one line)."""


# ------------------------------------------------------------------------------ data
@dataclass
class Experiment:
    """The per-step signals of one experiment, from ``controller/internals``."""

    record: dict[str, Any]  #: its results.jsonl record
    bag: str  #: the bag it was read from
    t: np.ndarray  #: time since the experiment's first step [s]
    k: np.ndarray  #: drive step index
    signals: dict[str, np.ndarray]  #: INTERNALS_FIELDS name -> values

    @property
    def direction(self) -> int:
        return int(self.record.get('direction') or 1)


@dataclass
class RunReport:
    """Everything the report needs about one run."""

    path: Path
    label: str
    run: dict[str, Any]
    records: list[dict[str, Any]]
    summary: dict[str, Any]
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

    @property
    def evals(self) -> list[dict[str, Any]]:
        """The evaluation records (not lost), in order."""
        return [r for r in self.records if r['kind'] == 'eval' and r['status'] != 'lost']


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
) -> RunReport:
    """Read one run directory (and, with ``signals``, its bags).

    Raises :class:`ReportError` when ``path`` is not a tuning run."""
    try:
        rd = RunDir.open(path)
        run = rd.read_run()
        records = rd.read_results(repair=False)  # a torn last line is left alone
    except RunDirError as exc:
        raise ReportError(str(exc)) from None
    try:
        ck = rd.read_checkpoint()
    except RunDirError:
        ck = None  # only its session list is read; the records are the truth
    live = rd.holder()  # a tuner is working on it now (its lock)
    sat = float(run.get('satisfactory_loss', 0.0))
    st = tally_all(records, sat)
    saved = None
    with contextlib.suppress(OSError, ValueError):
        saved = json.loads((rd.path / 'summary.json').read_text())
    if (
        saved is not None
        and saved.get('evaluations') == st.evals
        and saved.get('experiments') == st.experiments
    ):
        summary, source = saved, 'summary.json'
    else:
        # killed (no summary, or the one of an earlier session): rebuild from the records
        sessions = (
            (ck or {}).get('tuner', {}).get('sessions') or (saved or {}).get('sessions') or []
        )
        st.sessions = sessions
        outcome = (
            f'running (a tuner has it: {live}); a snapshot of the records so far'
            if live
            else 'interrupted (killed: no final summary)'
        )
        summary = summarize(
            st,
            records,
            budget=int(run.get('budget', 0)),
            satisfactory_loss=sat,
            outcome=outcome,
            wall_s=None,
        )
        summary['loop_wall_s'] = sum(float(r.get('wall_s') or 0.0) for r in records)
        summary['real_time_factor'] = (
            summary['sim_s'] / summary['loop_wall_s'] if summary['loop_wall_s'] > 0 else None
        )
        source = 'results.jsonl'
    rr = RunReport(rd.path, label or rd.path.name, run, records, summary, source, live=live)
    rr.record_bag = _session_bags(summary.get('sessions') or [], len(records))
    if signals:
        _load_signals(rr, progress)
    return rr


def _ts_ns(rec: dict[str, Any]) -> int | None:
    steps = int(rec.get('steps') or 0)
    if steps <= 0 or rec.get('t_start_ns') is None or rec.get('t_end_ns') is None:
        return None
    return round((int(rec['t_end_ns']) - int(rec['t_start_ns'])) / steps)


def _window(rec: dict[str, Any]) -> tuple[int, int] | None:
    ts = _ts_ns(rec)
    if not ts:
        return None
    k0 = int(rec['t_start_ns']) // ts
    return (k0, k0 + int(rec['steps']))


def _wanted(rr: RunReport) -> dict[str, int]:
    """Which records' signals the figures need: name -> record index."""
    want: dict[str, int] = {}
    ran = [i for i, r in enumerate(rr.records) if r['status'] != 'lost' and _window(r) is not None]
    for i in ran:
        if rr.records[i]['kind'] == 'reference':
            want['reference'] = i
            break
    best = rr.summary.get('best')
    if best is not None:
        for i in ran:
            r = rr.records[i]
            if r['kind'] == 'eval' and r['eval'] == best['eval']:
                want['best'] = i
                break
    # Fig. 5: the first two experiments that ran back to back in one session
    for a, b in itertools.pairwise(ran):
        ra, rb = rr.records[a], rr.records[b]
        if rr.record_bag[a] == rr.record_bag[b] and ra['t_end_ns'] == rb['t_start_ns']:
            want['consecutive0'], want['consecutive1'] = a, b
            break
    return want


def _load_signals(rr: RunReport, progress: Callable[[str], None] | None = None) -> None:
    want = _wanted(rr)
    windows = [w for i in set(want.values()) if (w := _window(rr.records[i])) is not None]
    for bag_dir in RunDir(rr.path).bag_dirs():
        if progress:
            size = sum(p.stat().st_size for p in bag_dir.glob('*.mcap'))
            progress(f'reading {rr.label}/{bag_dir.name} ({size / 1e6:.0f} MB)')
        try:
            rr.bags.append(read_bag(bag_dir, {INTERNALS_TOPIC: windows}, LOSS_TOPIC))
        except (BagReadError, OSError) as exc:
            rr.bag_errors.append(f'{bag_dir.name}: {exc}')
    fields = tuple(
        (rr.run.get('controller_parameters') or {}).get('internals_fields') or INTERNALS_FIELDS
    )
    found: dict[str, Experiment] = {}
    for name, i in want.items():
        exp = _experiment(rr, i, fields)
        if exp is None:
            r = rr.records[i]
            what = f'{r["kind"]} {r["eval"]} (experiment {r["experiment_id"]})'
            if what not in rr.missing:  # one record may be wanted for two figures
                rr.missing.append(what)
        else:
            found[name] = exp
    rr.reference = found.get('reference')
    rr.best = found.get('best')
    rr.consecutive = [found[n] for n in ('consecutive0', 'consecutive1') if n in found]
    rr.loss_check = _check_losses(rr)


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
        if rec['status'] == 'lost' or rec.get('experiment_id') is None:
            continue
        key = (str(rec['experiment_id']), str(rec['t_start_ns']))
        got = by_bag.get(bag_name, {}).get(key) if bag_name is not None else None
        if got is None:
            got = next(
                (c[key] for name, c in by_bag.items() if key in c and name != bag_name), None
            )
            out['elsewhere'] += got is not None and bag_name is not None
        if got is None:
            out['missing'] += 1
        elif float(got) == rec['loss']:
            out['matched'] += 1
        else:
            out['differ'] += 1
    return out


# --------------------------------------------------------------------------- summary
def _gains_text(g: dict[str, float]) -> str:
    return ', '.join(f'{n} {g[n]:.6g} {GAIN_UNITS[n]}' for n in GAIN_NAMES)


def _options_text(run: dict[str, Any]) -> str:
    opts = run.get('options') or {}
    return ', '.join(f'{k}={v}' for k, v in opts.items()) or 'defaults'


def summary_text(rr: RunReport) -> str:
    """The printed summary of one run (see the module docstring)."""
    s, run = rr.summary, rr.run
    L = [
        f'run {rr.path}: {run.get("algo")} ({_options_text(run)}), seed {run.get("seed")}, '
        f'budget {run.get("budget")}, bench {run.get("bench")}'
    ]
    L.append(
        f'  outcome: {s["outcome"]}; {s["evaluations"]}/{s["budget"]} evaluations, '
        f'{s["experiments"]} experiments'
        + ('' if rr.summary_source == 'summary.json' else ' (from results.jsonl)')
    )
    ref = s.get('reference')
    if ref is not None:
        L.append(
            f'  start (hand-tuned) loss: {ref["loss"]:.4f}'
            + (' (aborted)' if ref['aborted'] else '')
            + f': {_gains_text(ref["gains"])}'
        )
    b = s.get('best')
    if b is not None:
        rm = (
            f', re-measured {b["remeasured_loss"]:.4f}'
            if b.get('remeasured_loss') is not None
            else ''
        )
        L.append(f'  best loss: {b["loss"]:.4f} (evaluation {b["eval"]}{rm})')
        L.append(f'  best gains: {_gains_text(b["gains"])}')
    else:
        L.append('  best loss: none (no evaluation completed without abort)')
    a = s.get('applied')
    if a is not None and (b is None or a['eval'] != b['eval']):
        L.append(
            '  applied at the end: '
            + (
                'the start gains'
                if a['source'] == 'reference'
                else f'evaluation {a["eval"]} (loss {a["loss"]:.4f})'
            )
        )
    sat = s.get('evaluations_to_satisfactory')
    L.append(
        f'  satisfactory (loss <= {s["satisfactory_loss"]:g}): '
        + (f'after {sat} evaluations' if sat else 'not reached')
    )
    L.append(
        f'  aborted experiments: {s["aborted"]} of {s["evaluations"]} evaluations '
        f'(safety faults {s["safety_faults"]}); lost results re-run: {s["lost"]}'
    )
    rtf = s.get('real_time_factor')
    wall = f'wall time {s["wall_s"]:.1f} s, ' if s.get('wall_s') is not None else ''
    L.append(
        f'  {wall}simulated experiment time {s["sim_s"]:.1f} s'
        + (f', real-time factor {rtf:.2f}' if rtf else '')
    )
    for bag in rr.bags:
        L.extend(_bag_lines(bag, live=rr.live is not None))
    L.extend(f'  bag {e}' for e in rr.bag_errors)
    if not rr.bags and not rr.bag_errors:
        L.append('  no bag (run with --no-record?)')
    if rr.loss_check and rr.bags:
        c = rr.loss_check
        L.append(
            f'  losses in the bags vs results.jsonl: {c["matched"]} equal'
            + (
                f" ({c['elsewhere']} found only in a later session's replay)"
                if c.get('elsewhere')
                else ''
            )
            + (f', {c["differ"]} DIFFER' if c['differ'] else '')
            + (f', {c["missing"]} not in a bag' if c['missing'] else '')
        )
    L.extend(f'  no signals in the bags for {m}: its plot is left out' for m in rr.missing)
    return '\n'.join(L)


def _bag_lines(bag: BagData, live: bool = False) -> list[str]:
    t0, t1 = bag.t_range_ns
    when = (
        _dt.datetime.fromtimestamp(t0 * 1e-9, _dt.UTC).strftime('%Y-%m-%d %H:%M:%S UTC')
        if t0
        else '-'
    )
    if bag.complete:
        state = 'closed' if bag.state == 'closed' else f'complete ({bag.state})'
    elif live and bag.state == 'recording':
        state = (
            f'being recorded (the run is live; {bag.unread_bytes} bytes after the last '
            'complete chunk not read yet)'
        )
    else:
        state = (
            f'NOT CLOSED (recorder killed; {bag.unread_bytes} bytes after the last '
            'complete chunk not read; --resume repairs it)'
        )
    L = [
        f'  {bag.path.name}: {state}; {bag.messages} messages in {bag.chunks} chunks, '
        f'{(t1 - t0) * 1e-9:.1f} s from {when}'
    ]
    rc = bag.recorder_counts
    w = max([len(n) for n in bag.topics] + [5])
    wt = max([len(t.type) for t in bag.topics.values()] + [4])
    L.append(
        f'    {"topic":<{w}}  {"type":<{wt}} {"messages":>9} {"wall rate":>10}  '
        'recorded / published'
    )
    empty = []
    for name in sorted(bag.topics):
        t = bag.topics[name]
        if t.count == 0:
            empty.append(name)
            continue
        rate = f'{t.rate_hz:7.1f} Hz' if t.rate_hz else f'{"-":>10}'
        if rc is None or name not in rc:
            check = 'not known (bag not closed by the recorder)'
        else:
            c = rc[name]
            check = f'{c["recorded"]} / {c["published"]}'
            if c['lost'] or c['recorded'] != t.count:
                check += f'  <-- LOST {c["lost"]}' if c['lost'] else f'  <-- file has {t.count}'
            elif c.get('published_before_recording'):
                check += f' (+{c["published_before_recording"]} before recording began)'
            else:
                check += ' ok'
        L.append(f'    {name:<{w}}  {t.type:<{wt}} {t.count:>9} {rate}  {check}')
    if empty:
        L.append(f'    no messages: {", ".join(empty)}')
    return L


# ------------------------------------------------------------------------------- CSV
def _best_so_far(records: list[dict[str, Any]]) -> list[float | None]:
    best, out = None, []
    for r in records:
        if (
            r['kind'] == 'eval'
            and r['status'] == 'ok'
            and not r['aborted']
            and (best is None or r['loss'] < best)
        ):
            best = r['loss']
        out.append(best if r['kind'] == 'eval' else None)
    return out


def _csv_row(rr: RunReport, rec: dict[str, Any], best: float | None, bag: str | None) -> list[str]:
    def f(v: Any) -> str:
        if v is None:
            return ''
        if isinstance(v, bool):
            return 'true' if v else 'false'
        if isinstance(v, float):
            return repr(v)
        return str(v)

    terms = rec.get('terms') or [None] * 3
    u = rec.get('u') or [None] * len(GAIN_NAMES)
    vals = {
        'run': rr.label,
        'best_loss': best,
        'term1': terms[0],
        'term2': terms[1],
        'term3': terms[2],
        **(rec.get('gains') or {}),
        **{f'u{i}': x for i, x in enumerate(u)},
        'bag': bag,
    }
    return [f(vals[c]) if c in vals else f(rec.get(c)) for c in CSV_COLUMNS]


def write_csv(runs: list[RunReport], path: Path) -> int:
    """One row per experiment of every run (CSV_COLUMNS); returns the rows written."""
    n = 0
    with open(path, 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for rr in runs:
            for rec, best, bag in zip(
                rr.records, _best_so_far(rr.records), rr.record_bag, strict=True
            ):
                w.writerow(_csv_row(rr, rec, best, bag))
                n += 1
    return n


def read_csv(path: Path | str) -> list[dict[str, Any]]:
    """evaluations.csv back as typed rows (None for empty cells); floats are exact."""
    out = []
    with open(path, newline='') as f:
        for row in csv.DictReader(f):
            r: dict[str, Any] = {}
            for k, v in row.items():
                if v == '':
                    r[k] = None
                elif k in _INT_COLS:
                    r[k] = int(v)
                elif k in _FLOAT_COLS:
                    r[k] = float(v)
                elif k in _BOOL_COLS:
                    r[k] = v == 'true'
                else:
                    r[k] = v
            out.append(r)
    return out


# --------------------------------------------------------------------------- figures
_START_COLOR = 'black'


def _colors(n: int) -> list:
    import matplotlib

    cmap = matplotlib.colormaps['tab10']
    return [cmap(i % 10) for i in range(n)]


def _load_step(rr: RunReport) -> float | None:
    p = rr.run.get('controller_parameters') or {}
    v = p.get('trajectory.load_delay')
    return float(v) if v is not None else None


def fig5(runs: list[RunReport]):
    """Position reference and load torque of two consecutive experiments (paper Fig. 5)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 5.5), layout='constrained')
    ax_p, ax_l = fig.subplots(2, 1, sharex=True)
    rr = next((r for r in runs if r.consecutive), None)
    if rr is None:
        ax_p.text(
            0.5,
            0.5,
            'no two consecutive experiments in the bags',
            ha='center',
            va='center',
            transform=ax_p.transAxes,
        )
    else:
        e0 = rr.consecutive[0]
        t_ref = e0.record['t_start_ns'] * 1e-9
        th0 = e0.signals['theta_ref'][0]
        for j, e in enumerate(rr.consecutive):
            t = e.t + (e.record['t_start_ns'] * 1e-9 - t_ref)
            what = (
                'start gains'
                if e.record['kind'] == 'reference'
                else f'evaluation {e.record["eval"]}'
            )
            ax_p.plot(
                t,
                e.signals['theta_ref'] - th0,
                color='C0',
                lw=1.5,
                label='position reference' if j == 0 else None,
                gid=f'theta_ref:{j}',
            )
            ax_l.plot(
                t,
                e.signals['load_cmd'],
                color='C3',
                lw=1.5,
                label='load torque' if j == 0 else None,
                gid=f'load:{j}',
            )
            for ax in (ax_p, ax_l):
                ax.axvline(t[0], color='grey', lw=0.8, ls=':')
            ax_p.annotate(
                f'experiment {e.record["experiment_id"]}\n({what})',
                (t[0], 0),
                xytext=(4, -4),
                textcoords='offset points',
                va='top',
                fontsize=8,
            )
        ax_p.set_title(
            f'{rr.label}: position reference and load torque of two consecutive experiments'
        )
    ax_p.set_ylabel('position reference θ* − θ*(0) [rad]')
    ax_l.set_ylabel('load torque [N m]')
    ax_l.set_xlabel("sim time from the first experiment's start [s]")
    for ax in (ax_p, ax_l):
        ax.grid(True, alpha=0.3)
    return fig


def fig8(runs: list[RunReport]):
    """Position error, speed error, current reference: best vs start controller (Fig. 8).

    Signals of a negative move are multiplied by -1 so that every move reads as positive."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 8), layout='constrained')
    axes = fig.subplots(3, 1, sharex=True)
    panels = (
        ('e_theta', 'position error [rad]'),
        ('e_omega', 'speed error [rad/s]'),
        ('isq_ref', 'current reference i*sq [A]'),
    )
    curves: list[tuple[str, str, Experiment, Any, float, str]] = []
    starts: dict[tuple[float, ...], tuple[RunReport, Experiment]] = {}
    for rr in runs:  # runs from the same start gains share one start curve
        e = rr.reference
        if e is not None:
            starts.setdefault(tuple(e.record['gains'][n] for n in GAIN_NAMES), (rr, e))
    for j, (rr, e) in enumerate(starts.values()):  # several different starts: dashes
        curves.append(
            (
                f'start:{rr.label}',
                f'start gains (loss {e.record["loss"]:.3f}'
                + (', aborted)' if e.record['aborted'] else ')')
                + ('' if len(starts) == 1 else f', {rr.label}'),
                e,
                _START_COLOR,
                1.0,
                ('-', '--', ':', '-.')[j % 4],
            )
        )
    for rr, c in zip(runs, _colors(len(runs)), strict=True):
        e = rr.best
        if e is not None:
            curves.append(
                (
                    f'best:{rr.label}',
                    f'{rr.label} best: evaluation {e.record["eval"]} (loss {e.record["loss"]:.3f})',
                    e,
                    c,
                    1.4,
                    '-',
                )
            )
    for gid, label, e, color, lw, ls in curves:
        for ax, (name, _yl) in zip(axes, panels, strict=True):
            ax.plot(
                e.t,
                e.direction * e.signals[name],
                color=color,
                lw=lw,
                ls=ls,
                label=label,
                gid=f'{name}:{gid}',
            )
    step = _load_step(runs[0]) if runs else None
    for ax, (_n, yl) in zip(axes, panels, strict=True):
        ax.set_ylabel(yl)
        ax.grid(True, alpha=0.3)
        if step is not None:
            ax.axvline(step, color='grey', lw=0.8, ls=':')
    if step is not None:
        axes[0].annotate(
            'load torque step',
            (step, 1),
            xycoords=('data', 'axes fraction'),
            xytext=(3, -3),
            textcoords='offset points',
            va='top',
            fontsize=8,
        )
    axes[-1].set_xlabel("time from the experiment's start [s]")
    if curves:
        axes[0].legend(fontsize=8, loc='lower right')
    else:
        axes[0].text(
            0.5,
            0.5,
            'no experiment signals in the bags',
            ha='center',
            va='center',
            transform=axes[0].transAxes,
        )
    flipped = any(c[2].direction < 0 for c in curves)
    fig.suptitle(
        'best controller vs start controller under the load torque step'
        + ('\n(negative moves plotted with their sign reversed)' if flipped else ''),
        fontsize=10,
    )
    return fig


def fig9_loss(runs: list[RunReport]):
    """Loss per evaluation and the best so far, each run (paper Fig. 9 a, b)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 5), layout='constrained')
    ax = fig.subplots()
    for rr, c in zip(runs, _colors(len(runs)), strict=True):
        ev = rr.evals
        if not ev:
            continue
        x = np.array([r['eval'] + 1 for r in ev], float)
        y = np.array([r['loss'] for r in ev], float)
        ab = np.array([bool(r['aborted']) for r in ev])
        best = np.array(_best_so_far(ev), dtype=float)  # None -> nan
        ax.plot(
            x[~ab],
            y[~ab],
            '.',
            ms=4,
            color=c,
            alpha=0.6,
            label=f'{rr.label}: loss',
            gid=f'loss:{rr.label}',
        )
        if ab.any():
            ax.plot(
                x[ab],
                y[ab],
                'x',
                ms=5,
                color=c,
                alpha=0.8,
                label=f'{rr.label}: aborted (penalised)',
                gid=f'aborted:{rr.label}',
            )
        ax.step(
            x,
            best,
            where='post',
            color=c,
            lw=2,
            label=f'{rr.label}: best so far',
            gid=f'best:{rr.label}',
        )
        sat = rr.summary.get('evaluations_to_satisfactory')
        if sat:
            ax.plot(
                [sat],
                [best[sat - 1]],
                'v',
                color=c,
                ms=9,
                mec='black',
                gid=f'satisfactory:{rr.label}',
            )
    if runs:
        s0 = runs[0].summary
        ax.axhline(
            s0['satisfactory_loss'],
            color='grey',
            ls='--',
            lw=1,
            label=f'satisfactory loss {s0["satisfactory_loss"]:g}',
            gid='satisfactory',
        )
        ref = s0.get('reference')
        if ref is not None and not ref['aborted']:
            ax.axhline(
                ref['loss'],
                color=_START_COLOR,
                ls=':',
                lw=1,
                label=f'start gains {ref["loss"]:.3f}',
                gid='start',
            )
    ax.set_yscale('log')
    ax.set_xlabel('evaluation')
    ax.set_ylabel('loss')
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=8, ncols=2, loc='upper right')
    ax.set_title('loss per evaluation and best so far (▼: first satisfactory)')
    return fig


def fig9_gains(runs: list[RunReport]):
    """Each gain over the evaluations, each run, inside its search box (Fig. 9 c, d)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 10), layout='constrained')
    axes = fig.subplots(len(GAIN_NAMES), 1, sharex=True)
    for rr, c in zip(runs, _colors(len(runs)), strict=True):
        ev = rr.evals
        x = np.array([r['eval'] + 1 for r in ev], float)
        for ax, n in zip(axes, GAIN_NAMES, strict=True):
            ax.plot(
                x,
                [r['gains'][n] for r in ev],
                '.-',
                ms=3,
                lw=0.7,
                color=c,
                label=rr.label,
                gid=f'{n}:{rr.label}',
            )
    box = (runs[0].run.get('search_box') or {}) if runs else {}
    for ax, n in zip(axes, GAIN_NAMES, strict=True):
        b = box.get(n)
        if b:
            for v in (b['lo'], b['hi']):
                ax.axhline(v, color='grey', ls='--', lw=0.8)
            ax.axhline(b['start'], color=_START_COLOR, ls=':', lw=1, gid=f'start:{n}')
        ax.set_ylabel(f'{n} [{GAIN_UNITS[n]}]')
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel('evaluation')
    axes[0].legend(fontsize=8)
    axes[0].set_title('gains over the evaluations (dashed: search box; dotted: start)')
    return fig


def make_figures(runs: list[RunReport]) -> dict[str, Any]:
    """name -> matplotlib Figure (not drawn on any screen)."""
    return {
        'fig5_trajectory': fig5(runs),
        'fig8_best_vs_start': fig8(runs),
        'fig9_loss': fig9_loss(runs),
        'fig9_gains': fig9_gains(runs),
    }


# ------------------------------------------------------------------------- the command
def write_report(runs: list[RunReport], out: Path) -> dict[str, Path]:
    """Write summary.txt, the PNGs and evaluations.csv into ``out``; returns name -> path."""
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    text = '\n\n'.join(summary_text(rr) for rr in runs) + '\n'
    paths['summary'] = out / 'summary.txt'
    paths['summary'].write_text(text)
    paths['csv'] = out / 'evaluations.csv'
    write_csv(runs, paths['csv'])
    for name, fig in make_figures(runs).items():
        paths[name] = out / f'{name}.png'
        fig.savefig(paths[name], dpi=110)
    return paths


def _labels(paths: list[Path], runs: list[dict[str, Any]]) -> list[str]:
    """Short names: '<algo> seed <s>', the directory name when that is not unique."""
    short = [f'{r.get("algo")} seed {r.get("seed")}' for r in runs]
    if len(set(short)) == len(short):
        return short
    return (
        [p.name for p in paths]
        if len({p.name for p in paths}) == len(paths)
        else [str(p) for p in paths]
    )


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        raise ReportError(message)


def _build_parser() -> argparse.ArgumentParser:
    ap = _Parser(
        prog='ros2 run im_tuner report',
        description='Summary, plots (paper Figs. 5, 8, 9) and per-evaluation CSV of '
        'one or more tuning runs (docs/tuner.md, "The report").',
    )
    ap.add_argument(
        'runs',
        nargs='+',
        type=Path,
        metavar='RUN_DIR',
        help='run directories made by `ros2 run im_tuner tuner` (several: overlaid)',
    )
    ap.add_argument(
        '--out',
        type=Path,
        metavar='DIR',
        help='where to write (default: RUN_DIR/report, or for several runs '
        '<parent of the first>/compare_<UTC time>)',
    )
    return ap


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if args is None else args)
    try:
        cli = _build_parser().parse_args(argv)
        # validate every run before reading any bag or writing anything
        for p in cli.runs:
            try:
                RunDir.open(p).read_run()
                RunDir(p).read_results()  # every record checked: no traceback later
            except RunDirError as exc:
                raise ReportError(str(exc)) from None
        if cli.out is not None and cli.out.exists() and not cli.out.is_dir():
            raise ReportError(f'--out {cli.out}: exists and is not a directory')
    except ReportError as exc:
        print(f'error: report: {exc}', file=sys.stderr)
        return EXIT_USAGE
    heads = [RunDir(p).read_run() for p in cli.runs]
    labels = _labels(cli.runs, heads)

    def progress(msg: str) -> None:
        print(f'report: {msg}', file=sys.stderr, flush=True)

    try:
        runs = [
            load_run(p, lab, progress=progress) for p, lab in zip(cli.runs, labels, strict=True)
        ]
    except ReportError as exc:
        print(f'error: report: {exc}', file=sys.stderr)
        return EXIT_USAGE
    if cli.out is not None:
        out = cli.out
    elif len(runs) == 1:
        out = runs[0].path / 'report'
    else:
        stamp = _dt.datetime.now(_dt.UTC).strftime('%Y%m%dT%H%M%SZ')
        out = runs[0].path.parent / f'compare_{stamp}'
    progress('plotting')
    try:
        paths = write_report(runs, out)
    except OSError as exc:
        print(f'error: report: cannot write {out}: {exc.strerror or exc}', file=sys.stderr)
        return 1
    print(paths['summary'].read_text(), end='')
    print(f'report written to {out}/: ' + ', '.join(p.name for k, p in paths.items()))
    return 0


if __name__ == '__main__':
    sys.exit(main())
