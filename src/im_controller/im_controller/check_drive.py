"""Drive conformance check: ``ros2 run im_controller check_drive``.

Probes the drive node on the graph (in this node's namespace) against docs/interfaces.md
and prints one line per item -- ``topics``, ``fields``, ``rate``, ``latency``,
``step_response``, ``watchdog`` -- with the measured figures and what was expected, then a
summary; exit code 0 when every item passes, 1 otherwise, 2 when it refuses to run (bad
option, no drive, another node already commanding the drive). What each item checks and
why its thresholds are what they are: docs/check-drive.md.

Two parts: pure judging functions (numpy only, no ROS; the tests call them on synthetic
arrays) and a thin probe (:class:`Probe`, :func:`run_check`) that drives the experiment
through DDS and records every state, joint state and command it saw.
"""

from __future__ import annotations

import itertools
import json
import math
import signal
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from im_drive_sim.cli import Parser, UsageError, check_ros_args, input_file, output_file
from im_drive_sim.sim import STATE_FIELDS  # layout of drive/state (docs/interfaces.md)

#: Items, in the order they are printed.
ITEMS: tuple[str, ...] = ('topics', 'fields', 'rate', 'latency', 'step_response', 'watchdog')

F = {name: i for i, name in enumerate(STATE_FIELDS)}
CURRENT_FIELDS = ('isd', 'isq', 'i_alpha', 'i_beta')

#: Expected topic types (docs/interfaces.md).
TYPES = {
    'drive/state': 'std_msgs/msg/Float64MultiArray',
    'drive/command': 'std_msgs/msg/Float64MultiArray',
    'drive/joint_states': 'sensor_msgs/msg/JointState',
    'drive/status': 'diagnostic_msgs/msg/DiagnosticArray',
}

# --- thresholds (why: docs/check-drive.md) -----------------------------------------------
#: fields: currents must stay within this factor of the largest current the drive may carry
#: (hypot(isq_max, rated flux current)): beyond it, a value is not a current in A.
CURRENT_BOUND_FACTOR = 1.5
#: fields: integral of omega_meas over the motion / change of theta_meas (1 when both are SI;
#: 57.3 for degrees, 9.55 for rpm). The band absorbs encoder quantisation and filter lag.
UNITS_RATIO_BAND = (0.8, 1.25)
#: fields: motion needed to judge the units [encoder counts of the configured encoder].
UNITS_MIN_COUNTS = 10
#: rate (real time): median period within this fraction of Ts (a drive and this check
#: competing for 2 loaded cores measured 200-211 us) ...
RATE_TOLERANCE = 0.10
#: ... and at most this fraction of periods longer than 2 Ts (measured 0.4-4 %, 9 % while
#: another real-time test ran beside it).
RATE_MAX_LONG_FRACTION = 0.20
#: latency: command published -> next state received, wall time [s].
LATENCY_MEDIAN_MAX = 2e-3
LATENCY_P99_MAX = 20e-3
#: latency: the state in which a command first shows (k+1 answers k). Real time allows one
#: period of transport (k+2), judged on the fastest quarter of the changes: a change this
#: check answers late (its own process descheduled on a loaded machine) shows later
#: through no fault of the drive, but a drive that applies commands late never shows early.
EFFECT_DELAY_LOCKSTEP = 1
EFFECT_DELAY_REALTIME = 2
#: latency/step: a response starts where isq leaves its extrapolated course by this fraction
#: of the commanded change (or 8 noise levels, whichever is larger): 10 mA for 0.5 A.
ONSET_FRACTION = 0.02
#: step_response: 10-90 % rise time of isq [s] (the paper's current loop: about 1.5 ms).
RISE_TIME_MAX = 5e-3
#: step_response: |mean isq over the last quarter of a step - isq*| / |isq*|.
STEADY_STATE_ERROR_MAX = 0.10
#: step_response: fitted displacement from the acceleration that counts as motion [counts].
ACCEL_MIN_COUNTS = 3
#: watchdog (real time): zero current within command_timeout + max(30 ms, 25 %) ...
WATCHDOG_MARGIN_S, WATCHDOG_MARGIN_REL = 0.03, 0.25
#: ... and not before half of it (the contract holds the last command until the timeout).
WATCHDOG_EARLIEST = 0.5
#: watchdog: |isq| below this fraction of the test current counts as zero current ...
ZERO_CURRENT_FRACTION = 0.2
#: ... and the fall to it starts where isq leaves this fraction of the test current.
WATCHDOG_ACT_FRACTION = 0.9
#: watchdog (lock-step): silence during which the drive must not step [s].
LOCKSTEP_SILENCE_S = 0.35

#: No current is commanded before this long after the check joined the graph [s]: a node
#: that was there before is discovered at the latest by its periodic announcement (Fast
#: DDS: every 3 s); a second commander found by then refuses the check. (Measured: most
#: are found within 0.1 s, one in six took 2.6 s.)
DISCOVERY_SETTLE_S = 3.2
DEFAULT_TIMEOUT = 0.05  # [s] command_timeout when the drive has no such parameter
NS_PER_S = 1_000_000_000


