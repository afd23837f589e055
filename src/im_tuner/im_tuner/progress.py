"""What the tuner prints: progress lines while it runs, and the run summary at the end."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from im_controller.config import GAIN_NAMES, GAIN_UNITS

# benches, not tuner_cli (rclpy), and the tuning loop only for its type: the report
# imports drive_text from here and must start without rclpy, pycma or scipy
from .benches import is_simulated
from .runlog.records import evaluation_name

if TYPE_CHECKING:
    from .runlog import Record, RunConfig, Summary
    from .tuning import TuningRun


class Eta:
    """The time left of a job, from its rate since the first progress call (its start-up
    is not work done): ``ETA m:ss``, or ``ETA -:--`` until it has a rate (one more item
    done and a second gone). One clock for the tuner's, the study's and replay's lines."""

    MIN_S = 1.0  #: [s] of progress before a rate is trusted

    def __init__(self) -> None:
        self._t0: float | None = None
        self._done0 = 0

    def __call__(self, done: int, total: int) -> str:
        now = time.monotonic()
        if self._t0 is None:
            self._t0, self._done0 = now, done
        dt, dd = now - self._t0, done - self._done0
        if dd <= 0 or dt < self.MIN_S:
            return 'ETA -:--'
        left = round(dt / dd * max(total - done, 0))
        return f'ETA {left // 60}:{left % 60:02d}'


class Line:
    """One progress line on ``stream`` (the tuner's, the study's, replay's): redrawn in place
    on a terminal (at most every ``REDRAW_S``), otherwise printed each time ``done`` crosses
    another 1/``parts`` of ``total``, and at the end; notes between; nothing with ``quiet``
    but warnings."""

    REDRAW_S = 0.2  #: [s] between two redraws on a terminal

    def __init__(self, quiet: bool, parts: int, stream=sys.stderr) -> None:
        self.quiet, self.parts, self.stream = quiet, parts, stream
        self.tty = stream.isatty()
        self.eta = Eta()
        self._part = 0  # the last 1/parts of the total printed (not a terminal)
        self._drawn = -self.REDRAW_S
        self._open = False

    @staticmethod
    def bar(done: int, total: int, width: int = 24) -> str:
        fill = width * done // total
        return f'[{"#" * fill}{"." * (width - fill)}]'

    def update(self, done: int, total: int, text: str) -> None:
        if self.quiet:
            return
        end, part, now = done >= total, self.parts * done // total, time.monotonic()
        if self.tty and (end or now - self._drawn >= self.REDRAW_S):
            self._drawn = now
            self.stream.write('\r\x1b[2K' + text + ('\n' if end else ''))
            self.stream.flush()
            self._open = not end
        elif not self.tty and (end or part > self._part):
            self._part = part
            print(text, file=self.stream, flush=True)

    def warn(self, text: str) -> None:
        """Printed even with --quiet: something went wrong that the user must know."""
        self.quiet, quiet = False, self.quiet
        try:
            self.note(text)
        finally:
            self.quiet = quiet

    def note(self, text: str) -> None:
        if self.quiet:
            return
        self.close()
        print(text, file=self.stream, flush=True)

    def close(self) -> None:
        if self._open:
            self.stream.write('\n')
            self.stream.flush()
            self._open = False


