"""check_drive's pure judges of the drive's response to commands: the ``latency`` item
(how many periods a command takes to act, against its ``applied_step`` labels), the
``step_response`` item (rise time, steady-state error, torque and acceleration) and the
``watchdog`` item. Numpy arrays in, an :class:`~.thresholds.Item` out; no ROS.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..contract import STATE_INDEX as F
from . import thresholds as TH


def onset_delay(x: np.ndarray, i0: int, delta_ref: float, max_delay: int = 20) -> int | None:
    """Steps after sample ``i0`` (the state answered by a command changing the reference by
    ``delta_ref``) until ``x`` first leaves its course -- the straight line fitted to samples
    i0-4..i0 -- by more than max(ONSET_FRACTION |delta_ref|, 8 x the median |second
    difference| over the 16 samples before i0, a noise level). None when it never does
    within ``max_delay`` steps (or samples are missing)."""
    if i0 < 16 or i0 + 1 >= len(x):
        return None
    pre = x[i0 - 16 : i0 + 1]
    if not np.isfinite(pre).all():
        return None
    noise = float(np.median(np.abs(np.diff(pre, 2))))
    thr = max(TH.ONSET_FRACTION * abs(delta_ref), 8.0 * noise)
    slope, level = np.polyfit(np.arange(-4, 1), x[i0 - 4 : i0 + 1], 1)
    for d in range(1, min(max_delay, len(x) - 1 - i0) + 1):
        if not math.isfinite(x[i0 + d]):
            return None
        if abs(x[i0 + d] - (level + d * slope)) > thr:
            return d
    return None


def label_delay(applied: np.ndarray, i0: int, k0: int, max_delay: int = 20) -> int | None:
    """The first state after row ``i0`` (state k0) whose ``applied`` (applied_step) is
    k0 or newer, as a delay d (row i0 + d); None when none does within ``max_delay`` rows
    (or a row is missing)."""
    for d in range(1, min(max_delay, len(applied) - 1 - i0) + 1):
        a = applied[i0 + d]
        if not math.isfinite(a):
            return None
        if a >= k0:
            return d
    return None


def judge_latency(
    delays: Sequence[int | None],
    wall_s: np.ndarray,
    realtime: bool,
    declared: int = 1,
    labels: Sequence[int | None] | None = None,
    complete: Sequence[bool] | None = None,
    busy: str = '',
    on_time: Sequence[bool] | None = None,
    host: str = '',
) -> TH.Item:
    """``delays``: per command changing the reference, the state (k + d) in which it first
    showed; ``wall_s``: command published -> next state received [s]; ``declared``: the
    drive's command_delay; ``labels``: per change, the first state (k + l) whose
    applied_step is the changing command's or newer (None: not judged); ``complete``: per
    change, whether every state around it came (False: a None delay is not 'never', the
    change is not judged); ``busy``: why the check's timing cannot be trusted ('');
    ``on_time``: per change, whether every period of the drive from the change to where
    it showed and was labelled started on time (False: its label is not judged -- a
    period that started late may act a period late through no fault of the drive);
    ``host``: the drive's host in words, for the reason when too few were. The rule, and
    when it is inconclusive: docs/check-drive.md, ``latency``."""
    n = len(delays)
    whole = list(complete) if complete is not None else [True] * n
    lab = list(labels) if labels is not None else [None] * n
    limit = declared + (TH.TRANSPORT_SLACK_REALTIME if realtime else 0)
    punctual = list(on_time) if on_time is not None else [True] * n
    usable = [(x, y) for x, y, c in zip(delays, lab, whole, strict=False) if c]
    # the labels: judged on the changes whose drive periods were all on time
    labelled = [(x, y) for x, y, c, t in zip(delays, lab, whole, punctual, strict=False) if c and t]
    gaps = n - len(usable)  # changes with states missing around them

    def came_in_time(y: int | None) -> bool:
        # by the drive's labels (real time): applied by k+d+1; without labels, assumed
        return not realtime or labels is None or (y is not None and y <= limit)

    # complete, came in time, and isq never moved: the drive ignored the command
    missing = sum(x is None and came_in_time(y) for x, y in usable)
    late = sum(not came_in_time(y) for _, y in usable)
    d = np.array([x for x, y in usable if x is not None and came_in_time(y)], dtype=float)
    shown = np.array([x for x, _ in usable if x is not None], dtype=float)
    med = float(np.median(wall_s)) if len(wall_s) else math.nan
    p99 = float(np.percentile(wall_s, 99)) if len(wall_s) else math.nan
    if realtime:
        effect_ok = len(d) >= 3 and float(np.percentile(d, 25, method='lower')) <= limit
    else:
        effect_ok = len(d) >= 3 and bool(np.all(d == limit)) and missing == 0
    judged = [(x, y) for x, y in labelled if x is not None and y is not None]
    unpunctual = sum(
        not t and x is not None and y is not None
        for x, y, t in zip(delays, lab, punctual, strict=False)
    )
    honest = sum(x == y for x, y in judged)
    slower = sum(x > y for x, y in judged)
    if labels is None:
        labels_ok = True
    elif realtime:
        labels_ok = len(judged) >= 3 and slower <= TH.LABEL_SLOWER_MAX_REALTIME * len(judged)
    else:
        labels_ok = len(judged) == len(shown) and honest == len(judged)
    wall_ok = med <= TH.LATENCY_MEDIAN_MAX and p99 <= TH.LATENCY_P99_MAX
    ok = effect_ok and labels_ok and wall_ok
    hist = ', '.join(f'k+{int(v)}: {int(np.sum(shown == v))}' for v in np.unique(shown))
    figures = (
        f'command -> next state median {med * 1e6:.0f} us, p99 {p99 * 1e6:.0f} us; '
        f'takes effect in {hist or "-"}' + (f', never: {missing}' if missing else '')
    )
    if late:
        figures += f' ({late} reached the drive late, by its labels: not judged against k+{limit})'
    if gaps:
        figures += f'; {gaps} not judged (states missing around them)'
    if labels is not None:
        figures += f'; declared delay {declared}: {honest}/{len(judged)} where applied_step says'
        if slower:
            figures += f', {slower} later (slower than declared)'
        if unpunctual:
            figures += f' ({unpunctual} not judged: a period of the drive started late around them)'
    when = f' (fastest quarter by k+{limit})' if realtime else ' always'
    expected = (
        f'effect in k+{declared}{when}, never after applied_step says, '
        f'median <= {TH.LATENCY_MEDIAN_MAX * 1e3:g} ms, '
        f'p99 <= {TH.LATENCY_P99_MAX * 1e3:g} ms'
    )
    item = TH.Item(
        'latency',
        ok,
        figures,
        expected,
        {
            'median_s': TH.finite_or_none(med),
            'p99_s': TH.finite_or_none(p99),
            'effect_delays': [None if x is None else int(x) for x in delays],
            'declared_delay': declared,
            'label_delays': None if labels is None else list(labels),
            'complete': whole,
            'on_time': punctual,
        },
    )
    # What is not the drive's fault: too few changes judged (the check answered late, or
    # the link lost the states), or wall-time limits missed while the check was late.
    # A label the drive broke (slower than declared) or an effect later than allowed in
    # a change that reached it in time is its fault whatever the load.
    why = []
    if (realtime and len(d) < 3) or (labels is not None and len(judged) < 3):
        why.append(
            f'only {len(d)} of {n} changes reached the drive in time with every state '
            'around them received'
            + (f', {len(judged)} with every period of the drive on time ({host})' if host else '')
        )
    if not wall_ok and busy:
        why.append(busy)
    if (
        why
        and not (len(d) >= 3 and not effect_ok)
        and not (labels is not None and len(judged) >= 3 and not labels_ok)
    ):
        return item.undecided('; '.join(why))
    return item


def rise_time(x: np.ndarray, ts: float, x0: float, x1: float) -> float:
    """10-90 % rise time [s] of samples ``x`` (every ``ts`` s) going from x0 towards x1,
    crossings linearly interpolated; inf when 90 % is never reached."""
    y = (np.asarray(x, dtype=float) - x0) / (x1 - x0)

    def crossing(level: float) -> float:
        above = np.flatnonzero(y >= level)
        if len(above) == 0:
            return math.inf
        i = int(above[0])
        if i == 0:
            return 0.0
        return (i - 1 + (level - y[i - 1]) / (y[i] - y[i - 1])) * ts

    return crossing(0.9) - crossing(0.1)


def fit_acceleration(theta: np.ndarray, ts: float) -> float:
    """Acceleration [rad/s^2] of a least-squares parabola through consecutive positions."""
    t = np.arange(len(theta)) * ts
    return float(2.0 * np.polyfit(t, theta, 2)[0])


def step_metrics(
    rows: np.ndarray, level: float, previous: float, ts: float, delay: int | None
) -> dict[str, float]:
    """Rise time (from the onset), steady-state error, torque per ampere and acceleration of
    one level of the step test: ``rows``, the states (``STATE_FIELDS``) from the one the
    level's first command answered; ``level``, ``previous``: commanded isq* [A] and the
    one before."""
    isq, torque, theta = (rows[:, F[c]] for c in ('isq', 'torque', 'theta_meas'))
    n = len(isq)
    start = delay if delay is not None else 1
    rise = rise_time(isq[start - 1 :], ts, isq[start - 1], level) if level != previous else math.nan
    tail = isq[n - n // 4 :]
    sse = abs(float(np.mean(tail)) - level) / abs(level) if level else math.nan
    half = slice(n // 2, n)
    i_mean = float(np.mean(isq[half]))
    kt = float(np.mean(torque[half])) / i_mean if i_mean else math.nan
    acc = fit_acceleration(theta[start:], ts) if n - start >= 10 else math.nan
    return {
        'rise_s': rise,
        'steady_error': sse,
        'torque_per_amp': kt,
        'accel': acc,
        'duration_s': (n - start) * ts,
        'isq_mean': float(np.mean(isq[start:])) if n > start else math.nan,
    }


def judge_step_response(
    plus: dict[str, float],
    minus: dict[str, float],
    amplitude: float,
    counts_per_rad: float,
    aborted: str = '',
    busy: str = '',
    gaps: str = '',
) -> TH.Item:
    """``plus``/``minus``: step_metrics of the +isq and the -isq step. Why the step the
    drive was given may not be the one commanded ('': it is): ``gaps`` (states missing:
    a line across a gap stretches the rise) and ``busy`` (commands that reached the drive
    late: the steady state is measured where the step may not have been applied). A
    wrong sign fails whatever they say; the rise time is inconclusive only with
    ``gaps`` (it is measured from the onset, wherever a late command put it), or with
    ``busy`` when there was no onset (the step was never given); the other figures with
    either."""
    problems = []
    if aborted:
        problems.append(aborted)
    # signs are the drive's whatever the load; the timing figures are not
    signs: list[str] = []
    rise = max(plus['rise_s'], minus['rise_s'])
    rise_bad = not rise <= TH.RISE_TIME_MAX
    if rise_bad:
        problems.append(f'rise time {rise * 1e3:.2f} ms')
    sse = max(plus['steady_error'], minus['steady_error'])
    if not sse <= TH.STEADY_STATE_ERROR_MAX:
        problems.append(f'steady-state error {sse * 100:.1f} %')
    if plus['torque_per_amp'] < 0 or minus['torque_per_amp'] < 0:
        signs.append('torque sign opposite to isq')
    elif not (plus['torque_per_amp'] > 0 and minus['torque_per_amp'] > 0):
        problems.append('no torque')
    for m, sign, name in ((plus, 1.0, '+'), (minus, -1.0, '-')):
        moved = abs(m['accel']) * m['duration_s'] ** 2 / 2 * counts_per_rad
        # the acceleration's sign is judged against the current the drive measured: where
        # it did not carry the commanded sign the drive was not given the step (a command
        # the link held, the watchdog's zero), which the steady-state error says
        given = m.get('isq_mean', sign * amplitude) * sign > 0.5 * amplitude
        if not moved >= TH.ACCEL_MIN_COUNTS:
            problems.append(f'no acceleration in the {name} step')
        elif m['accel'] * sign <= 0 and given:
            signs.append(f'acceleration {m["accel"]:+.3g} rad/s^2 in the {name}isq step')
        elif m['accel'] * sign <= 0:
            problems.append(
                f'acceleration {m["accel"]:+.3g} rad/s^2 in the {name}isq step, whose '
                f'current the drive did not carry (mean isq {m["isq_mean"]:+.3g} A)'
            )
    problems = signs + problems
    figures = (
        f'isq rise {rise * 1e3:.2f} ms, steady-state error {sse * 100:.1f} %, '
        f'torque/isq {plus["torque_per_amp"]:+.3f}/{minus["torque_per_amp"]:+.3f} N m/A, '
        f'accel {plus["accel"]:+.0f}/{minus["accel"]:+.0f} rad/s^2 for '
        f'+-{amplitude:g} A'
    )
    if problems:
        figures = '; '.join(problems) + ' -- ' + figures
    item = TH.Item(
        'step_response',
        not problems,
        figures,
        f'rise <= {TH.RISE_TIME_MAX * 1e3:g} ms, error <= {TH.STEADY_STATE_ERROR_MAX * 100:g} %, '
        'torque and acceleration with the sign of isq',
        {
            'plus': {k: TH.finite_or_none(v) for k, v in plus.items()},
            'minus': {k: TH.finite_or_none(v) for k, v in minus.items()},
            'aborted': aborted or None,
        },
    )
    # a rise is timed from its onset, wherever a late command put it: a slow one is the
    # drive's -- but no onset at all while the commands came late is a step never given
    rise_judged = rise_bad and not gaps and (math.isfinite(rise) or not busy)
    if signs or rise_judged:
        return item  # the drive's, whatever the load
    return item.undecided('; '.join(w for w in (gaps, busy) if w))


def watchdog_limits(timeout: float) -> tuple[float, float]:
    """(earliest, latest) time [s] after the last command at which zero current is due."""
    return TH.WATCHDOG_EARLIEST * timeout, timeout + max(
        TH.WATCHDOG_MARGIN_S, TH.WATCHDOG_MARGIN_REL * timeout
    )


def judge_watchdog_realtime(
    t_act: float | None,
    t_zero: float | None,
    timeout: float,
    resumed_s: float | None,
    timeout_source: str,
    aborted: str = '',
    busy: str = '',
) -> TH.Item:
    """Times after the last command was published [s]: ``t_act`` when isq started its fall to
    zero (left WATCHDOG_ACT_FRACTION of the test current), ``t_zero`` when it got there
    (None: never); ``resumed_s``: new command -> current back [s] (None: did not resume).
    The watchdog's own timing is judged on ``t_act``: the fall itself is the current
    loop's business (step_response)."""
    lo, hi = watchdog_limits(timeout)
    ok = (
        t_act is not None
        and t_zero is not None
        and lo <= t_act <= hi
        and resumed_s is not None
        and not aborted
    )
    zero = (
        f'current falls {t_act * 1e3:.1f} ms after the last command, zero at {t_zero * 1e3:.1f} ms'
        if t_act is not None and t_zero is not None
        else 'current never went to zero'
    )
    back = (
        f'resumed {resumed_s * 1e3:.1f} ms after a new command'
        if resumed_s is not None
        else 'did not resume on a new command'
    )
    figures = f'{zero}; {back}' + (f'; {aborted}' if aborted else '')
    item = TH.Item(
        'watchdog',
        ok,
        figures,
        f'falls to zero {lo * 1e3:.0f}..{hi * 1e3:.0f} ms after (command_timeout '
        f'{timeout:g} s, {timeout_source}), then resume',
        {
            't_act_s': t_act,
            't_zero_s': t_zero,
            'resumed_s': resumed_s,
            'command_timeout_s': timeout,
            'limits_s': [lo, hi],
        },
    )
    return item.undecided(busy)


def judge_watchdog_lockstep(silence_s: float, advanced: int, resumed_s: float | None) -> TH.Item:
    ok = advanced == 0 and resumed_s is not None and silence_s >= TH.LOCKSTEP_SILENCE_S * 0.99
    back = (
        f'stepped {resumed_s * 1e3:.1f} ms after a new command'
        if resumed_s is not None
        else 'did not step on a new command'
    )
    return TH.Item(
        'watchdog',
        ok,
        f'{advanced} steps during {silence_s:.2f} s without commands; {back}',
        f'lock-step: no step during >= {TH.LOCKSTEP_SILENCE_S} s of silence, '
        'then one on the next command',
        {'silence_s': silence_s, 'advanced': advanced, 'resumed_s': resumed_s},
    )
