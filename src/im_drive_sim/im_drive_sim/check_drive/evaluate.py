"""check_drive's evaluation of a recording: what the probe saw and did (``Recording``),
judged item by item (``evaluate``). Pure: numpy only, no ROS -- a recording can be saved
and judged again, and the tests judge synthetic ones."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..contract import JOINT_STATE_TOPIC, STATE_FIELDS, STATE_INDEX as F, TOPIC_TYPES
from . import conditions as C, judges as J, response as R, thresholds as TH


def fill_missed(d: np.ndarray) -> np.ndarray:
    """``d`` (rows by step, NaN where no state came) with the interior gaps of at most
    ``MISSED_FILL_MAX`` steps linearly interpolated, column by column: a drive on the wall
    clock that cannot pause skips the periods its late loop missed (it held its command
    over them; docs/real-drive.md), and their values lie between the states around them.
    Longer gaps and the edges stay NaN (missing)."""
    out = d.copy()
    have = np.isfinite(d).all(axis=1)
    idx = np.flatnonzero(have)
    for a, b in itertools.pairwise(idx):
        if 1 < b - a <= MISSED_FILL_MAX + 1:
            w = (np.arange(a + 1, b) - a)[:, None] / (b - a)
            out[a + 1 : b] = d[a] + w * (d[b] - d[a])
    return out


#: Longest run of skipped steps :func:`fill_missed` bridges (10 ms at 5 kHz).
MISSED_FILL_MAX = 50


@dataclass
class Recording:
    """Everything the probe took and sent, and the marks of its phases.

    Arrays (rows in the order taken): ``states`` [n, STATE_FIELDS] (NaN rows where the
    message had another length, ``lengths``), their DDS ``source_ns``/``recv_ns`` and
    ``take_ns`` wall times [ns] and publication ``seq``; ``cmd`` [m, 3] (answers_step, isq*
    [A], load [N m]) published at ``cmd_ns``; ``joints`` [j, 4] (stamp [ns], position
    [rad], velocity [rad/s], effort [N m]). Marks: the state rows (start, end) of the
    ``phases`` 'rate', 'latency' and 'step'; the rate phase's first command ``m_rate0``
    and wall time ``rate_wall`` [s]; the level changes ``trans`` (latency) and
    ``step_trans`` (step response) as (step, level, previous level); the watchdog phase's
    figures ``watchdog``.
    """

    states: np.ndarray
    lengths: np.ndarray
    source_ns: np.ndarray
    recv_ns: np.ndarray
    take_ns: np.ndarray
    seq: np.ndarray
    cmd: np.ndarray
    cmd_ns: np.ndarray
    joints: np.ndarray
    endpoints: dict[str, list[str]]
    ts: float
    ts_ns: int
    isq_max: float
    rated_flux_current: float
    counts_per_rad: float
    amplitude: float
    realtime: bool
    idle_advance: int
    mode_note: str
    m_rate0: int
    rate_wall: float
    trans: list[tuple[int, float, float]]
    step_trans: list[tuple[int, float, float]]
    k_step_end: int
    aborted_why: str
    watchdog: dict[str, Any]
    command_timeout: float
    command_timeout_source: str
    phases: dict[str, tuple[int, int]]
    #: the +A and -A steps' commanded length [periods]
    step_steps: int = 0

    def rows_by_step(self, first: int, last: int, filled: bool = False) -> np.ndarray:
        """States of steps first..last as a dense array indexed by step - first (NaN where
        a step was not received; the first copy of a re-sent state); ``filled``: in real
        time with the short gaps bridged (:func:`fill_missed`)."""
        out = np.full((last - first + 1, len(STATE_FIELDS)), np.nan)
        s = self.states[self.lengths == len(STATE_FIELDS)]
        k = s[:, F['step_index']].astype(np.int64)
        sel = (k >= first) & (k <= last)
        for row, kk in zip(s[sel][::-1], k[sel][::-1], strict=True):
            out[kk - first] = row
        return fill_missed(out) if filled and self.realtime else out


def evaluate(rec: Recording, kept_up: dict | None = None) -> list[TH.Item]:
    """The six items, in ``ITEMS`` order, judged from ``rec``. ``kept_up``, when given,
    receives the check's own measures per phase (:mod:`.conditions`)."""
    realtime, step_trans, k_step_end = rec.realtime, rec.step_trans, rec.k_step_end
    items = {'topics': J.judge_topics(rec.endpoints)}

    bound = TH.CURRENT_BOUND_FACTOR * math.hypot(rec.isq_max, rec.rated_flux_current)
    sp = J.state_field_problems(rec.states, rec.lengths, rec.seq, rec.ts_ns, realtime, bound)
    k_first = step_trans[0][0] if step_trans else k_step_end
    dense = rec.rows_by_step(k_first, k_step_end + 1, filled=True)
    motion = dense[np.isfinite(dense[:, F['theta_meas']])]
    if len(motion) > 20 and np.all(np.diff(motion[:, 0]) == 1):
        th = motion[:, F['theta_meas']]
        ratio = J.units_ratio(th, motion[:, F['omega_meas']], rec.ts)
        motion_counts = float(np.ptp(th) * rec.counts_per_rad)
    else:
        ratio, motion_counts = math.nan, 0.0
    joint_types = rec.endpoints[JOINT_STATE_TOPIC]
    ok_rows = rec.lengths == len(STATE_FIELDS)
    jp = (
        J.joint_state_problems(rec.joints.reshape(-1, 4), rec.states[ok_rows], rec.ts_ns)
        if joint_types and all(t == TOPIC_TYPES[JOINT_STATE_TOPIC] for t in joint_types)
        else None
    )
    lateness = DriveLateness(rec)
    # the units ratio integrates omega over k Ts: doubted where the drive's samples were
    # late (any ratio a late sample can bend it to), or where states are missing and the
    # line across them stands in for the motion (any ratio)
    host, doubt_band = '', TH.UNITS_LATE_BAND
    late_share, missing_share = lateness.shares(k_first, k_step_end)
    if realtime and late_share > TH.DRIVE_LATE_SHARE_MAX:
        host = lateness.describe(k_first, k_step_end)
        if missing_share > TH.DRIVE_LATE_SHARE_MAX:
            doubt_band = (0.0, math.inf)
    items['fields'] = J.judge_fields(sp, ratio, motion_counts, jp, host=host, doubt_band=doubt_band)

    declared = rec.states[ok_rows, F['command_delay']]
    d_declared = int(np.median(declared)) if len(declared) else 1
    excess = C.excess_delay(rec.take_ns, rec.source_ns)
    conds = {
        name: C.phase_conditions(
            rec.states, rec.lengths, rec.seq, excess, d_declared, slice(r0, r1)
        )
        for name, (r0, r1) in rec.phases.items()
    }
    if kept_up is not None:
        kept_up.update({k: c.as_dict() for k, c in conds.items()})

    def busy(phase: str) -> str:
        c = conds.get(phase)
        return C.busy_reason(c) if c is not None and realtime else ''

    steps = rec.states[:, F['step_index']]
    r0, r1 = rec.phases['rate']
    if realtime:
        stats = J.period_stats(steps[r0:r1], rec.source_ns[r0:r1], rec.ts, rec.seq[r0:r1])
        items['rate'] = J.judge_rate_realtime(stats, rec.ts, rec.mode_note, busy('rate'))
    else:
        per_s = np.count_nonzero(np.diff(steps[r0:r1]) > 0) / rec.rate_wall
        items['rate'] = J.judge_rate_lockstep(
            steps, rec.take_ns, rec.cmd[:, 0], rec.cmd_ns, rec.idle_advance, per_s, rec.mode_note
        )

    # latency: wall time command(k) -> state k+1 received, and the onset of each change
    by_step: dict[int, int] = {}  # step -> the row of its first copy
    for i in np.flatnonzero(ok_rows):
        by_step.setdefault(int(steps[i]), int(i))
    wall = []
    for j in range(rec.m_rate0, len(rec.cmd)):
        k = int(rec.cmd[j, 0])
        row = by_step.get(k + 1)
        if k >= 0 and row is not None:
            wall.append((rec.recv_ns[row] - rec.cmd_ns[j]) * 1e-9)
    delays: list[int | None] = []
    labels: list[int | None] = []
    complete: list[bool] = []
    on_time: list[bool] = []
    for k0, level, prev in rec.trans[1:] + step_trans[1:]:
        d = rec.rows_by_step(k0 - 20, k0 + 25, filled=True)
        # judged only with every state from 16 before to 21 after (filled in real time)
        complete.append(bool(np.isfinite(d[4:42]).all()))
        delays.append(R.onset_delay(d[:, F['isq']], 20, level - prev))
        labels.append(R.label_delay(d[:, F['applied_step']], 20, k0))
        x, y = delays[-1], labels[-1]
        # the drive's periods from the change to where it shows and is labelled
        on_time.append(
            not realtime
            or (x is not None and y is not None and lateness.on_time(k0, k0 + max(x, y) + 1))
        )
    items['latency'] = R.judge_latency(
        delays,
        np.array(wall),
        realtime,
        declared=d_declared,
        labels=labels,
        complete=complete,
        busy=busy('latency'),
        on_time=on_time,
        host=lateness.describe(),
    )

    # step response
    a, counts_per_rad = rec.amplitude, rec.counts_per_rad
    if len(step_trans) >= 4 and not rec.aborted_why:
        metrics = []
        for (k0, level, prev), (k1, _, _) in itertools.pairwise(step_trans[1:4]):
            d = rec.rows_by_step(k0 - 20, k1, filled=True)
            delay = R.onset_delay(d[:, F['isq']], 20, level - prev)
            metrics.append(R.step_metrics(d[20 : k1 - k0 + 20], level, prev, rec.ts, delay))
        gaps, late = step_busy(rec, d_declared)
        items['step_response'] = R.judge_step_response(
            metrics[0], metrics[1], a, counts_per_rad, busy=late, gaps=gaps
        )
    else:
        figures = ('rise_s', 'steady_error', 'torque_per_amp', 'accel')
        nan = {**dict.fromkeys(figures, math.nan), 'duration_s': 0.0}
        item = R.judge_step_response(
            nan, nan, a, counts_per_rad, rec.aborted_why or 'step test incomplete'
        )
        held = abort_busy(rec, d_declared) if rec.aborted_why and realtime else ''
        if held:
            # the drive held a step longer than commanded (the check answered late): its
            # speed ran past the limit through no fault of the drive
            item = item.undecided(f'{held}: the step it was given was longer than commanded')
        elif not rec.aborted_why:
            # the check answered too few of the step's states to change its level four
            # times: it fell behind (descheduled, or the link held the states), not the
            # drive -- nothing was measured to judge
            c = conds.get('step')
            seen = C.busy_reason(c) if c is not None else ''
            late = f'; took states up to {c.late_max_s * 1e3:.1f} ms late' if c else ''
            item = item.undecided(
                f"the check answered {len(step_trans)} of the step test's 4 level changes "
                f'(it fell behind{late}{"; " + seen if seen else ""})'
            )
        items['step_response'] = item

    wd = rec.watchdog
    if realtime:
        items['watchdog'] = R.judge_watchdog_realtime(
            wd['t_act'],
            wd['t_zero'],
            rec.command_timeout,
            wd['resumed_s'],
            rec.command_timeout_source,
            wd['aborted'],
            busy=watchdog_busy(rec, d_declared, excess),
        )
    else:
        items['watchdog'] = R.judge_watchdog_lockstep(
            wd['silence_s'], wd['advanced'], wd['resumed_s']
        )
    return [items[name] for name in TH.ITEMS]


