"""check_drive's pure judging functions: numpy arrays in, an :class:`Item` out.

No ROS: the tests call them on synthetic arrays, the probe on what it recorded.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..contract import COMMAND_DELAYS, COMMAND_TOPIC
from .thresholds import (
    ACCEL_MIN_COUNTS,
    CURRENT_FIELDS,
    EFFECT_DELAY_LOCKSTEP,
    LABEL_SLOWER_MAX_REALTIME,
    LATENCY_MEDIAN_MAX,
    LATENCY_P99_MAX,
    LOCKSTEP_SILENCE_S,
    ONSET_FRACTION,
    RATE_MAX_LONG_FRACTION,
    RATE_TOLERANCE,
    RISE_TIME_MAX,
    STATE_FIELDS,
    STEADY_STATE_ERROR_MAX,
    TRANSPORT_SLACK_REALTIME,
    TYPES,
    UNITS_MIN_COUNTS,
    UNITS_RATIO_BAND,
    WATCHDOG_EARLIEST,
    WATCHDOG_MARGIN_REL,
    WATCHDOG_MARGIN_S,
    F,
    Item,
)

__all__ = [
    'StepSegment',
    'fit_acceleration',
    'joint_state_problems',
    'judge_fields',
    'judge_latency',
    'judge_rate_lockstep',
    'judge_rate_realtime',
    'judge_step_response',
    'judge_topics',
    'judge_watchdog_lockstep',
    'judge_watchdog_realtime',
    'label_delay',
    'lockstep_step_problems',
    'onset_delay',
    'period_stats',
    'rise_time',
    'state_field_problems',
    'step_metrics',
    'summary_line',
    'units_ratio',
    'watchdog_limits',
]

# ================================ pure judging functions ===================================


def _finite_or_none(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def judge_topics(endpoints: dict[str, list[str]]) -> Item:
    """``endpoints``: for 'drive/state', 'drive/joint_states', 'drive/status' the types of
    their publishers, for 'drive/command' the types of its subscribers other than us."""
    problems, seen = [], []
    for topic, want in TYPES.items():
        role = 'subscriber' if topic == COMMAND_TOPIC else 'publisher'
        types = endpoints.get(topic, [])
        if not types:
            problems.append(f'no {role} on {topic}')
        elif any(t != want for t in types):
            problems.append(f'{topic} {role} type {",".join(sorted(set(types)))}')
        else:
            seen.append(topic)
    figures = '; '.join(problems) if problems else f'{len(seen)}/4 topics with the right types'
    return Item(
        'topics',
        not problems,
        figures,
        'drive/state + drive/joint_states + drive/status published, drive/command '
        'subscribed, types ' + ', '.join(f'{t.split("/")[-1]}' for t in TYPES.values()),
        {'endpoints': endpoints, 'problems': problems},
    )


def state_field_problems(
    states: np.ndarray,
    lengths: np.ndarray,
    seq: np.ndarray,
    ts_ns: int,
    realtime: bool,
    current_bound: float,
) -> list[str]:
    """Problems with the raw states: count, integer step_index, consecutive in lock-step
    and increasing in real time (a drive that cannot pause skips the periods its late
    loop missed) where the publication sequence numbers are consecutive (nothing lost in
    transit),
    time_ns == step_index * Ts exactly, all finite, currents within ``current_bound`` [A];
    in lock-step a re-sent state must equal the original."""
    problems = []
    bad_len = int(np.count_nonzero(lengths != len(STATE_FIELDS)))
    if bad_len:
        legacy = int(np.count_nonzero(lengths == len(STATE_FIELDS) - 1))
        why = (
            ' (the last field, command_delay, is missing: 1 or 2, docs/interfaces.md)'
            if legacy == bad_len
            else ''
        )
        problems.append(f'{bad_len} states without {len(STATE_FIELDS)} values{why}')
    ok = lengths == len(STATE_FIELDS)
    s, q = states[ok], seq[ok]
    if len(s) == 0:
        return [*problems, 'no state received']
    if not np.isfinite(s).all():
        bad = [STATE_FIELDS[i] for i in np.flatnonzero(~np.isfinite(s).all(axis=0))]
        problems.append(f'non-finite values in {",".join(bad)}')
        return problems
    delays = np.unique(s[:, F['command_delay']])
    if len(delays) > 1 or delays[0] not in COMMAND_DELAYS:
        problems.append(f'command_delay {", ".join(f"{v:g}" for v in delays)}: one value, 1 or 2')
    k = s[:, F['step_index']]
    if np.any(k != np.floor(k)) or np.any(k < 0):
        problems.append('step_index not a non-negative integer')
        return problems
    wrong_t = np.count_nonzero(s[:, F['time_ns']] != k * ts_ns)
    if wrong_t:
        problems.append(f'time_ns != step_index*{ts_ns} in {wrong_t} states')
    dk, dq = np.diff(k), np.diff(q)
    lossless = dq == 1  # states with consecutive sequence numbers: the drive sent them so
    if realtime:
        # a drive on the wall clock cannot pause: a period its loop started late by m
        # whole periods follows m periods held (not published), and its step index
        # advances by them (docs/real-drive.md); it must never stand still or go back
        back = np.count_nonzero(lossless & (dk < 1))
        if back:
            problems.append(f'step_index not increasing {back} times')
    else:  # lock-step re-sends state k while it waits: a repeat must be identical
        jumps = np.count_nonzero(lossless & (dk != 1) & (dk != 0))
        rep = np.flatnonzero(lossless & (dk == 0))
        if len(rep) and not np.array_equal(s[rep], s[rep + 1]):
            problems.append('a re-sent state differs from the original')
        if jumps:
            problems.append(f'step_index not consecutive {jumps} times')
    cur = np.abs(s[:, [F[c] for c in CURRENT_FIELDS]]).max()
    if cur > current_bound:
        problems.append(f'current {cur:.3g} A beyond {current_bound:.3g} A')
    return problems


def units_ratio(theta_meas: np.ndarray, omega_meas: np.ndarray, ts: float) -> float:
    """Least-squares ratio of the integrated speed to the change of position (1 when
    theta_meas is in rad and omega_meas in rad/s; about 1/57.3 when theta is in degrees,
    9.55 when omega is in rpm). Arrays are consecutive steps."""
    dtheta = theta_meas - theta_meas[0]
    # theta(k) - theta(0) = sum of the speed over steps 1..k (backward difference)
    integral = np.concatenate(([0.0], np.cumsum(omega_meas[1:]) * ts))
    den = float(np.dot(dtheta, dtheta))
    return float(np.dot(integral, dtheta) / den) if den > 0 else math.nan


def joint_state_problems(joints: np.ndarray, states: np.ndarray, ts_ns: int) -> list[str]:
    """``joints`` rows (stamp_ns, position, velocity, effort): each must equal the state of
    the same step (stamp == time_ns; position, velocity, effort == theta_meas, omega_meas,
    torque, exactly) and they must come every 10 steps."""
    if len(joints) == 0:
        return ['no drive/joint_states received']
    by_time = {int(t): i for i, t in enumerate(states[:, F['time_ns']])}
    matched = mismatched = 0
    for t, pos, vel, eff in joints:
        i = by_time.get(int(t))
        if i is None:
            continue
        matched += 1
        s = states[i]
        if (pos, vel, eff) != (s[F['theta_meas']], s[F['omega_meas']], s[F['torque']]):
            mismatched += 1
    problems = []
    if matched == 0:
        problems.append('no joint_states stamp equals a state time_ns')
    if mismatched:
        problems.append(f'{mismatched}/{matched} joint_states differ from the state')
    steps = np.unique(joints[:, 0].astype(np.int64)) / ts_ns
    if len(steps) > 2 and np.median(np.diff(steps)) != 10:
        problems.append(f'joint_states every {np.median(np.diff(steps)):g} steps, not 10')
    return problems


def judge_fields(
    state_problems: list[str], ratio: float, motion_counts: float, joint_problems: list[str] | None
) -> Item:
    """Combine the field checks; ``joint_problems`` None = not judged (wrong topic type,
    reported by 'topics')."""
    problems = list(state_problems)
    if motion_counts >= UNITS_MIN_COUNTS:
        lo, hi = UNITS_RATIO_BAND
        if not lo <= ratio <= hi:
            problems.append(f'integral(omega_meas)/delta(theta_meas) = {ratio:.3g} (units?)')
        units = f'integral(omega)/delta(theta) {ratio:.3f}'
    else:
        units = f'units not judged (motion {motion_counts:.0f} counts)'
    if joint_problems is not None:
        problems += joint_problems
        joints = 'joint_states match' if not joint_problems else ''
    else:
        joints = 'joint_states not judged (type)'
    figures = (
        '; '.join(problems)
        if problems
        else f'{len(STATE_FIELDS)} finite values, step_index consecutive, time_ns = k Ts; '
        f'{units}; {joints}'
    )
    if problems and joint_problems is None:
        figures += f'; {joints}'
    return Item(
        'fields',
        not problems,
        figures,
        f'{len(STATE_FIELDS)} finite values, time_ns = k Ts exactly, currents plausible, ratio in '
        f'[{UNITS_RATIO_BAND[0]}, {UNITS_RATIO_BAND[1]}], joint_states = state',
        {
            'problems': problems,
            'units_ratio': _finite_or_none(ratio),
            'motion_counts': float(motion_counts),
        },
    )


def period_stats(steps: np.ndarray, source_ts_ns: np.ndarray, ts: float) -> dict[str, float]:
    """Publication periods [s] from the drive's own source time stamps, per step: median,
    99th percentile, mean, and the fraction of steps that took longer than 2 Ts."""
    dk = np.diff(steps)
    keep = dk > 0
    per_step = np.diff(source_ts_ns.astype(np.float64))[keep] / dk[keep] * 1e-9
    if len(per_step) == 0:
        return {
            'n': 0,
            'median': math.nan,
            'p99': math.nan,
            'mean': math.nan,
            'long_fraction': math.nan,
        }
    return {
        'n': len(per_step),
        'median': float(np.median(per_step)),
        'p99': float(np.percentile(per_step, 99)),
        'mean': float(np.mean(per_step)),
        'long_fraction': float(np.mean(per_step > 2 * ts)),
    }


def judge_rate_realtime(stats: dict[str, float], ts: float, mode_note: str = '') -> Item:
    ok = (
        stats['n'] >= 100
        and abs(stats['median'] - ts) <= RATE_TOLERANCE * ts
        and stats['long_fraction'] <= RATE_MAX_LONG_FRACTION
    )
    figures = (
        f'median period {stats["median"] * 1e6:.1f} us, p99 {stats["p99"] * 1e6:.0f} us, '
        f'mean {stats["mean"] * 1e6:.1f} us, {stats["long_fraction"] * 100:.2f} % '
        f'> 2 Ts over {stats["n"]} steps'
    )
    if mode_note:
        ok = False
        figures += f'; {mode_note}'
    return Item(
        'rate',
        ok,
        figures,
        f'median {ts * 1e6:.0f} us +-{RATE_TOLERANCE * 100:.0f} %, <= '
        f'{RATE_MAX_LONG_FRACTION * 100:.0f} % of periods > 2 Ts',
        {k: _finite_or_none(v) for k, v in stats.items()},
    )


def lockstep_step_problems(
    steps: np.ndarray, take_ns: np.ndarray, cmd_answers: np.ndarray, cmd_pub_ns: np.ndarray
) -> tuple[int, int, int]:
    """Lock-step: (new steps seen, steps without a command answering the previous state
    published before they arrived, steps advancing by more than one)."""
    new = np.flatnonzero(np.diff(steps) > 0) + 1
    unanswered = skipped = 0
    for i in new:
        k, prev = steps[i], steps[i - 1]
        if k - prev != 1:
            skipped += 1
        sel = (cmd_answers == prev) | (cmd_answers < 0)
        if not np.any(cmd_pub_ns[sel] <= take_ns[i]):
            unanswered += 1
    return len(new), unanswered, skipped


def judge_rate_lockstep(
    n_steps: int,
    unanswered: int,
    skipped: int,
    idle_advance: int,
    steps_per_s: float,
    mode_note: str = '',
) -> Item:
    ok = n_steps > 0 and unanswered == 0 and skipped == 0 and idle_advance == 0 and not mode_note
    figures = (
        f'{n_steps} steps, {unanswered} without a command, {skipped} skipping, '
        f'{idle_advance} while idle; {steps_per_s:.0f} steps/s'
    )
    if mode_note:
        figures += f'; {mode_note}'
    return Item(
        'rate',
        ok,
        figures,
        'lock-step: one step per command, none without one',
        {
            'steps': n_steps,
            'unanswered': unanswered,
            'skipped': skipped,
            'idle_advance': idle_advance,
            'steps_per_s': _finite_or_none(steps_per_s),
        },
    )


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
    thr = max(ONSET_FRACTION * abs(delta_ref), 8.0 * noise)
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
    declared: int = EFFECT_DELAY_LOCKSTEP,
    labels: Sequence[int | None] | None = None,
) -> Item:
    """``delays``: per command changing the reference, the state (k + d) in which it first
    showed; ``wall_s``: command published -> next state received [s]; ``declared``: the
    drive's command_delay; ``labels``: per change, the first state (k + l) whose
    applied_step is the changing command's or newer (None: not judged)."""
    d = np.array([x for x in delays if x is not None], dtype=float)
    missing = sum(x is None for x in delays)
    med = float(np.median(wall_s)) if len(wall_s) else math.nan
    p99 = float(np.percentile(wall_s, 99)) if len(wall_s) else math.nan
    limit = declared + (TRANSPORT_SLACK_REALTIME if realtime else 0)
    if realtime:
        effect_ok = len(d) >= 3 and float(np.percentile(d, 25, method='lower')) <= limit
    else:
        effect_ok = len(d) >= 3 and bool(np.all(d == limit)) and missing == 0
    pairs = [(x, y) for x, y in zip(delays, labels or (), strict=False) if x is not None]
    judged = [(x, y) for x, y in pairs if y is not None]
    honest = sum(x == y for x, y in judged)
    slower = sum(y is not None and x > y for x, y in judged)
    if labels is None:
        labels_ok = True
    elif realtime:
        labels_ok = len(judged) >= 3 and slower <= LABEL_SLOWER_MAX_REALTIME * len(judged)
    else:
        labels_ok = len(judged) == len(d) and honest == len(judged)
    ok = effect_ok and labels_ok and med <= LATENCY_MEDIAN_MAX and p99 <= LATENCY_P99_MAX
    hist = ', '.join(f'k+{int(v)}: {int(np.sum(d == v))}' for v in np.unique(d))
    figures = (
        f'command -> next state median {med * 1e6:.0f} us, p99 {p99 * 1e6:.0f} us; '
        f'takes effect in {hist or "-"}' + (f', never: {missing}' if missing else '')
    )
    if labels is not None:
        figures += f'; declared delay {declared}: {honest}/{len(judged)} where applied_step says'
        if slower:
            figures += f', {slower} later (slower than declared)'
    when = f' (fastest quarter by k+{limit})' if realtime else ' always'
    expected = (
        f'effect in k+{declared}{when}, never after applied_step says, '
        f'median <= {LATENCY_MEDIAN_MAX * 1e3:g} ms, '
        f'p99 <= {LATENCY_P99_MAX * 1e3:g} ms'
    )
    return Item(
        'latency',
        ok,
        figures,
        expected,
        {
            'median_s': _finite_or_none(med),
            'p99_s': _finite_or_none(p99),
            'effect_delays': [None if x is None else int(x) for x in delays],
            'declared_delay': declared,
            'label_delays': None if labels is None else list(labels),
        },
    )


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