class CheckRefused(Exception):
    """The check cannot run (bad option, no drive, another commander): exit code 2."""


@dataclass
class Item:
    """The verdict on one item: one printed line, one JSON object."""

    name: str
    passed: bool
    figures: str  #: what was measured, human-readable
    expected: str  #: what the contract asks
    values: dict = field(default_factory=dict)  #: the figures, machine-readable (SI)

    def line(self) -> str:
        return (
            f'{"PASS" if self.passed else "FAIL"}  {self.name:<13s} {self.figures} '
            f'(expected: {self.expected})'
        )


# ================================ pure judging functions ===================================


def _finite_or_none(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def judge_topics(endpoints: dict[str, list[str]]) -> Item:
    """``endpoints``: for 'drive/state', 'drive/joint_states', 'drive/status' the types of
    their publishers, for 'drive/command' the types of its subscribers other than us."""
    problems, seen = [], []
    for topic, want in TYPES.items():
        role = 'subscriber' if topic == 'drive/command' else 'publisher'
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
    """Problems with the raw states: count, integer and consecutive step_index (where the
    publication sequence numbers are consecutive, i.e. nothing was lost in transit),
    time_ns == step_index * Ts exactly, all finite, currents within ``current_bound`` [A];
    in lock-step a re-sent state must equal the original."""
    problems = []
    bad_len = int(np.count_nonzero(lengths != len(STATE_FIELDS)))
    if bad_len:
        problems.append(f'{bad_len} states without {len(STATE_FIELDS)} values')
    ok = lengths == len(STATE_FIELDS)
    s, q = states[ok], seq[ok]
    if len(s) == 0:
        return [*problems, 'no state received']
    if not np.isfinite(s).all():
        bad = [STATE_FIELDS[i] for i in np.flatnonzero(~np.isfinite(s).all(axis=0))]
        problems.append(f'non-finite values in {",".join(bad)}')
        return problems
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
        jumps = np.count_nonzero(lossless & (dk != 1))
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
        else f'12 finite values, step_index consecutive, time_ns = k Ts; {units}; {joints}'
    )
    if problems and joint_problems is None:
        figures += f'; {joints}'
    return Item(
        'fields',
        not problems,
        figures,
        f'12 finite values, time_ns = k Ts exactly, currents plausible, ratio in '
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


def judge_latency(delays: Sequence[int | None], wall_s: np.ndarray, realtime: bool) -> Item:
    """``delays``: per command changing the reference, the state (k + d) in which it first
    showed; ``wall_s``: command published -> next state received [s]."""
    d = np.array([x for x in delays if x is not None], dtype=float)
    missing = sum(x is None for x in delays)
    med = float(np.median(wall_s)) if len(wall_s) else math.nan
    p99 = float(np.percentile(wall_s, 99)) if len(wall_s) else math.nan
    limit = EFFECT_DELAY_REALTIME if realtime else EFFECT_DELAY_LOCKSTEP
    if realtime:
        effect_ok = len(d) >= 3 and float(np.percentile(d, 25, method='lower')) <= limit
    else:
        effect_ok = len(d) >= 3 and bool(np.all(d == limit)) and missing == 0
    ok = effect_ok and med <= LATENCY_MEDIAN_MAX and p99 <= LATENCY_P99_MAX
    hist = ', '.join(f'k+{int(v)}: {int(np.sum(d == v))}' for v in np.unique(d))
    figures = (
        f'command -> next state median {med * 1e6:.0f} us, p99 {p99 * 1e6:.0f} us; '
        f'takes effect in {hist or "-"}' + (f', never: {missing}' if missing else '')
    )
    when = ' (fastest quarter by k+2)' if realtime else ' always'
    expected = (
        f'effect in k+1{when}, median <= {LATENCY_MEDIAN_MAX * 1e3:g} ms, '
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


# ======================================= the probe ==========================================


class Interrupted(Exception):
    """SIGINT/SIGTERM during the check."""


class DriveLost(Exception):
    """The drive stopped publishing states in the middle of the check: exit code 1."""


class Probe:
    """Records every drive/state (with its DDS time stamps), joint state and command."""

    def __init__(self, node, capacity: int = 60000) -> None:
        # ROS imports here, not at module level: the judging functions need none.
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray

        from im_drive_sim.cdr import parse_float64_array

        self.node = node
        self._parse, self._deserialize = parse_float64_array, deserialize_message
        self._Float64MultiArray, self._JointState = Float64MultiArray, JointState
        self._DiagnosticArray = DiagnosticArray
        # A deep keep-last reader: a stall of this process up to 1 s loses nothing, and
        # the drive's reliable writer is never held back by it.
        deep = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=5000,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )
        noop = lambda _m: None  # noqa: E731 (taken by hand, never by an executor)
        self.state_sub = node.create_subscription(Float64MultiArray, 'drive/state', noop, deep)
        self.joint_sub = node.create_subscription(JointState, 'drive/joint_states', noop, 1000)
        self.status_sub = node.create_subscription(DiagnosticArray, 'drive/status', noop, 10)
        self.cmd_pub = None
        self.stopped = False
        self.waitset = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, node.context.handle)
        n = capacity
        self.states = np.full((n, len(STATE_FIELDS)), np.nan)
        self.lengths = np.zeros(n, dtype=np.int64)
        self.source_ns = np.zeros(n, dtype=np.int64)  # drive's publication time [ns, wall]
        self.recv_ns = np.zeros(n, dtype=np.int64)  # DDS reception time [ns, wall]
        self.take_ns = np.zeros(n, dtype=np.int64)  # when this process took it [ns, wall]
        self.seq = np.zeros(n, dtype=np.int64)
        self.n = 0
        self.cmd = np.zeros((n, 3))  # answers_step, isq*, load
        self.cmd_ns = np.zeros(n, dtype=np.int64)  # published at [ns, wall]
        self.m = 0
        self.joints: list[tuple[float, float, float, float]] = []
        self.status: dict[str, str] = {}
        self.answered = -1  # newest step index we answered
        self.created = time.monotonic()  # when this participant joined
        self.stop: Callable[[], bool] = lambda: False

    def open_command(self) -> None:
        from im_drive_sim.drive_sim_node import RECORDED_QOS

        self.cmd_pub = self.node.create_publisher(
            self._Float64MultiArray, 'drive/command', RECORDED_QOS
        )
        self._cmd_msg = self._Float64MultiArray(data=[0.0, 0.0, 0.0])

    def poll(self, timeout_s: float) -> int:
        """Wait up to ``timeout_s`` for states; take every pending message. Returns the
        number of new states."""
        if self.stop():
            raise Interrupted
        ws = self.waitset
        ws.clear_entities()
        ws.add_subscription(self.state_sub.handle)
        ws.wait(int(max(0.0, timeout_s) * NS_PER_S))
        got = 0
        width = len(STATE_FIELDS)
        while self.n < len(self.states):
            r = self.state_sub.handle.take_message(self._Float64MultiArray, True)
            if r is None:
                break
            raw, info = r
            data = self._parse(raw, width)  # our compact layout, straight into numpy
            if data is None:  # another layout: the general way
                data = np.asarray(self._deserialize(raw, self._Float64MultiArray).data)
            i = self.n
            self.lengths[i] = len(data)
            if len(data) == width:
                self.states[i] = data
            self.source_ns[i] = info['source_timestamp']
            self.recv_ns[i] = info.get('received_timestamp') or time.time_ns()
            self.take_ns[i] = time.time_ns()
            self.seq[i] = info.get('publication_sequence_number') or 0
            self.n += 1
            got += 1
        while (r := self.joint_sub.handle.take_message(self._JointState, False)) is not None:
            j = r[0]
            if len(j.position) and len(j.velocity) and len(j.effort):
                self.joints.append(
                    (
                        j.header.stamp.sec * NS_PER_S + j.header.stamp.nanosec,
                        j.position[0],
                        j.velocity[0],
                        j.effort[0],
                    )
                )
        while (r := self.status_sub.handle.take_message(self._DiagnosticArray, False)) is not None:
            for st in r[0].status:
                self.status = {kv.key: kv.value for kv in st.values}
        return got

    def newest(self) -> np.ndarray | None:
        """The newest complete state taken (a view), or None."""
        for i in range(self.n - 1, -1, -1):
            if self.lengths[i] == len(STATE_FIELDS):
                return self.states[i]
        return None

    def command(self, answers: int, isq: float, load: float = 0.0) -> None:
        msg = self._cmd_msg
        msg.data[0], msg.data[1], msg.data[2] = float(answers), float(isq), float(load)
        self.cmd_pub.publish(msg)
        if self.m < len(self.cmd):
            self.cmd[self.m] = (answers, isq, load)
            self.cmd_ns[self.m] = time.time_ns()
            self.m += 1
        self.answered = max(self.answered, answers)

    def run(
        self,
        policy: Callable[[int, np.ndarray], float | None],
        done: Callable[[], bool],
        max_wall: float,
    ) -> bool:
        """Answer each new state k with isq* = policy(k, state) (None: stay silent) until
        ``done()``; False when ``max_wall`` s passed first."""
        deadline = time.monotonic() + max_wall
        while not done():
            if time.monotonic() > deadline:
                return False
            if self.poll(min(0.05, max(0.0, deadline - time.monotonic()))) == 0:
                continue
            s = self.newest()
            if s is None:
                continue
            k = int(s[F['step_index']])
            if k <= self.answered:
                continue  # a re-sent state (lock-step) or one already answered
            isq = policy(k, s)
            if isq is not None:
                self.command(k, isq)
        return True

    def safe_stop(self) -> None:
        """Leave the drive commanding zero current (and no load); once."""
        if self.cmd_pub is None or self.stopped:
            return
        self.stopped = True
        from rclpy.duration import Duration

        s = self.newest()
        k = int(s[F['step_index']]) if s is not None else -1
        self.command(k if k > self.answered else -1, 0.0)
        self.command(-1, 0.0)
        # Delivered before this process goes (reliable only promises it while we live).
        self.cmd_pub.wait_for_all_acked(Duration(seconds=0.3))


