"""check_drive's measure of itself: did the check keep up, and did the link deliver?
Per phase, from what was recorded (pure numpy, no ROS): the **command lag** by the
drive's ``applied_step`` labels, the **excess take delay** (publication to take, less the
smallest) and the states **lost** (publication sequence gaps); :func:`busy_reason` turns
them into the reason a timing verdict cannot be trusted ('' when the check kept up).
What each measures and why: docs/check-drive.md, "When the check falls behind".
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ..contract import STATE_FIELDS, STATE_INDEX as F
from .thresholds import BUSY_FRESH_MIN, BUSY_LATE_P99_S


def excess_delay(take_ns: np.ndarray, source_ns: np.ndarray) -> np.ndarray:
    """Per state: (take - source) - min(take - source) [s]; the clocks' offset cancels."""
    d = take_ns.astype(np.int64) - source_ns.astype(np.int64)
    if len(d) == 0:
        return np.zeros(0)
    return (d - d.min()) * 1e-9


def command_lag(states: np.ndarray, declared: int) -> np.ndarray:
    """step_index - declared - applied_step [periods] of the states that show a command
    applied (applied_step >= 0; a row that is not a full state shows none)."""
    a = states[:, F['applied_step']]
    lag = states[:, F['step_index']] - declared - a
    return lag[np.isfinite(lag) & (a >= 0)]


def drive_lateness(
    steps: np.ndarray, source_ns: np.ndarray, period_ns: float, window: int = 60
) -> tuple[np.ndarray, int]:
    """How late the drive published each of its steps, on its own clock: per step from
    the first received (``first``, returned) to the last, ``source - k period`` less the
    lower quartile of the same over the received steps within ``window`` steps either
    side [s]; NaN where no state of that step came (skipped by a drive that cannot pause,
    or lost). ``period_ns``: the drive's own period (its clock, ``judges.clock_period``;
    a drive paced wrong is judged by ``rate``, not here). The lower quartile (not the
    minimum: one early outlier) is the drive's on-time schedule there (docs/check-drive.md,
    "When the check falls behind")."""
    ok = np.isfinite(steps)
    k = steps[ok].astype(np.int64)
    if len(k) == 0:
        return np.zeros(0), 0
    first = int(k.min())
    t = source_ns[ok].astype(np.int64) - np.round((k - k.min()) * period_ns).astype(np.int64)
    off = np.full(int(k.max()) - first + 1, np.nan)
    # the first copy of each step (a lock-step drive re-sends)
    order = np.argsort(k, kind='stable')
    ks, ts_ = k[order], t[order]
    keep = np.concatenate(([True], np.diff(ks) != 0))
    ks, ts_ = ks[keep], ts_[keep]
    off[ks - first] = (ts_ - ts_[0]) * 1e-9
    out = np.full_like(off, np.nan)
    have = np.flatnonzero(np.isfinite(off))
    for i in have:
        lo, hi = np.searchsorted(have, (i - window, i + window + 1))
        out[i] = off[i] - np.percentile(off[have[lo:hi]], 25)
    return out, first


@dataclass
class Conditions:
    """What the check and the link did over one phase (its state rows)."""

    states: int  #: states received
    lost: int  #: states lost in transit (publication sequence gaps)
    fresh: float  #: fraction of the commanded states with lag 0 (answered in time)
    lag_max: float  #: largest command lag [periods]
    late_p99_s: float  #: 99th percentile of the excess take delay [s]
    late_max_s: float  #: largest excess take delay [s]

    def as_dict(self) -> dict:
        return {k: (v if not isinstance(v, float) or math.isfinite(v) else None)
                for k, v in asdict(self).items()}  # fmt: skip


def phase_conditions(
    states: np.ndarray,
    lengths: np.ndarray,
    seq: np.ndarray,
    excess: np.ndarray,
    declared: int,
    rows: slice,
) -> Conditions:
    """The measures over state ``rows`` (``excess``: :func:`excess_delay` of all rows)."""
    ok = lengths[rows] == len(STATE_FIELDS)
    s = states[rows][ok]
    q = seq[rows][ok]
    lost = int(np.sum(np.clip(np.diff(q) - 1, 0, None))) if len(q) > 1 else 0
    lag = command_lag(s, declared)
    ex = excess[rows][ok]
    return Conditions(
        states=len(s),
        lost=lost,
        fresh=float(np.mean(lag <= 0)) if len(lag) else math.nan,
        lag_max=float(lag.max()) if len(lag) else math.nan,
        late_p99_s=float(np.percentile(ex, 99)) if len(ex) else math.nan,
        late_max_s=float(ex.max()) if len(ex) else math.nan,
    )


def busy_reason(c: Conditions) -> str:
    """Why timing measured over this phase cannot be trusted ('' when the check kept up):
    it answered fewer than BUSY_FRESH_MIN of the periods in time, or took states more than
    BUSY_LATE_P99_S late (99th percentile)."""
    why = []
    if math.isfinite(c.fresh) and c.fresh < BUSY_FRESH_MIN:
        why.append(
            f'the check answered {c.fresh * 100:.0f} % of the periods in time '
            f'(lag up to {c.lag_max:.0f} periods)'
        )
    if math.isfinite(c.late_p99_s) and c.late_p99_s > BUSY_LATE_P99_S:
        why.append(f'it took states up to {c.late_p99_s * 1e3:.1f} ms late (p99)')
    if why and c.lost:
        why.append(f'{c.lost} states lost in transit')
    return '; '.join(why)
