"""What this host lets a 5 kHz loop do: the loop's own wait (``loop_clock``) run alone on
the wall clock (:func:`measure`; in a thread of its own with the real-time options applied:
:func:`probe`), the periods it held, and what that means for an experiment's timing
(:func:`judge`): ``ros2 run im_drive_sim host_check``, and a run's check before its first
experiment (:func:`check_before_run`). What it reports and why: docs/real-drive.md, "Check
the host first" and "Timing tolerance". Pure: numpy (numba in the measurement), no rclpy.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from . import rt

#: An experiment's periods (1.125 s at 200 us: the paper's move and load step).
EXPERIMENT_PERIODS = 5625
#: The period of the loop the host is checked for [s].
TS = 200e-6
#: The composed loop's busy-wait before each period start [us] (``rt.SPIN_US``).
SPIN_US = rt.SPIN_US
#: The share of experiments a tolerance must let count (the host check's verdict).
MEET_SHARE = 0.95

#: Held periods in an experiment -> the 95th percentile of the change of its loss [%],
#: the worst placement (at random or one burst) of docs/real-drive.md's held-period table
#: ("Why 10"; ``research/held.py``), made monotone. Beyond the last row nothing was measured.
LOSS_CHANGE_P95: tuple[tuple[int, float], ...] = (
    (0, 0.0),
    (1, 0.83),
    (2, 1.40),
    (5, 1.40),
    (10, 1.95),
    (20, 8.77),
    (50, 8.77),
)


def loss_change_pct(tolerance: int) -> float:
    """The 95th-percentile change of a loss [%] that ``tolerance`` held periods may bring
    (:data:`LOSS_CHANGE_P95`, the first row at or above it); ``inf`` beyond the table."""
    for held, pct in LOSS_CHANGE_P95:
        if tolerance <= held:
            return pct
    return math.inf


@dataclass
class HostFloor:
    """One measurement of the host's floor, and its verdict (:func:`judge`)."""

    seconds: float  #: measured [s]
    spin_us: float  #: the wait's busy-wait before each start [us]
    periods: int  #: periods that went by
    overruns: int  #: starts more than a period late
    held: int  #: periods those starts skipped (a drive that cannot pause held them)
    late_pct: float  #: overruns / periods [%] (``benchmarks/loop_floor.py``'s figure)
    held_pct: float  #: held / periods [%]
    late_per_s: float  #: overruns per second
    max_lateness_us: float  #: the worst start [us]
    histogram: dict[str, int]  #: period starts per lateness bin (``pacing.LATENESS_BINS``)
    bursts: dict[str, int]  #: runs of consecutive held periods, by length
    longest_burst: int  #: the longest such run [periods]
    #: over every experiment-long window of the measurement: held periods per experiment
    held_per_experiment: dict[str, float] = field(default_factory=dict)
    tolerance_checked: int = 10  #: the tolerance judged (``share_meeting``)
    share_meeting: float = 1.0  #: the share of experiments with at most that many held
    tolerance: int = 0  #: the least tolerance that MEET_SHARE of the experiments meet
    loss_change_pct: float = 0.0  #: what that tolerance may change a loss by (p95) [%]
    meets: bool = True  #: ``share_meeting`` >= MEET_SHARE
    realtime: dict[str, Any] = field(default_factory=dict)  #: ``rt.report()`` of the loop

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if not math.isfinite(d['loss_change_pct']):
            d['loss_change_pct'] = None  # JSON has no infinity
        return d


#: Bursts of held periods by length: 1, 2-4, 5-9, 10-49, 50 and more.
BURST_BINS = ('1', '2-4', '5-9', '10-49', '>=50')
BURST_EDGES = (1, 4, 9, 49)


def _bursts(held: np.ndarray) -> tuple[dict[str, int], int]:
    """Runs of consecutive held periods (an overrun skipping m is a run of m; adjacent
    ones merge), counted by length: 1, 2-4, 5-9, 10-49, >=50."""
    runs: list[int] = []
    end = -1  # the period after the last run
    for n in np.flatnonzero(held).tolist():
        m = int(held[n])
        if n == end:
            runs[-1] += m
        else:
            runs.append(m)
        end = n + m
    bins = dict.fromkeys(BURST_BINS, 0)
    for r in runs:
        bins[BURST_BINS[int(np.searchsorted(BURST_EDGES, r))]] += 1
    return bins, max(runs, default=0)


