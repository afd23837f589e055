"""The report's summary text (summary.txt, also printed)."""

from __future__ import annotations

import datetime as _dt
from typing import TYPE_CHECKING

from ..progress import (
    clock_text,
    drive_text,
    gains_text,
    mechanics_lines,
    satisfactory_line,
    tolerance_text,
)
from ..runlog.records import evaluation_name

if TYPE_CHECKING:
    from ..record.reader import BagData
    from ..runlog import Record
    from .load import RunReport


def summary_text(rr: RunReport) -> str:
    """The printed summary of one run (see the module docstring)."""
    s, run = rr.summary, rr.run
    opts = ', '.join(f'{k}={v}' for k, v in (run.options or {}).items()) or 'defaults'
    L = [
        f'run {rr.path}: {run.algo} ({opts}), seed {run.seed}, '
        f'budget {run.budget}, bench {run.bench}'
    ]
    L.append(
        f'  outcome: {s.outcome}; {s.evaluations}/{s.budget} evaluations, '
        f'{s.experiments} experiments'
        + ('' if rr.summary_source == 'summary.json' else ' (from results.jsonl)')
    )
    ref = s.reference
    if ref is not None:
        L.append(
            f'  start (hand-tuned) loss: {ref["loss"]:.4f}'
            + (' (aborted)' if ref['aborted'] else '')
            + f': {gains_text(ref["gains"])}'
        )
    b = s.best
    if b is not None:
        rm = (
            f', re-measured {b["remeasured_loss"]:.4f}'
            if b.get('remeasured_loss') is not None
            else ''
        )
        L.append(f'  best loss: {b["loss"]:.4f} ({evaluation_name(b["eval"])}{rm})')
        L.append(f'  best gains: {gains_text(b["gains"])}')
    else:
        L.append('  best loss: none (no evaluation completed without abort)')
    a = s.applied
    if a is not None and (b is None or a['eval'] != b['eval']):
        L.append(
            '  applied at the end: '
            + (
                'the start gains'
                if a['source'] == 'reference'
                else f'{evaluation_name(a["eval"])} (loss {a["loss"]:.4f})'
            )
        )
    L.append(satisfactory_line(s))
    L.append(
        f'  aborted experiments: {s.aborted} of {s.evaluations} evaluations '
        f'(safety faults {s.safety_faults}); lost results re-run: {s.lost}; '
        f'off the paper timing, re-run: {s.timing or 0}{tolerance_text(s)}'
    )
    L.extend(mechanics_lines(s))
    L.extend(_period_lines(rr.records))
    sessions = s.sessions or []
    for i, sess in enumerate(sessions):  # the drive's own counters, per session
        if 'drive' in sess:
            L.extend(
                drive_text(
                    sess['drive'], None if len(sessions) == 1 else f'session {i + 1}'
                ).splitlines()
            )
    rtf = s.real_time_factor
    wall = f'wall time {s.wall_s:.1f} s, ' if s.wall_s is not None else ''
    L.append(
        f'  {wall}{clock_text(run)} {s.sim_s:.1f} s'
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
                f" ({c['elsewhere']} found only in another bag: a later session's replay"
                + (', or --bags' if rr.extra_bags else '')
                + ')'
                if c.get('elsewhere')
                else ''
            )
            + (f', {c["differ"]} DIFFER' if c['differ'] else '')
            + (f', {c["missing"]} not in a bag' if c['missing'] else '')
        )
    L.extend(f'  no signals in the bags for {m}: its plot is left out' for m in rr.missing)
    return '\n'.join(L)


def _period_lines(records: list[Record]) -> list[str]:
    """The drive timeline of the experiments: how their periods were driven."""
    ran = [r for r in records if r.periods is not None]
    if not ran:
        return []
    tot = {k: sum(int(r.periods[k]) for r in ran if r.periods) for k in ('fresh', 'held', 'late')}
    n = sum(tot.values())
    spans = sorted({int(r.steps) for r in ran if r.steps is not None})
    line = (
        f'  drive periods of the {len(ran)} experiments: {n} ({tot["fresh"]} fresh, '
        f'{tot["held"]} held, {tot["late"]} late'
        + (f', {100.0 * (tot["held"] + tot["late"]) / n:.3f} % not fresh' if n else '')
        + '); periods per experiment: '
        + (', '.join(str(x) for x in spans[:4]) + (' ...' if len(spans) > 4 else ''))
    )
    out = [line]
    bad = [r for r in ran if r.periods and (r.periods['held'] or r.periods['late'])]
    for r in bad[:10]:
        p = r.periods or {}
        out.append(
            f'    experiment {r.experiment_id} ({r.kind} {r.eval}, {r.status}): '
            f'{p["fresh"]} fresh, {p["held"]} held, {p["late"]} late'
        )
    if len(bad) > 10:
        out.append(f'    ... and {len(bad) - 10} more experiments with held or late periods')
    return out


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
    L += [
        f'  DAMAGED: {d.describe()}; its messages are left out of every count' for d in bag.damaged
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
