"""check_drive's pure judges of what the drive publishes: the ``topics``, ``fields`` and
``rate`` items, and the summary line. Numpy arrays in, an :class:`Item` out (the items of
the drive's response to commands: :mod:`.response`).

No ROS: the tests call them on synthetic arrays, the evaluation on what the probe recorded.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..contract import COMMAND_DELAYS, COMMAND_TOPIC, STATE_FIELDS, STATE_INDEX as F, TOPIC_TYPES
from . import thresholds as TH

# ================================ pure judging functions ===================================


def judge_topics(endpoints: dict[str, list[str]]) -> TH.Item:
    """``endpoints``: for 'drive/state', 'drive/joint_states', 'drive/status' the types of
    their publishers, for 'drive/command' the types of its subscribers other than us."""
    problems, seen = [], []
    for topic, want in TOPIC_TYPES.items():
        role = 'subscriber' if topic == COMMAND_TOPIC else 'publisher'
        types = endpoints.get(topic, [])
        if not types:
            problems.append(f'no {role} on {topic}')
        elif any(t != want for t in types):
            problems.append(f'{topic} {role} type {",".join(sorted(set(types)))}')
        else:
            seen.append(topic)
    figures = '; '.join(problems) if problems else f'{len(seen)}/4 topics with the right types'
    return TH.Item(
        'topics',
        not problems,
        figures,
        'drive/state + drive/joint_states + drive/status published, drive/command '
        'subscribed, types ' + ', '.join(f'{t.split("/")[-1]}' for t in TOPIC_TYPES.values()),
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
    cur = np.abs(s[:, [F[c] for c in TH.CURRENT_FIELDS]]).max()
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
    # every 10 steps: their spacings' greatest common divisor is 10 (a drive on the wall
    # clock skips the periods its late loop missed, and the link may lose one: a median
    # spacing is 20 on a loaded machine)
    steps = np.unique(joints[:, 0].astype(np.int64)) // ts_ns
    every = int(np.gcd.reduce(np.diff(steps))) if len(steps) > 2 else 10
    if every != 10:
        problems.append(f'joint_states every {every} steps, not 10')
    return problems


def judge_fields(
    state_problems: list[str],
    ratio: float,
    motion_counts: float,
    joint_problems: list[str] | None,
    host: str = '',
    doubt_band: tuple[float, float] = TH.UNITS_LATE_BAND,
) -> TH.Item:
    """Combine the field checks; ``joint_problems`` None = not judged (wrong topic type,
    reported by 'topics'). ``host``: why the units ratio cannot be trusted ('' when it
    can: the drive kept its periods during the motion); a ratio out of its band but
    inside ``doubt_band`` (what the host can bend it to) is then inconclusive, not a
    failure, unless another field problem fails the item."""
    problems = list(state_problems)
    units_doubt = ''
    if motion_counts >= TH.UNITS_MIN_COUNTS:
        lo, hi = TH.UNITS_RATIO_BAND
        if not lo <= ratio <= hi:
            if host and doubt_band[0] <= ratio <= doubt_band[1]:
                units_doubt = (
                    f'the units ratio {ratio:.3g} is outside [{lo}, {hi}] while {host} during '
                    'the step test (a late sample is not where k Ts says)'
                )
            else:
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
    item = TH.Item(
        'fields',
        not problems and not units_doubt,
        figures,
        f'{len(STATE_FIELDS)} finite values, time_ns = k Ts exactly, currents plausible, '
        f'ratio in [{TH.UNITS_RATIO_BAND[0]}, {TH.UNITS_RATIO_BAND[1]}], joint_states = state',
        {
            'problems': problems,
            'units_ratio': TH.finite_or_none(ratio),
            'motion_counts': float(motion_counts),
        },
    )
    return item.undecided(units_doubt) if units_doubt and not problems else item


def clock_period(steps: np.ndarray, source_ts_ns: np.ndarray) -> float:
    """The drive's clock [s per step]: the slope of its publication times over its step
    index, fitted to the punctual half of the periods (least squares, then three times
    again on the points at or below the median residual: the lower envelope). A late
    period publishes late but does not move the envelope; NaN with fewer than 10 states."""
    ok = np.isfinite(steps)
    k = steps[ok].astype(np.float64)
    if len(k) < 10 or np.ptp(k) == 0:
        return math.nan
    k = k - k[0]
    t = (source_ts_ns[ok].astype(np.int64) - int(source_ts_ns[ok][0])) * 1e-9
    slope, icpt = np.polyfit(k, t, 1)
    for _ in range(3):
        r = t - (slope * k + icpt)
        keep = r <= np.median(r)
        if np.count_nonzero(keep) < 5 or np.ptp(k[keep]) == 0:
            break
        slope, icpt = np.polyfit(k[keep], t[keep], 1)
    return float(slope)


def period_stats(
    steps: np.ndarray, source_ts_ns: np.ndarray, ts: float, seq: np.ndarray | None = None
) -> dict[str, float]:
    """Publication periods [s] from the drive's own source time stamps, per step: median,
    10th, 90th and 99th percentile, mean, the fraction of steps that took longer than 2 Ts,
    the drive's clock (:func:`clock_period`), and ``skipped``: how often the step index
    advanced by more than one where nothing was lost in transit (``seq``, the publication
    sequence numbers, consecutive; without them every jump counts) -- a drive on the wall
    clock that skips the periods its late loop missed."""
    dk = np.diff(steps)
    lossless = np.diff(seq) == 1 if seq is not None else np.ones(len(dk), dtype=bool)
    skipped = int(np.count_nonzero(lossless & (dk > 1)))
    keep = dk > 0
    per_step = np.diff(source_ts_ns.astype(np.float64))[keep] / dk[keep] * 1e-9
    if len(per_step) == 0:
        figures = ('median', 'p99', 'mean', 'long_fraction', 'p10', 'p90', 'clock')
        return {'n': 0, **dict.fromkeys(figures, math.nan), 'skipped': skipped}
    return {
        'n': len(per_step),
        'median': float(np.median(per_step)),
        'p99': float(np.percentile(per_step, 99)),
        'mean': float(np.mean(per_step)),
        'long_fraction': float(np.mean(per_step > 2 * ts)),
        'p10': float(np.percentile(per_step, 10)),
        'p90': float(np.percentile(per_step, 90)),
        'clock': clock_period(steps, source_ts_ns),
        'skipped': skipped,
    }


def judge_rate_realtime(
    stats: dict[str, float], ts: float, mode_note: str = '', busy: str = ''
) -> TH.Item:
    """Median period within RATE_TOLERANCE of Ts and at most RATE_MAX_LONG_FRACTION of
    periods longer than 2 Ts; inconclusive where that fails while the check fell behind
    (``busy``, the reason), unless the drive is paced wrong (its clock, or the spread of a
    drive that pauses, against Ts: docs/check-drive.md, ``rate``)."""
    clock = stats.get('clock', math.nan)
    p10, p90 = stats.get('p10', stats['median']), stats.get('p90', stats['median'])
    if stats.get('skipped', 0):
        paced = math.isfinite(clock) and abs(clock - ts) <= TH.CLOCK_TOLERANCE * ts
    else:
        paced = p10 <= (1 + TH.RATE_TOLERANCE) * ts and p90 >= (1 - TH.RATE_TOLERANCE) * ts
    ok = (
        stats['n'] >= 100
        and abs(stats['median'] - ts) <= TH.RATE_TOLERANCE * ts
        and stats['long_fraction'] <= TH.RATE_MAX_LONG_FRACTION
    )
    figures = (
        f'median period {stats["median"] * 1e6:.1f} us, p99 {stats["p99"] * 1e6:.0f} us, '
        f'mean {stats["mean"] * 1e6:.1f} us, {stats["long_fraction"] * 100:.2f} % '
        f'> 2 Ts over {stats["n"]} steps; clock {clock * 1e6:.1f} us/step'
    )
    if mode_note:
        figures += f'; {mode_note}'
    item = TH.Item(
        'rate',
        ok and not mode_note,
        figures,
        f'median {ts * 1e6:.0f} us +-{TH.RATE_TOLERANCE * 100:.0f} %, <= '
        f'{TH.RATE_MAX_LONG_FRACTION * 100:.0f} % of periods > 2 Ts',
        {k: TH.finite_or_none(v) for k, v in stats.items()},
    )
    # only the lateness may be the machine's fault: a wrong pace or mode never is
    return item.undecided(busy) if paced and not mode_note else item


def judge_rate_lockstep(
    steps: np.ndarray,
    take_ns: np.ndarray,
    cmd_answers: np.ndarray,
    cmd_pub_ns: np.ndarray,
    idle_advance: int,
    steps_per_s: float,
    mode_note: str = '',
) -> TH.Item:
    """Lock-step: every new step (``steps`` taken at ``take_ns``) follows a command
    answering the previous state (``cmd_answers``, published at ``cmd_pub_ns``), by one;
    none while idle (``idle_advance``)."""
    new = np.flatnonzero(np.diff(steps) > 0) + 1
    n_steps, unanswered, skipped = len(new), 0, 0
    for i in new:
        k, prev = steps[i], steps[i - 1]
        if k - prev != 1:
            skipped += 1
        sel = (cmd_answers == prev) | (cmd_answers < 0)
        if not np.any(cmd_pub_ns[sel] <= take_ns[i]):
            unanswered += 1
    ok = n_steps > 0 and unanswered == 0 and skipped == 0 and idle_advance == 0 and not mode_note
    figures = (
        f'{n_steps} steps, {unanswered} without a command, {skipped} skipping, '
        f'{idle_advance} while idle; {steps_per_s:.0f} steps/s'
    )
    if mode_note:
        figures += f'; {mode_note}'
    return TH.Item(
        'rate',
        ok,
        figures,
        'lock-step: one step per command, none without one',
        {
            'steps': n_steps,
            'unanswered': unanswered,
            'skipped': skipped,
            'idle_advance': idle_advance,
            'steps_per_s': TH.finite_or_none(steps_per_s),
        },
    )


def summary_line(items: Sequence[TH.Item], mode: str = '', status_mode: str | None = None) -> str:
    """The last line: verdict, failing and inconclusive items, the mode (and what
    drive/status said)."""
    failed = [i.name for i in items if i.verdict == 'fail']
    undecided = [i.name for i in items if i.verdict == 'inconclusive']
    passed = sum(i.verdict == 'pass' for i in items)
    n = len(items)
    if not failed and not undecided:
        verdict = f'all {n} items PASS'
    else:
        verdict = f'{passed}/{n} items pass'
        if failed:
            verdict += f'; FAIL: {", ".join(failed)}'
        if undecided:
            verdict += (
                f'; INCONCLUSIVE: {", ".join(undecided)} (the check or the link fell behind: '
                'run it again on a quieter machine or link)'
            )
    how = f' ({mode}; drive/status mode={status_mode or "not seen"})' if mode else ''
    return f'check_drive: {verdict}{how}'


def conditions_line(conditions: dict[str, dict]) -> str:
    """One line: how the check itself kept up in each phase (docs/check-drive.md, "When
    the check falls behind")."""
    parts = []
    for phase, c in conditions.items():
        fresh = c.get('fresh')
        late = c.get('late_p99_s')
        parts.append(
            f'{phase} '
            + (f'{fresh * 100:.0f} % in time' if fresh is not None else 'no commands')
            + (f', p99 {late * 1e3:.2f} ms late' if late is not None else '')
            + (f', {c["lost"]} lost' if c.get('lost') else '')
        )
    return 'check_drive: its own timing: ' + '; '.join(parts)


def exit_code(items: Sequence[TH.Item]) -> int:
    """0: every item passes; 1: some item fails; 3: none fails, some inconclusive."""
    verdicts = {i.verdict for i in items}
    if 'fail' in verdicts:
        return 1
    return 3 if 'inconclusive' in verdicts else 0