@dataclass
class Options:
    config: str | None = None
    amplitude: float = 0.5
    step_duration: float = 0.02
    command_timeout: float | None = None
    max_speed: float = 30.0
    timeout: float = 10.0
    namespace: str | None = None
    json: str | None = None


def _rows_by_step(p: Probe, first: int, last: int) -> tuple[np.ndarray, int]:
    """States of steps first..last as a dense array indexed by step - first (NaN where a step
    was not received; the first copy of a re-sent state)."""
    out = np.full((last - first + 1, len(STATE_FIELDS)), np.nan)
    ok = p.lengths[: p.n] == len(STATE_FIELDS)
    s = p.states[: p.n][ok]
    k = s[:, F['step_index']].astype(np.int64)
    sel = (k >= first) & (k <= last)
    for row, kk in zip(s[sel][::-1], k[sel][::-1], strict=True):
        out[kk - first] = row
    return out, first


def run_check(
    opts: Options, node, log: Callable[[str], None], stop: Callable[[], bool]
) -> tuple[list[Item], dict]:
    """Probe the drive in ``node``'s namespace; return the items and run information."""
    from im_drive_sim.params import load_config

    cfg = load_config(opts.config)
    isq_max = cfg.machine.isq_max
    if not 0 < opts.amplitude <= 0.5 * isq_max:
        raise CheckRefused(
            f'--amplitude {opts.amplitude:g} A: must be in (0, '
            f'{0.5 * isq_max:g}] A (50 % of isq_max {isq_max:g} A)'
        )
    p = Probe(node)
    p.stop = stop
    state_topic = p.state_sub.topic_name
    cmd_topic = node.resolve_topic_name('drive/command')

    # -- discovery --------------------------------------------------------------------
    deadline = time.monotonic() + opts.timeout
    while not node.get_publishers_info_by_topic(state_topic):
        if time.monotonic() > deadline:
            raise CheckRefused(
                f'no publisher of {state_topic} within {opts.timeout:g} s '
                '(is the drive running, in this namespace and ROS_DOMAIN_ID?)'
            )
        p.poll(0.05)
    # Node names arrive a moment after the endpoints; other commanders with them.
    settle = time.monotonic() + 0.5
    drive_name = drive_ns = None
    while time.monotonic() < settle or drive_name is None:
        pubs = node.get_publishers_info_by_topic(state_topic)
        known = [e for e in pubs if not e.node_name.startswith('_NODE_NAME_UNKNOWN')]
        if known:
            drive_name, drive_ns = known[0].node_name, known[0].node_namespace
        if time.monotonic() > settle + 2.0:
            break
        if node.get_publishers_info_by_topic(cmd_topic):
            _refuse_commander(node, cmd_topic, p)
        p.poll(0.05)
    drive_full = (drive_ns.rstrip('/') + '/' + drive_name) if drive_name else '(unknown node)'

    timeout, timeout_src = _command_timeout(opts, node, drive_name, drive_ns)
    p.open_command()
    try:
        return _probe_and_judge(
            p, opts, node, cfg, drive_full, timeout, timeout_src, state_topic, cmd_topic, log
        )
    finally:
        p.safe_stop()  # zero current, whatever happened (also on SIGINT and errors)


