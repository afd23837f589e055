"""check_drive's items, thresholds and result type (why each threshold: docs/check-drive.md).

Pure: no ROS, no numba (the drive's field layout and topic types: ``..contract``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

#: Items, in the order they are printed.
ITEMS: tuple[str, ...] = ('topics', 'fields', 'rate', 'latency', 'step_response', 'watchdog')

CURRENT_FIELDS = ('isd', 'isq', 'i_alpha', 'i_beta')

# --- thresholds (why: docs/check-drive.md) -----------------------------------------------
#: fields: currents must stay within this factor of the largest current the drive may carry
#: (hypot(isq_max, rated flux current)): beyond it, a value is not a current in A.
CURRENT_BOUND_FACTOR = 1.5
#: fields: integral of omega_meas over the motion / change of theta_meas (1 when both are SI;
#: 57.3 for degrees, 9.55 for rpm). The band absorbs encoder quantisation and filter lag.
UNITS_RATIO_BAND = (0.8, 1.25)
#: ... and the band a drive's late samples can bend it to: outside it the units are wrong
#: whatever the host (research/NOTES.md, "From the source of im_drive_sim.check_drive.thresholds").
UNITS_LATE_BAND = (0.5, 2.0)
#: watchdog: the times run from the first state received that shows the last command
#: applied; shown later than this fraction of the timeout after it was due, the start
#: is not known well enough to judge (inconclusive).
WATCHDOG_REF_SLACK = 0.1
#: fields: motion needed to judge the units [encoder counts of the configured encoder].
UNITS_MIN_COUNTS = 10
#: rate (real time): median period within this fraction of Ts ...
RATE_TOLERANCE = 0.10
#: ... and at most this fraction of periods longer than 2 Ts.
RATE_MAX_LONG_FRACTION = 0.20
#: rate (real time): the drive's clock -- the slope of its publication times over its step
#: index, fitted to the punctual half of the periods -- within this fraction of Ts: a
#: drive that cannot pause keeps to the wall clock however loaded the machine (NOTES, as
#: for UNITS_LATE_BAND).
CLOCK_TOLERANCE = 0.02
#: The check kept up over a phase when it answered at least this fraction of the periods
#: in time (the drive's applied_step labels: lag 0) ...
BUSY_FRESH_MIN = 0.5
#: ... and took the states at most this late (99th percentile of the delay from the
#: drive's publication to the check's take, less the smallest) [s]. Otherwise the timing
#: items it judged there are `inconclusive`, not failed (conditions.py).
BUSY_LATE_P99_S = 2e-3
#: step_response: the step the drive was given is the one commanded when no more than this
#: many consecutive states are missing in it ...
STEP_GAP_MAX = 10
#: ... and its commands reached the drive at most this fraction of the step's duration
#: late (by its labels): the last quarter, where the steady state is measured, is then
#: still inside the applied step.
STEP_LAG_FRACTION = 0.25
#: latency: command published -> next state received, wall time [s].
LATENCY_MEDIAN_MAX = 2e-3
LATENCY_P99_MAX = 20e-3
#: latency: the state in which a command first shows: k+d for a command answering state k,
#: d the drive's declared command_delay (1 or 2). Real time allows this many periods of
#: transport more (k+d+1), judged on the fastest quarter of the changes.
TRANSPORT_SLACK_REALTIME = 1
#: latency: the drive's labels must be honest, whatever the transport: a change never
#: shows after the first state whose applied_step is the changing command's (or newer) --
#: in no change in lock-step, in at most this fraction of the detected ones in real time.
LABEL_SLOWER_MAX_REALTIME = 0.25
#: The drive's host: a period of the drive is *on time* when the drive published its
#: state at most this late against its own schedule [s] (the lower quartile of its
#: publication times less k Ts around it). The labels are judged on the changes whose
#: periods were all on time (``latency``); the units ratio only where ...
DRIVE_LATE_MAX_S = 100e-6
#: ... at most this fraction of the step's periods were late or skipped (held).
DRIVE_LATE_SHARE_MAX = 0.05
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
#: DDS: every 3 s); a second commander found by then refuses the check.
DISCOVERY_SETTLE_S = 3.2
DEFAULT_TIMEOUT = 0.05  # [s] command_timeout when the drive has no such parameter
#: [s] the whole check's limit beyond --timeout (finding the drive): a check not ended by
#: then stops at zero current, INCONCLUSIVE, exit 3
CHECK_LIMIT_S = 60.0


class CheckRefused(Exception):
    """The check cannot run (bad option, no drive, another commander): exit code 2."""


def finite_or_none(x: float | None) -> float | None:
    """A figure for an :class:`Item`'s ``values``: None unless a finite number (JSON has no
    inf or nan)."""
    return float(x) if x is not None and math.isfinite(x) else None


@dataclass
class Item:
    """The verdict on one item: one printed line, one JSON object."""

    name: str
    passed: bool  #: True only for a pass (an inconclusive item has not passed)
    figures: str  #: what was measured, human-readable
    expected: str  #: what the contract asks
    values: dict = field(default_factory=dict)  #: the figures, machine-readable (SI)
    #: why the item could not be judged ('' when it was): the check fell behind or the
    #: link lost or held what it needed; then ``passed`` is False and the verdict
    #: 'inconclusive', never 'fail'
    inconclusive: str = ''

    @property
    def verdict(self) -> str:
        """'pass', 'fail' or 'inconclusive'."""
        if self.inconclusive:
            return 'inconclusive'
        return 'pass' if self.passed else 'fail'

    def undecided(self, why: str) -> Item:
        """This item as `inconclusive` for reason ``why`` (a failed verdict whose
        preconditions did not hold); a passing item stays as it is."""
        if self.passed or not why:
            return self
        return Item(self.name, False, self.figures, self.expected, self.values, why)

    def line(self) -> str:
        if self.inconclusive:
            return (
                f'INCONCLUSIVE  {self.name:<13s} {self.figures} -- not judged: '
                f'{self.inconclusive} (expected: {self.expected})'
            )
        return (
            f'{"PASS" if self.passed else "FAIL"}  {self.name:<13s} {self.figures} '
            f'(expected: {self.expected})'
        )