@dataclass
class StepSegment:
    """One commanded level of the step test, as recorded."""

    level: float  #: commanded isq* [A]
    previous: float  #: the level before [A]
    isq: np.ndarray  #: isq from the state answered by the first command of the level
    torque: np.ndarray  #: torque, same samples [N m]
    theta: np.ndarray  #: theta_meas, same samples [rad]


def step_metrics(seg: StepSegment, ts: float, delay: int | None) -> dict[str, float]:
    """Rise time (from the onset), steady-state error, torque per ampere and acceleration of
    one level of the step test."""
    n = len(seg.isq)
    start = delay if delay is not None else 1
    rise = (
        rise_time(seg.isq[start - 1 :], ts, seg.isq[start - 1], seg.level)
        if seg.level != seg.previous
        else math.nan
    )
    tail = seg.isq[n - n // 4 :]
    sse = abs(float(np.mean(tail)) - seg.level) / abs(seg.level) if seg.level else math.nan
    half = slice(n // 2, n)
    i_mean = float(np.mean(seg.isq[half]))
    kt = float(np.mean(seg.torque[half])) / i_mean if i_mean else math.nan
    acc = fit_acceleration(seg.theta[start:], ts) if n - start >= 10 else math.nan
    return {
        'rise_s': rise,
        'steady_error': sse,
        'torque_per_amp': kt,
        'accel': acc,
        'duration_s': (n - start) * ts,
    }


def judge_step_response(
    plus: dict[str, float],
    minus: dict[str, float],
    amplitude: float,
    counts_per_rad: float,
    aborted: str = '',
) -> Item:
    """``plus``/``minus``: step_metrics of the +isq and the -isq step."""
    problems = []
    if aborted:
        problems.append(aborted)
    rise = max(plus['rise_s'], minus['rise_s'])
    if not rise <= RISE_TIME_MAX:
        problems.append(f'rise time {rise * 1e3:.2f} ms')
    sse = max(plus['steady_error'], minus['steady_error'])
    if not sse <= STEADY_STATE_ERROR_MAX:
        problems.append(f'steady-state error {sse * 100:.1f} %')
    if not (plus['torque_per_amp'] > 0 and minus['torque_per_amp'] > 0):
        problems.append('torque sign opposite to isq')
    for m, sign, name in ((plus, 1.0, '+'), (minus, -1.0, '-')):
        moved = abs(m['accel']) * m['duration_s'] ** 2 / 2 * counts_per_rad
        if not moved >= ACCEL_MIN_COUNTS:
            problems.append(f'no acceleration in the {name} step')
        elif m['accel'] * sign <= 0:
            problems.append(f'acceleration {m["accel"]:+.3g} rad/s^2 in the {name}isq step')
    figures = (
        f'isq rise {rise * 1e3:.2f} ms, steady-state error {sse * 100:.1f} %, '
        f'torque/isq {plus["torque_per_amp"]:+.3f}/{minus["torque_per_amp"]:+.3f} N m/A, '
        f'accel {plus["accel"]:+.0f}/{minus["accel"]:+.0f} rad/s^2 for '
        f'+-{amplitude:g} A'
    )
    if problems:
        figures = '; '.join(problems) + ' -- ' + figures
    return Item(
        'step_response',
        not problems,
        figures,
        f'rise <= {RISE_TIME_MAX * 1e3:g} ms, error <= {STEADY_STATE_ERROR_MAX * 100:g} %, '
        'torque and acceleration with the sign of isq',
        {
            'plus': {k: _finite_or_none(v) for k, v in plus.items()},
            'minus': {k: _finite_or_none(v) for k, v in minus.items()},
            'aborted': aborted or None,
        },
    )


def watchdog_limits(timeout: float) -> tuple[float, float]:
    """(earliest, latest) time [s] after the last command at which zero current is due."""
    return WATCHDOG_EARLIEST * timeout, timeout + max(
        WATCHDOG_MARGIN_S, WATCHDOG_MARGIN_REL * timeout
    )


def judge_watchdog_realtime(
    t_act: float | None,
    t_zero: float | None,
    timeout: float,
    resumed_s: float | None,
    timeout_source: str,
    aborted: str = '',
) -> Item:
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
    return Item(
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


def judge_watchdog_lockstep(silence_s: float, advanced: int, resumed_s: float | None) -> Item:
    ok = advanced == 0 and resumed_s is not None and silence_s >= LOCKSTEP_SILENCE_S * 0.99
    back = (
        f'stepped {resumed_s * 1e3:.1f} ms after a new command'
        if resumed_s is not None
        else 'did not step on a new command'
    )
    return Item(
        'watchdog',
        ok,
        f'{advanced} steps during {silence_s:.2f} s without commands; {back}',
        f'lock-step: no step during >= {LOCKSTEP_SILENCE_S} s of silence, '
        'then one on the next command',
        {'silence_s': silence_s, 'advanced': advanced, 'resumed_s': resumed_s},
    )


def summary_line(items: Sequence[Item], mode: str = '', status_mode: str | None = None) -> str:
    """The last line: verdict, failing items, the mode (and what drive/status said)."""
    failed = [i.name for i in items if not i.passed]
    n = len(items)
    verdict = (
        f'all {n} items PASS'
        if not failed
        else f'{n - len(failed)}/{n} items pass; FAIL: {", ".join(failed)}'
    )
    how = f' ({mode}; drive/status mode={status_mode or "not seen"})' if mode else ''
    return f'check_drive: {verdict}{how}'