def judge(
    held: np.ndarray, tolerance: int = 10, window: int = EXPERIMENT_PERIODS
) -> dict[str, Any]:
    """Over every ``window``-long stretch of ``held`` (periods held at each period): the
    held periods an experiment there would have (p50, p95, max), the share with at most
    ``tolerance``, the least tolerance :data:`MEET_SHARE` of them meet and the change of a
    loss it allows. A measurement shorter than an experiment is judged on its rate (a
    Poisson guess: said so in ``held_per_experiment['from']``)."""
    h = np.asarray(held, np.int64)
    if len(h) >= window:
        c = np.concatenate(([0], np.cumsum(h)))
        per = c[window:] - c[:-window]
        src = 'windows'
    else:  # scaled: the rate over an experiment's length
        per = np.array([round(h.sum() * window / max(1, len(h)))], np.int64)
        src = 'rate'
    share = float(np.mean(per <= tolerance))
    need = int(np.quantile(per, MEET_SHARE, method='higher'))
    return {
        'held_per_experiment': {
            'p50': float(np.median(per)),
            'p95': float(need),
            'max': float(per.max()),
            'from': src,
        },
        'tolerance_checked': int(tolerance),
        'share_meeting': share,
        'tolerance': need,
        'loss_change_pct': loss_change_pct(need),
        'meets': share >= MEET_SHARE,
    }


def measure(
    seconds: float, spin_us: float = SPIN_US, tolerance: int = 10, ts: float = TS
) -> HostFloor:
    """Run the loop's wait alone for ``seconds`` on the wall clock (periods ``ts`` [s],
    busy-waiting the last ``spin_us`` [us] before each start) in the calling thread, and
    judge it against ``tolerance`` held periods per experiment (:func:`judge`)."""
    if not seconds > 0.0:
        raise ValueError(f'seconds must be > 0, got {seconds!r}')
    # (numba: imported when a loop runs, not with a command line that refuses at once)
    from . import loop_clock as LC
    from .pacing import LATENESS_BINS, LATENESS_EDGES_US

    ts_ns = round(ts * 1e9)
    n = max(1, int(seconds * 1e9 / ts_ns))
    T = np.zeros(LC.N_CLOCK, np.int64)
    hist = np.zeros(len(LATENESS_BINS), np.int64)
    edges = np.array([round(e * 1000) for e in LATENESS_EDGES_US], np.int64)
    scratch = np.zeros(2, np.int64)
    held = np.zeros(n, np.int64)

    def reset() -> None:
        T[:] = 0
        T[LC.T_TS], T[LC.T_SPIN], T[LC.T_WALL] = ts_ns, round(spin_us * 1e3), 1
        hist[:] = 0
        held[:] = 0
        T[LC.T_T0] = LC.now_ns(scratch, LC.CLOCK_MONOTONIC)

    reset()
    LC.run_schedule(T, held[:10], hist, edges, scratch)  # compiled (or loaded from the cache) here
    reset()
    t0 = time.perf_counter()
    LC.run_schedule(T, held, hist, edges, scratch)
    elapsed = time.perf_counter() - t0
    periods = int(T[LC.T_N])  # (the last start may have skipped past n)
    overruns, missed = int(T[LC.T_OVERRUNS]), int(T[LC.T_MISSED_TOTAL])
    bursts, longest = _bursts(held)
    verdict = judge(held, tolerance)
    return HostFloor(
        seconds=elapsed,
        spin_us=float(spin_us),
        periods=periods,
        overruns=overruns,
        held=missed,
        late_pct=100.0 * overruns / periods,
        held_pct=100.0 * missed / periods,
        late_per_s=overruns / elapsed,
        max_lateness_us=int(T[LC.T_MAX_LATE]) / 1000.0,
        histogram=dict(zip(LATENESS_BINS, hist.tolist(), strict=True)),
        bursts=bursts,
        longest_burst=longest,
        **verdict,
    )