class Progress(Line):
    """The tuner's line: evaluation i/N, best and last loss, ETA (a line every 5 % of the
    budget off a terminal)."""

    def __init__(self, algo: str, budget: int, quiet: bool, stream=sys.stderr) -> None:
        super().__init__(quiet, 20, stream)
        self.algo, self.budget = algo, budget

    def __call__(self, kind: str, rec: Record, run: TuningRun) -> None:
        if self.quiet:
            return
        if kind != 'eval':  # the reference, a re-measurement
            what = 'start controller (reference) loss'
            if kind == 'remeasure':
                what = f're-measured {evaluation_name(rec.eval)}:'
            self.note(f'{self.algo}: {what} {self._fmt(rec)}')
            return
        st, i, n = run.state, run.state.evals, self.budget
        if self.eta._t0 is None:  # the first evaluation's time is in its rate
            self.eta(i - 1, n)
        best = f'{st.best["loss"]:.4f}' if st.best else '-'
        self.update(
            i,
            n,
            f'{self.algo} {self.bar(i, n)} eval {i}/{n}  best {best}  last {self._fmt(rec)}  '
            f'{self.eta(i, n)}',
        )

    @staticmethod
    def _fmt(rec: Record) -> str:
        if rec.status == 'lost':
            return 'lost (re-run)'
        if rec.status == 'timing':
            return f'{rec.reason} (re-run)'
        return f'{rec.loss:.4f}' + (f' (aborted: {rec.reason})' if rec.aborted else '')

    def steps(self, what: str, every_s: float = 10.0) -> Callable[[int, int], None]:
        """A ``(done, total)`` callback for a long step before the search (the plant's
        replay on --resume): ``<what>: done/total, ETA`` at most every ``every_s`` s
        and at the end."""
        eta, last = Eta(), [time.monotonic()]

        def report(done: int, total: int) -> None:
            left = eta(done, total)
            now = time.monotonic()
            if done == total or now - last[0] >= every_s:
                last[0] = now
                self.note(f'{what}: {done}/{total}, {left}')

        return report


def mechanics_lines(s: Summary) -> list[str]:
    """The drive the start identified (against the file's) and the standstill ripple of
    isq* of the start and of the applied gains: lines for the summary and the report."""
    L: list[str] = []
    i = s.identification
    if i:
        L.append(
            f'  identified from the start: J {i["J"]:.4g} +- {i["J_sd"]:.2g} kg m^2 '
            f"({i['J'] / i['J_file']:.2f}x the file's {i['J_file']:.4g}), Kt {i['Kt']:.4g} "
            f'+- {i["Kt_sd"]:.2g} N m/A (file {i["Kt_file"]:.4g}), B {i["B"]:.3g} N m s/rad, '
            f'Tc {i["Tc"]:.3g} +- {i["Tc_sd"]:.2g} N m'
        )
    if s.screened is not None:
        L.append(
            f'  abort screen: {s.screened} candidate(s) predicted to abort on the identified '
            'model, not run on the drive'
        )
    r = s.ripple
    if r:
        rated = r.get('rated_isq_a')

        def one(d: dict[str, Any] | None) -> str:
            if not d:
                return 'not measured'
            rms = [d.get('rms_after_move'), d.get('rms_after_load')]
            pp = [d.get('pp_after_move'), d.get('pp_after_load')]
            f = lambda v: '-' if v is None else f'{v:.3f}'  # noqa: E731
            pct = (
                f' ({max(v for v in rms if v is not None) / rated:.1%} of rated isq)'
                if rated and any(v is not None for v in rms)
                else ''
            )
            return f'{f(rms[0])}/{f(rms[1])} A rms, {f(pp[0])}/{f(pp[1])} A p-p{pct}'

        L.append(
            f'  standstill ripple of isq* (after the move/after the load): start '
            f'{one(r.get("start"))}; applied {one(r.get("applied"))}'
        )
        L += _limit_lines(r)
    return L


def _limit_lines(r: dict[str, Any]) -> list[str]:
    """The ripple limit's line of the summary."""
    limit, bound = r['limit'], r['bound']
    if limit is None:
        return ['  ripple limit: off']
    if not bound:
        return [
            f"  ripple limit {limit:g}x the start's: not applied (the start's ripple not measured)"
        ]
    b = '/'.join(
        f'{bound[k]:.3f}' if k in bound else '-' for k in ('rms_after_move', 'rms_after_load')
    )
    if r.get('fallback'):
        what = 'no evaluated point within it: the start is applied'
    else:
        what = (
            'applied gains within it' if r.get('applied_within') else 'applied gains NOT within it'
        )
    if r.get('changed'):
        what += f'; it kept out evaluation{"s" if len(r["excluded"]) > 1 else ""} ' + ', '.join(
            str(i) for i in r['excluded']
        )
    else:
        what += '; it changed nothing'
    return [f"  ripple limit {limit:g}x the start's ({b} A rms): {what}"]