def _probe_and_judge(
    p: Probe,
    opts: Options,
    node,
    cfg,
    drive_full: str,
    timeout: float,
    timeout_src: str,
    state_topic: str,
    cmd_topic: str,
    log: Callable[[str], None],
) -> tuple[list[Item], dict]:
    ts, ts_ns = cfg.Ts, cfg.Ts_ns
    isq_max = cfg.machine.isq_max
    a = opts.amplitude
    counts_per_rad = cfg.sensors.encoder_counts / (2.0 * math.pi)

    info = {
        'drive': drive_full,
        'namespace': node.get_namespace(),
        'Ts_s': ts,
        'isq_max_A': isq_max,
        'amplitude_A': a,
        'command_timeout_s': timeout,
        'command_timeout_source': timeout_src,
    }

    def check_alone() -> None:
        if len(node.get_publishers_info_by_topic(cmd_topic)) > 1:
            _refuse_commander(node, cmd_topic, p)

    # -- mode: does step_index advance without commands? ---------------------------------
    if not p.run(lambda k, s: None, lambda: p.newest() is not None, opts.timeout):
        raise CheckRefused(
            f'{state_topic} has a publisher but no state came within {opts.timeout:g} s'
        )
    k_idle0 = int(p.newest()[F['step_index']])
    t_end = time.monotonic() + 0.3
    p.run(lambda k, s: None, lambda: time.monotonic() > t_end, 1.0)
    idle_advance = int(p.newest()[F['step_index']]) - k_idle0
    realtime = idle_advance >= 5
    mode = 'realtime' if realtime else 'lockstep'
    status_mode = p.status.get('mode')
    mode_note = ''
    if status_mode is not None and status_mode != mode:
        mode_note = f'drive/status says mode={status_mode}'
    info['mode'] = mode
    log(
        f'check_drive: drive {drive_full}, mode {mode} (by behaviour; drive/status: '
        f'{status_mode or "not seen yet"}), Ts {ts * 1e6:g} us, isq_max {isq_max:g} A, '
        f'step +-{a:g} A, command_timeout {timeout:g} s ({timeout_src})'
    )
    check_alone()

    def schedule(
        segments: list[tuple[int, float]],
        record: list | None = None,
        guard: Callable[[np.ndarray], bool] | None = None,
    ) -> int:
        """Answer states with piecewise-constant isq*: ``segments`` of (steps, isq*),
        counted in step indices from the first state answered. ``record`` collects
        (k, level, previous level) at every change; ``guard(state)`` True aborts to zero.
        Returns the first step index answered."""
        total = sum(n for n, _ in segments)
        bounds = np.cumsum([n for n, _ in segments])
        st = {'k0': None, 'last': None, 'done': False}

        def policy(k: int, s: np.ndarray) -> float | None:
            if st['k0'] is None:
                st['k0'] = k
            rel = k - st['k0']
            if guard is not None and guard(s):
                st['done'] = True
                return 0.0  # abort to zero current at once
            if rel >= total:
                st['done'] = True
                return None  # the next phase answers this state
            level = segments[int(np.searchsorted(bounds, rel, side='right'))][1]
            if record is not None and level != st['last']:
                record.append((k, level, 0.0 if st['last'] is None else st['last']))
            st['last'] = level
            return level

        if not p.run(policy, lambda: st['done'], 5.0 + total * ts * 20):
            raise DriveLost(
                f'the drive stopped stepping (last state '
                f'{int(p.newest()[0])}, {p.n} states received)'
            )
        return st['k0']

    # -- rate: zero current, answer every state; and no current before the whole graph is
    # known (another commander discovered late must still refuse the check) -------------
    i_rate0, m_rate0 = p.n, p.m
    t0 = time.monotonic()
    while True:
        schedule([(2500 if realtime else 500, 0.0)])
        if time.monotonic() >= p.created + DISCOVERY_SETTLE_S:
            break
    rate_wall = time.monotonic() - t0
    i_rate1 = p.n
    check_alone()

    # -- latency: small level changes, every 25 steps -----------------------------------
    trans: list[tuple[int, float, float]] = []
    levels = [0.0, a, 0.0, -a, 0.0, a, 0.0, -a, 0.0]
    schedule([(25, lv) for lv in levels], trans)

    # -- step response ----------------------------------------------------------------
    n_step = max(10, round(opts.step_duration / ts))
    step_trans: list[tuple[int, float, float]] = []
    aborted = {'why': ''}

    def overspeed(s: np.ndarray) -> bool:
        if abs(s[F['omega_meas']]) > opts.max_speed:
            aborted['why'] = (
                f'aborted: |omega_meas| {abs(s[F["omega_meas"]]):.1f} > {opts.max_speed:g} rad/s'
            )
            return True
        return False

    schedule([(25, 0.0), (n_step, a), (n_step, -a), (n_step // 2, 0.0)], step_trans, overspeed)
    k_step_end = p.answered
    check_alone()

    # -- watchdog -----------------------------------------------------------------------
    w = a / 2
    if realtime:
        wd = _watchdog_realtime(p, schedule, w, timeout, overspeed, ts)
    else:
        wd = _watchdog_lockstep(p)
    schedule([(50 if realtime else 10, 0.0)])
    check_alone()
    # A status message (about 1 Hz) to cross-check the mode, if none came yet.
    if status_mode is None and realtime:
        t_end = time.monotonic() + 1.2
        p.run(lambda k, s: 0.0, lambda: bool(p.status) or time.monotonic() > t_end, 2.0)
        status_mode = p.status.get('mode')
        if status_mode is not None and status_mode != mode:
            mode_note = f'drive/status says mode={status_mode}'
    info['status_mode'] = status_mode
    p.safe_stop()  # before judging: the drive is not left waiting for commands meanwhile

    # ================================ judging ========================================
    items: dict[str, Item] = {}
    endpoints = {
        'drive/state': [e.topic_type for e in node.get_publishers_info_by_topic(state_topic)],
        'drive/command': [e.topic_type for e in node.get_subscriptions_info_by_topic(cmd_topic)],
        'drive/joint_states': [
            e.topic_type
            for e in node.get_publishers_info_by_topic(
                node.resolve_topic_name('drive/joint_states')
            )
        ],
        'drive/status': [
            e.topic_type
            for e in node.get_publishers_info_by_topic(node.resolve_topic_name('drive/status'))
        ],
    }
    items['topics'] = judge_topics(endpoints)

    n = p.n
    bound = CURRENT_BOUND_FACTOR * math.hypot(isq_max, cfg.machine.rated_flux_current)
    sp = state_field_problems(p.states[:n], p.lengths[:n], p.seq[:n], ts_ns, realtime, bound)
    k_first = step_trans[0][0] if step_trans else k_step_end
    dense, _ = _rows_by_step(p, k_first, k_step_end + 1)
    motion = dense[np.isfinite(dense[:, F['theta_meas']])]
    if len(motion) > 20 and np.all(np.diff(motion[:, 0]) == 1):
        th = motion[:, F['theta_meas']]
        ratio = units_ratio(th, motion[:, F['omega_meas']], ts)
        motion_counts = float(np.ptp(th) * counts_per_rad)
    else:
        ratio, motion_counts = math.nan, 0.0
    joints_ok_type = endpoints['drive/joint_states'] and all(
        t == TYPES['drive/joint_states'] for t in endpoints['drive/joint_states']
    )
    ok_rows = p.lengths[:n] == len(STATE_FIELDS)
    jp = (
        joint_state_problems(
            np.array(p.joints, dtype=float).reshape(-1, 4), p.states[:n][ok_rows], ts_ns
        )
        if joints_ok_type
        else None
    )
    items['fields'] = judge_fields(sp, ratio, motion_counts, jp)

    steps = p.states[:n, F['step_index']]
    if realtime:
        sl = slice(i_rate0, i_rate1)
        items['rate'] = judge_rate_realtime(
            period_stats(steps[sl], p.source_ns[sl], ts), ts, mode_note
        )
    else:
        new, unanswered, skipped = lockstep_step_problems(
            steps[:n], p.take_ns[:n], p.cmd[: p.m, 0], p.cmd_ns[: p.m]
        )
        rate_steps = np.count_nonzero(np.diff(steps[i_rate0:i_rate1]) > 0)
        items['rate'] = judge_rate_lockstep(
            new, unanswered, skipped, idle_advance, rate_steps / rate_wall, mode_note
        )

    # latency: wall time command(k) -> state k+1 received, and the onset of each change
    by_step = {}
    for i in range(n):
        if ok_rows[i]:
            by_step.setdefault(int(steps[i]), i)
    wall = []
    for j in range(m_rate0, p.m):
        k = int(p.cmd[j, 0])
        i = by_step.get(k + 1)
        if k >= 0 and i is not None:
            wall.append((p.recv_ns[i] - p.cmd_ns[j]) * 1e-9)
    delays = []
    for k0, level, prev in trans[1:] + step_trans[1:]:
        d, _ = _rows_by_step(p, k0 - 20, k0 + 25)
        delays.append(onset_delay(d[:, F['isq']], 20, level - prev))
    items['latency'] = judge_latency(delays, np.array(wall), realtime)

    # step response
    if len(step_trans) >= 4 and not aborted['why']:
        metrics = []
        for (k0, level, prev), (k1, _, _) in itertools.pairwise(step_trans[1:4]):
            d, _ = _rows_by_step(p, k0 - 20, k1)
            delay = onset_delay(d[:, F['isq']], 20, level - prev)
            seg = d[20 : k1 - k0 + 20]
            metrics.append(
                step_metrics(
                    StepSegment(
                        level, prev, seg[:, F['isq']], seg[:, F['torque']], seg[:, F['theta_meas']]
                    ),
                    ts,
                    delay,
                )
            )
        items['step_response'] = judge_step_response(metrics[0], metrics[1], a, counts_per_rad)
    else:
        nan = {
            'rise_s': math.nan,
            'steady_error': math.nan,
            'torque_per_amp': math.nan,
            'accel': math.nan,
            'duration_s': 0.0,
        }
        items['step_response'] = judge_step_response(
            nan, nan, a, counts_per_rad, aborted['why'] or 'step test incomplete'
        )

    if realtime:
        items['watchdog'] = judge_watchdog_realtime(
            wd['t_act'], wd['t_zero'], timeout, wd['resumed_s'], timeout_src, wd['aborted']
        )
    else:
        items['watchdog'] = judge_watchdog_lockstep(
            wd['silence_s'], wd['advanced'], wd['resumed_s']
        )
    return [items[name] for name in ITEMS], info


def _watchdog_realtime(p: Probe, schedule, w: float, timeout: float, overspeed, ts: float) -> dict:
    """Command w, go silent until zero current (or too long), then command -w for as long
    as w was on (so the shaft ends near rest) and check that the current follows."""
    _lo, hi = watchdog_limits(timeout)
    i_on = p.n
    schedule([(25, w)])
    i_silent, t_last = p.n, p.cmd_ns[p.m - 1]
    st = {'zero_at': None, 'zero_run': 0, 'why': ''}
    end = time.monotonic() + 2 * hi + 0.05

    def silent(k: int, s: np.ndarray) -> None:
        return None

    def done() -> bool:
        for i in range(st.get('i', i_silent), p.n):
            s = p.states[i]
            if abs(s[F['isq']]) < ZERO_CURRENT_FRACTION * w:
                if st['zero_at'] is None:
                    st['zero_at'] = i
                st['zero_run'] += 1
            else:
                st['zero_at'], st['zero_run'] = None, 0
            if overspeed(s):
                st['why'] = 'aborted silence: overspeed'
        st['i'] = p.n
        return st['zero_run'] >= 10 or bool(st['why']) or time.monotonic() > end

    p.run(silent, done, 2 * hi + 1.0)
    t_zero = t_act = None
    if st['zero_at'] is not None:
        t_zero = (p.source_ns[st['zero_at']] - t_last) * 1e-9
        i = st['zero_at']  # back along the fall to where it began
        while i > i_silent and p.states[i - 1, F['isq']] < WATCHDOG_ACT_FRACTION * w:
            i -= 1
        t_act = (p.source_ns[i] - t_last) * 1e-9
    if st['why']:
        p.command(max(p.answered, int(p.newest()[0])), 0.0)
    # Steps at +w: as many at -w bring the shaft back near rest.
    on = int(np.count_nonzero(p.states[i_on : p.n, F['isq']] > w / 2))
    # resume with -w; it must reach -w within 50 ms
    i_res, j_res, t_res = p.n, p.m, None
    k_res = schedule([(max(on, 50), -w)])
    for i in range(i_res, p.n):
        s = p.states[i]
        if s[F['step_index']] > k_res and abs(s[F['isq']] + w) < ZERO_CURRENT_FRACTION * w:
            t_res = (p.source_ns[i] - p.cmd_ns[j_res]) * 1e-9
            break
    if t_res is not None and t_res > 0.05:
        t_res = None
    return {'t_act': t_act, 't_zero': t_zero, 'resumed_s': t_res, 'aborted': st['why']}


def _watchdog_lockstep(p: Probe) -> dict:
    """Silence for LOCKSTEP_SILENCE_S: only re-sends of the same state allowed; then one
    command must make it step."""
    k_last = p.answered
    t0 = time.monotonic()
    i0 = p.n
    p.run(lambda k, s: None, lambda: time.monotonic() - t0 >= LOCKSTEP_SILENCE_S, 2.0)
    silence = time.monotonic() - t0
    ks = p.states[i0 : p.n, F['step_index']]
    advanced = int(np.count_nonzero(ks > k_last + 1))
    s = p.newest()
    k = int(s[F['step_index']])
    t1 = time.monotonic()
    p.command(k, 0.0)
    resumed = None
    while time.monotonic() - t1 < 2.0:
        p.poll(0.05)
        if int(p.newest()[F['step_index']]) > k:
            resumed = time.monotonic() - t1
            break
    return {'silence_s': silence, 'advanced': advanced, 'resumed_s': resumed}


def _clean(obj):
    """JSON-ready: non-finite floats -> None, numpy scalars -> Python."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def _refuse_commander(node, topic: str, p: Probe) -> None:
    """Raise CheckRefused naming the other publishers of ``topic`` (their node names are
    discovered a moment after the endpoints: wait up to 1 s for them)."""
    deadline = time.monotonic() + 1.0
    while True:
        others = [
            e
            for e in node.get_publishers_info_by_topic(topic)
            if not (e.node_name == node.get_name() and e.node_namespace == node.get_namespace())
        ]
        if time.monotonic() > deadline or not any(
            e.node_name.startswith('_NODE_NAME_UNKNOWN') for e in others
        ):
            break
        p.poll(0.05)
    names = sorted({(e.node_namespace.rstrip('/') + '/' + e.node_name) for e in others})
    raise CheckRefused(
        f'{", ".join(names) or "another node"} already publishes {topic}: a '
        'controller is connected and two commanders would fight; stop it first'
    )


def _command_timeout(
    opts: Options, node, drive_name: str | None, drive_ns: str | None
) -> tuple[float, str]:
    """The expected watchdog time: --command-timeout, else the drive node's
    ``command_timeout`` parameter, else 0.05 s."""
    if opts.command_timeout is not None:
        return opts.command_timeout, '--command-timeout'
    if drive_name is None:
        return DEFAULT_TIMEOUT, 'default'
    from rcl_interfaces.msg import ParameterType
    from rcl_interfaces.srv import GetParameters
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    helper = Node('check_drive_params', context=node.context)
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(helper)
    try:
        srv = drive_ns.rstrip('/') + '/' + drive_name + '/get_parameters'
        client = helper.create_client(GetParameters, srv)
        if not client.wait_for_service(timeout_sec=2.0):
            return DEFAULT_TIMEOUT, 'default: drive has no parameter service'
        future = client.call_async(GetParameters.Request(names=['command_timeout']))
        executor.spin_until_future_complete(future, timeout_sec=3.0)
        res = future.result()
        if res is None:
            return DEFAULT_TIMEOUT, 'default: no parameter answer'
        v = res.values[0] if res.values else None
        if v is not None and v.type == ParameterType.PARAMETER_DOUBLE:
            return float(v.double_value), 'drive parameter'
        return DEFAULT_TIMEOUT, 'default: drive has no command_timeout'
    finally:
        executor.shutdown()
        helper.destroy_node()


# ========================================== CLI ============================================


class _Parser(Parser):
    def error(self, message: str) -> None:  # one line, exit 2
        print(f'error: check_drive: {message}', file=sys.stderr)
        sys.exit(2)


def parse_args(argv: list[str]) -> Options:
    ap = _Parser(
        prog='ros2 run im_controller check_drive',
        description='Check a drive node against docs/interfaces.md (see '
        'docs/check-drive.md). Exit 0: all items pass; 1: some fail; '
        '2: refused (bad option, no drive, another commander).',
    )
    ap.add_argument(
        '--namespace', help='namespace of the drive (also: --ros-args -r __ns:=/bench1)'
    )
    ap.add_argument(
        '--config',
        metavar='FILE',
        type=input_file,
        help='drive parameter file (Ts, isq_max, encoder); default: the packaged motor',
    )
    ap.add_argument(
        '--amplitude',
        type=float,
        default=0.5,
        help='current step [A] (default 0.5; at most 50 %% of isq_max)',
    )
    ap.add_argument(
        '--step-duration',
        type=float,
        default=0.02,
        help='duration of each of the +isq and -isq steps [s] (default 0.02)',
    )
    ap.add_argument(
        '--command-timeout',
        type=float,
        help="expected watchdog time [s] (default: the drive's command_timeout "
        'parameter, else 0.05)',
    )
    ap.add_argument(
        '--max-speed',
        type=float,
        default=30.0,
        help='abort to zero current above this |omega_meas| [rad/s] (default 30)',
    )
    ap.add_argument(
        '--timeout', type=float, default=10.0, help='discovery timeout [s] (default 10)'
    )
    ap.add_argument(
        '--json',
        metavar='FILE',
        type=output_file,
        help='write the results as JSON (checked before probing)',
    )
    ns = ap.parse_args(argv)
    for name in ('amplitude', 'step_duration', 'max_speed', 'timeout', 'command_timeout'):
        v = getattr(ns, name)
        if v is not None and not (math.isfinite(v) and v > 0):
            ap.error(f'--{name.replace("_", "-")} must be a positive number, got {v:g}')
    if not 0.005 <= ns.step_duration <= 0.5:
        ap.error(f'--step-duration {ns.step_duration:g} s: must be in [0.005, 0.5] s')
    if ns.config is not None:  # the file is read after the probe starts: check it now
        from im_drive_sim.params import ConfigError, load_config

        try:
            load_config(ns.config)
        except ConfigError as exc:
            ap.error(str(exc))
        ns.config = str(ns.config)
    if ns.json is not None:
        ns.json = str(ns.json)
    if ns.namespace is not None:
        from rclpy.validate_namespace import validate_namespace

        try:
            validate_namespace(ns.namespace if ns.namespace.startswith('/') else '/' + ns.namespace)
        except Exception as exc:  # rclpy raises InvalidNamespaceException
            ap.error(f'--namespace {ns.namespace!r}: {str(exc).splitlines()[0]}')
    return Options(**vars(ns))


def main(args: list[str] | None = None) -> int:
    argv = sys.argv if args is None else args
    try:
        rest = check_ros_args(argv)
    except UsageError as exc:
        print(f'error: check_drive: {exc}', file=sys.stderr)
        return 2
    opts = parse_args(rest[1:])
    import rclpy
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    from im_drive_sim.params import ConfigError

    stop = {'signal': None}

    def on_signal(signum, _frame) -> None:
        stop['signal'] = signum

    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    node = Node('check_drive', **({'namespace': opts.namespace} if opts.namespace else {}))
    code = 0
    try:
        items, info = run_check(
            opts, node, lambda s: print(s, flush=True), lambda: stop['signal'] is not None
        )
        for item in items:
            print(item.line())
        print(summary_line(items, info.get('mode', ''), info.get('status_mode')))
        code = 0 if all(i.passed for i in items) else 1
        if opts.json:
            Path(opts.json).write_text(
                json.dumps(
                    _clean({'passed': code == 0, **info, 'items': [asdict(i) for i in items]}),
                    indent=1,
                    allow_nan=False,
                )
                + '\n'
            )
    except (CheckRefused, ConfigError) as exc:
        print(f'error: check_drive: {exc}', file=sys.stderr)
        code = 2
    except DriveLost as exc:
        print(f'error: check_drive: {exc}', file=sys.stderr)
        code = 1
    except Interrupted:
        print('check_drive: interrupted; zero current commanded', file=sys.stderr)
        code = 130
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