def probe(
    seconds: float,
    opts: Any = None,
    tolerance: int = 10,
    spin_us: float = SPIN_US,
) -> HostFloor:
    """:func:`measure` in a thread of its own that runs as the loop would: the real-time
    options ``opts`` (``rt.RtOptions``; None: SCHED_FIFO 50, as the composed loop)
    applied to it, the CPU latency request held, timer slack 1 ns. The caller's thread is
    left as it was. ``realtime``: what the thread ran with (``rt.report``)."""
    import ctypes
    import threading

    options = rt.RtOptions(rt.DEFAULT_PRIORITY) if opts is None else opts
    out: dict[str, Any] = {}

    def body() -> None:
        try:
            refused = rt.apply(options)  # (a memory lock is the process's: kept)
            ctypes.CDLL(None).prctl(29, ctypes.c_ulong(1), 0, 0, 0)  # PR_SET_TIMERSLACK 1 ns
            floor = measure(seconds, spin_us, tolerance)
            floor.realtime = rt.report(options, refused)
            out['floor'] = floor
        except BaseException as exc:  # (handed to the caller's thread)
            out['error'] = exc

    t = threading.Thread(target=body, name='host-check', daemon=True)
    t.start()
    t.join()
    if 'error' in out:
        raise out['error']
    return out['floor']


# -- the check before a run ---------------------------------------------------------------
#: ``--timing-tolerance auto``: the tolerance the host check derives (never below the
#: default, whose held periods stay within the bench's noise).
AUTO = 'auto'
#: How long a run's check of its host lasts [s] (before the first experiment).
PROBE_S = 2.0
#: ``auto`` takes this many times what 95 % of the check's experiments held: a whole
#: real-time process holds more periods than the wait alone (research/NOTES.md, "From the
#: source of im_drive_sim.host").
AUTO_MARGIN = 2


def tolerance_arg(text: str) -> int | str:
    """argparse type of ``--timing-tolerance``: an integer 0-1000000 [held periods per
    experiment] or ``auto``."""
    if text.strip().lower() == AUTO:
        return AUTO
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"not an integer or 'auto': {text!r} [held periods per experiment]"
        ) from None
    if not 0 <= v <= 1_000_000:
        raise argparse.ArgumentTypeError(f'must be in [0, 1000000] periods, got {v} (or auto)')
    return v


tolerance_arg.__name__ = 'tolerance'


def loss_change_words(tolerance: int, noise: bool = False) -> str:
    """What ``tolerance`` held periods may do to a loss, in words (the held-period table);
    ``noise``: beside the bench's own noise."""
    pct = loss_change_pct(tolerance)
    if math.isfinite(pct) and noise:
        return (
            f"a loss may change by up to {pct:.2f} % (95th percentile; the bench's own noise "
            'is 2.4 %)'
        )
    if math.isfinite(pct):
        return f'a loss may change by up to {pct:.2f} %, 95th percentile'
    return (
        'more than the 50 held periods whose effect on a loss was measured (50 in one burst: '
        'up to 10.6 %)'
    )


def check_before_run(
    tolerance: int | str, default: int, opts: Any = None, seconds: float = PROBE_S
) -> tuple[int, dict[str, Any], str | None]:
    """A run's check of its host, before its first experiment: :func:`probe` for
    ``seconds``, judged at ``tolerance`` (``auto``: at ``default``). Returns the tolerance
    to run with (``auto``: the larger of ``default`` and :data:`AUTO_MARGIN` times what
    95 % of the experiments meet), the record (``as_dict`` and ``auto``) and one line to
    say, or None when there is nothing to say (a fixed tolerance the host meets)."""
    auto = tolerance == AUTO
    asked = default if auto else int(tolerance)
    f = probe(seconds, opts, asked)
    record = {**f.as_dict(), 'auto': auto}
    rt_seen = record.pop('realtime')  # (the run records its loop's own settings)
    record['policy'] = rt_seen.get('policy')
    record['pm_qos_held'] = rt_seen.get('pm_qos', {}).get('held')
    seen = (
        f'{f.seconds:.1f} s host check: late {f.late_pct:.3f} % of periods, worst '
        f'{f.max_lateness_us / 1000:.1f} ms'
    )
    if auto:
        chosen = max(default, AUTO_MARGIN * f.tolerance)
        record['tolerance_chosen'] = chosen
        line = (
            f'timing tolerance auto: {chosen} held periods per experiment ({seen}; 95 % of '
            f'its experiments meet {f.tolerance}, a whole run holds up to {AUTO_MARGIN}x that; '
            f'{loss_change_words(chosen)})'
        )
        return chosen, record, line
    if f.meets:
        return asked, record, None
    return (
        asked,
        record,
        (
            f'this host cannot meet --timing-tolerance {asked}: {100 * f.share_meeting:.0f} % of '
            f'experiments would ({seen}); 95 % meet {f.tolerance} '
            f'({loss_change_words(f.tolerance)}): give '
            '--timing-tolerance auto, or quieten the host (docs/real-drive.md, "Check the host '
            'first")'
        ),
    )