def gains_text(g: dict[str, float]) -> str:
    return ', '.join(f'{n} {g[n]:.6g} {GAIN_UNITS[n]}' for n in GAIN_NAMES)


def satisfactory_line(s: Summary) -> str:
    sat = s.evaluations_to_satisfactory
    return f'  satisfactory (loss <= {s.satisfactory_loss:g}): ' + (
        f'after {sat} evaluations' if sat else 'not reached'
    )


def clock_text(run: RunConfig) -> str:
    """What the experiments' time is: a real drive's (a hardware class on the composed
    bench too: benches.is_simulated) is the drive's, not simulated."""
    if is_simulated(run.bench, run.drive):
        return 'simulated experiment time'
    return "experiment time (the drive's clock)"


def format_summary(s: Summary, run: RunConfig, rundir: Path) -> str:
    """The summary the tuner prints at the end of a session (summary.json and run.yaml)."""
    L = [
        f'im_tuner: {run.algo}, {s.evaluations}/{s.budget} evaluations, seed '
        f'{run.seed}: {s.outcome}'
    ]
    ref = s.reference
    if s.best is not None:
        b = s.best
        rm = f'; re-measured {b["remeasured_loss"]:.4f}' if b['remeasured_loss'] is not None else ''
        L.append(f'  best loss:   {b["loss"]:.4f} ({evaluation_name(b["eval"])}{rm})')
        L.append(f'  best gains:  {gains_text(b["gains"])}')
    else:
        L.append('  best loss:   none (no evaluation completed without abort)')
    if ref is not None:
        L.append(
            f'  start (hand-tuned) loss: {ref["loss"]:.4f}'
            + (' (aborted)' if ref['aborted'] else '')
        )
    a = s.applied
    if a is not None and a.get('on_controller') is False:
        L.append(
            '  NOT applied: the controller could not be reached at the end; its gains are '
            'whatever it had (best gains above)'
        )
    elif a is not None:
        if a['source'] == 'reference':
            L.append('  applied: the start gains (no evaluation beat them)')
        else:
            rm = (
                f', re-measured {a["remeasured_loss"]:.4f}'
                if a['remeasured_loss'] is not None
                else ''
            )
            L.append(
                f'  applied on the controller: {evaluation_name(a["eval"])} (loss {a["loss"]:.4f}'
                f'{rm})'
                + ('' if s.best and a['eval'] == s.best['eval'] else f': {gains_text(a["gains"])}')
            )
    L.append(satisfactory_line(s))
    L.extend(mechanics_lines(s))
    sessions = s.sessions or []
    outside = sum(len(p.get('faults_outside', [])) for p in sessions)
    L.append(
        f'  aborted experiments: {s.aborted} of {s.evaluations} (safety faults '
        f'{s.safety_faults}'
        + (f', {outside} of them met between experiments' if outside else '')
        + f'); lost results re-run: {s.lost}; off the paper '
        f'timing, re-run: {s.timing or 0}{tolerance_text(s)}'
    )
    rtf = s.real_time_factor
    L.append(
        f'  wall time {s.wall_s:.1f} s (tuning loop {s.loop_wall_s:.1f} s); '
        f'{clock_text(run)} {s.sim_s:.1f} s; real-time factor ' + (f'{rtf:.2f}' if rtf else '-')
    )
    if s.optimizer_us_per_eval is not None:
        L.append(f'  optimiser ask+tell: {s.optimizer_us_per_eval:.1f} us per evaluation')
    for i, p in enumerate(sessions):
        if 'drive' in p:
            L.append(
                drive_text(
                    p['drive'],
                    None
                    if len(sessions) == 1
                    else 'this session'
                    if i == len(sessions) - 1
                    else f'session {i + 1}' + (f', {p["bag"]}' if p.get('bag') else ''),
                )
            )
    bags = [
        b
        for p in sessions
        for b in [p.get('bag'), *(m['bag'] for m in p.get('more_bags', []))]
        if b
    ]
    L.append(
        f'  run directory: {rundir}  (run.yaml, results.jsonl, summary.json'
        + ''.join(f', {b}/' for b in bags)
        + ')'
    )
    if len(sessions) > 1:
        rep = sum(p.get('replayed', 0) for p in sessions)
        L.append(
            f'  sessions: {len(sessions)} (resumed; {rep} experiments replayed to '
            'restore the simulated plant)'
            if rep
            else f'  sessions: {len(sessions)} (resumed)'
        )
    if s.report_command:
        L.append(f'  report (summary, plots, CSV): {s.report_command}')
    L.extend(f'  what to do: {text}' for text in s.what_to_do or [])
    return '\n'.join(L)