class DriveLateness:
    """The drive's periods during the check, on its own clock
    (:func:`~.conditions.drive_lateness`): which were on time, and the share late."""

    def __init__(self, rec: Recording) -> None:
        ok = rec.lengths == len(STATE_FIELDS)
        steps, source = rec.states[ok, F['step_index']], rec.source_ns[ok]
        clock = J.clock_period(steps, source)  # [s per step]; NaN with too few states
        period_ns = clock * 1e9 if math.isfinite(clock) else float(rec.ts_ns)
        self.late_s, self.first = C.drive_lateness(steps, source, period_ns)

    def _window(self, k0: int | None, k1: int | None) -> np.ndarray:
        """The lateness of periods k0..k1 (all: None)."""
        if k0 is None or k1 is None:
            return self.late_s
        a, b = max(0, k0 - self.first), max(0, k1 + 1 - self.first)
        return self.late_s[a:b]

    def on_time(self, k0: int, k1: int) -> bool:
        """Every period k0..k1 published, at most DRIVE_LATE_MAX_S late."""
        w = self._window(k0, k1)
        return len(w) == k1 - k0 + 1 and bool(np.all(w <= TH.DRIVE_LATE_MAX_S))

    def shares(self, k0: int | None = None, k1: int | None = None) -> tuple[float, float]:
        """The fractions of the periods k0..k1 (all: None) late or not published, and not
        published (a NaN lateness)."""
        w = self._window(k0, k1)
        if len(w) == 0:
            return 0.0, 0.0
        return float(np.mean(~(w <= TH.DRIVE_LATE_MAX_S))), float(np.mean(np.isnan(w)))

    def describe(self, k0: int | None = None, k1: int | None = None) -> str:
        """The drive's host in words, over k0..k1 (all: None)."""
        w = self._window(k0, k1)
        skipped = int(np.count_nonzero(np.isnan(w)))
        late = int(np.count_nonzero(w > TH.DRIVE_LATE_MAX_S))
        return (
            f"the drive's host: {late + skipped} of its {len(w)} periods "
            f'({self.shares(k0, k1)[0] * 100:.1f} %) started > {TH.DRIVE_LATE_MAX_S * 1e6:.0f} '
            f'us late or were not received ({skipped})'
        )