def drive_text(d: dict[str, Any] | None, which: str | None) -> str:
    """One summary line of the drive's own counters (drive/status) in session ``which``
    (None: the run has one session)."""
    head = '  drive' + (f' ({which})' if which else '')
    if d is None:
        return f'{head}: no drive/status received (its counters are unknown)'

    def n(k: str) -> str:
        v = d.get(k)
        return '-' if v is None else (f'{v:.0f}' if isinstance(v, float) else str(v))

    if d.get('mode') == 'realtime':
        text = (
            f'{head} (real time): {n("steps")} periods, overruns {n("overruns")} (worst '
            f'period-start lateness {n("max_lateness_us")} us), late commands {n("late")}, '
            f'held {n("held")}, ignored {n("stale_ignored")}, watchdog trips '
            f'{n("watchdog_trips")}'
            + (f', command delay {n("command_delay")}' if 'command_delay' in d else '')
            + (f'; delay probe at start: {d["delay_probe"]}' if 'delay_probe' in d else '')
        )
    else:
        text = (
            f'{head} ({d.get("mode")}): {n("steps")} steps, commands ignored '
            f'{n("stale_ignored")}, states re-sent {n("republished")}'
        )
    if d.get('per_session'):
        # a long-lived (external) drive: its counters ran before this session
        text += "; this session's share: the drive's counters at its end minus at its start"
        if 'max_lateness_us_at_most' in d:
            text = text.replace(
                'lateness - us', f'lateness <= {d["max_lateness_us_at_most"]:.0f} us'
            )
    elif d.get('restarted'):
        text += '; the drive restarted during the session: its counters since then'
    elif d.get('per_session') is False:
        text += "; the drive's counters since it started (none at the session's start)"
    if d.get('level', 0) >= 2:
        text += f'; last status ERROR: {d.get("message")}'
    loop = d.get('loop')
    if loop and loop.get('period_work_us'):
        w, a = loop['period_work_us'], loop['controller_answer_us']
        text += (
            f'\n{head} (composed loop): per-period work p50 {w["p50"]:.0f} / p99 '
            f'{w["p99"]:.0f} / max {w["max"]:.0f} us of {200} us; controller answer p50 '
            f'{a["p50"]:.0f} / p99 {a["p99"]:.0f} us; states unanswered in their period '
            f'{loop["answers_missed"]}'
        )
        late = loop.get('lateness_us')
        if late:
            text += f'; period-start lateness p50 {late["p50"]:.0f} / p99 {late["p99"]:.0f} us'
        if loop.get('outbox_lost'):
            text += f'; NOT DELIVERED {loop["outbox_lost"]} messages (summary: loop.outbox)'
    return text


def tolerance_text(s: Any) -> str:
    """The timing tolerance and the held periods of the counted experiments, for a
    summary line ('' for a run without a tolerance, or without a counted experiment)."""
    h, tol = s.held_periods, s.timing_tolerance
    if tol is None or not h:
        return ''
    text = f' (tolerance {tol} held + late periods per experiment'
    if h.get('with_held'):
        text += (
            f'; {h["with_held"]} of the {h["counted"]} counted experiments had some, '
            f'at most {h["max"]}'
        )
    return text + ')'