def step_busy(rec: Recording, declared: int) -> tuple[str, str]:
    """Why the step the drive was given may not be the one commanded (('', '') when it
    was), during the +A and -A steps: (more than STEP_GAP_MAX consecutive states missing
    or states under the drive's watchdog, commands that reached the drive later than
    STEP_LAG_FRACTION of the step's duration by its labels)."""
    if len(rec.step_trans) < 4:
        return '', ''
    k0, k1, k2 = rec.step_trans[1][0], rec.step_trans[2][0], rec.step_trans[3][0]
    d = rec.rows_by_step(k0, k2 + 2)
    have = np.isfinite(d).all(axis=1)
    gaps = late = ''
    idx = np.flatnonzero(have)
    gap = int(np.diff(np.concatenate(([-1], idx, [len(d)]))).max()) - 1 if len(d) else 0
    if gap > TH.STEP_GAP_MAX:
        gaps = f'{gap} consecutive states missing in the step'
    lag = C.command_lag(d[have], declared)
    if len(lag) and lag.max() > TH.STEP_LAG_FRACTION * (k1 - k0):
        late = (
            f'commands reached the drive up to {lag.max():.0f} periods late during the step '
            f'(in time: {np.mean(lag <= 0) * 100:.0f} %)'
        )
    # states under the drive's watchdog (applied_step -1): no command reached it for its
    # command_timeout -- the check fell silent (descheduled) or the link held the
    # commands -- and it held zero current where the step was commanded: the step it was
    # given is not the one commanded, its rise included
    held = int(np.count_nonzero(d[have][:, F['applied_step']] < 0))
    if held:
        gaps += (
            f"{'; ' if gaps else ''}the drive's watchdog held zero current over {held} of the "
            f"step's {int(np.count_nonzero(have))} states (no command reached it in time)"
        )
    return gaps, late


def abort_busy(rec: Recording, declared: int) -> str:
    """Why a step test the check aborted (overspeed) may not be the drive's doing ('' when
    it is): from the +A step on, the commands reached the drive later than
    STEP_LAG_FRACTION of the step's commanded length, by its labels -- it held a level
    that much longer than commanded, and sped up for it."""
    i0, i1 = rec.phases.get('step', (0, 0))
    if len(rec.step_trans) < 2 or rec.step_steps <= 0 or i1 <= i0:
        return ''
    rows = rec.states[i0:i1][rec.lengths[i0:i1] == len(STATE_FIELDS)]
    rows = rows[rows[:, F['step_index']] >= rec.step_trans[1][0]]
    lag = C.command_lag(rows, declared)
    if not len(lag) or lag.max() <= TH.STEP_LAG_FRACTION * rec.step_steps:
        return ''
    return (
        f'commands reached the drive up to {lag.max():.0f} periods late before the abort '
        f'(the step: {rec.step_steps} periods)'
    )


def watchdog_busy(rec: Recording, declared: int, excess: np.ndarray) -> str:
    """Why the watchdog's timing cannot be trusted ('' when it can): the drive saw a
    silence in the commands before the check fell silent (a command lag over half the
    timeout: it may have tripped early), the test's commands never reached it (neither
    its labels nor its current show them), the states stop before the silence was long
    enough to judge, or the resume command and its answer took more than 50 ms to
    cross while the check was late."""
    wd, why = rec.watchdog, []
    r0, r1 = wd.get('rows_on', (0, 0))
    q0 = wd.get('rows_resume', (r1, r1))[0]
    seen = rec.states[r0:q0][rec.lengths[r0:q0] == len(STATE_FIELDS)]
    if wd.get('ref') == 'published' and not np.any(seen[:, F['isq']] > rec.amplitude / 4):
        # the drive never showed the test's command applied, nor carried its current:
        # the commands did not reach it (its watchdog may have held zero before the test
        # began), so the fall and the resume were not its answer to the test
        newest = int(seen[:, F['applied_step']].max()) if len(seen) else -1
        why.append(
            "the drive never carried the watchdog test's current nor showed its commands "
            f"applied (the newest it showed answered step {newest}, the test's last "
            f'{wd.get("k_last")}; -1: none): they did not reach it'
        )
    lag = C.command_lag(rec.states[r0:r1], declared)
    if len(lag) and lag.max() * rec.ts > rec.command_timeout / 2:
        why.append(
            f'commands reached the drive up to {lag.max() * rec.ts * 1e3:.1f} ms late before '
            'the silence'
        )
    k_last, ref_step = wd.get('k_last'), wd.get('ref_step')
    if k_last is not None and ref_step is not None:
        # the times are from the first state received that shows the last command
        # applied; shown this long after it was due (the command came late, or the states
        # between were not received) the watchdog's start is not known that well
        late_s = (ref_step - declared - k_last) * rec.ts
        if late_s > TH.WATCHDOG_REF_SLACK * rec.command_timeout:
            why.append(
                f'the first state received showing the last command applied came '
                f'{late_s * 1e3:.1f} ms after it was due (the command came late, or the '
                "states between were not received): the watchdog's start is not known"
            )
    hi = R.watchdog_limits(rec.command_timeout)[1]
    t_act, t_before = wd.get('t_act'), wd.get('t_before')
    if t_act is not None and t_before is not None and t_before <= hi < t_act:
        # seen falling only after states were lost: it may have begun in time
        why.append(
            f'the states from {t_before * 1e3:.1f} to {t_act * 1e3:.1f} ms after the last '
            'command were not received: the fall began between the two'
        )
    if wd.get('t_zero') is None and wd.get('coverage_s', math.inf) < hi:
        why.append(f'the states received cover only {wd["coverage_s"] * 1e3:.0f} ms of the silence')
    if wd.get('resumed_s') is None:
        q0, q1 = wd.get('rows_resume', (0, 0))
        c = C.phase_conditions(rec.states, rec.lengths, rec.seq, excess, declared, slice(q0, q1))
        reason = C.busy_reason(c)
        if reason:
            why.append(f'while resuming, {reason}')
    return '; '.join(why)


def json_ready(obj: Any) -> Any:
    """``obj`` ready for ``json.dump`` (the ``--json`` report): non-finite floats ->
    None, numpy scalars -> Python, dicts and sequences converted throughout."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj
