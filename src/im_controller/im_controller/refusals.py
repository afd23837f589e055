"""Why the controller refuses a start, a fault reset or a parameter change, pure: each
function returns the refusal (prose, then ``contract``'s ``[code]``) or None.
"""

from __future__ import annotations

import math

import numpy as np

from . import contract as C
from .parameters import is_tunable
from .runner import ExperimentRunner


def start_refusal(runner: ExperimentRunner, has_state: bool, reset_hint: str) -> str | None:
    """Why ``~/start_experiment`` cannot start one now (None: it can). ``has_state``: a
    drive state came; ``reset_hint``: how a user clears a fault (command and service)."""
    if runner.running:
        return C.refusal(C.BUSY, f'refused: experiment {runner.experiment_id} is running')
    if runner.faulted and runner.fault_reason == 'tuner_lost':
        return C.refusal(
            C.TUNER_LOST,
            'refused: FAULT (tuner_lost): the tuner went silent and the drive was brought '
            f'to zero current; the drive is fine: clear it with {reset_hint}',
        )
    if runner.faulted:
        return C.refusal(
            C.SAFETY_FAULT,
            f'refused: safety fault ({runner.fault_reason}); check the drive, then clear it '
            f'with {reset_hint}',
        )
    if not has_state:
        return C.refusal(
            C.NO_DRIVE_STATE, 'refused: no drive state received yet (is the drive running?)'
        )
    if not runner.ready:
        return C.refusal(
            C.FINISHING_MOVE, 'refused: still finishing the stopped move; retry shortly'
        )
    return None


def reset_refusal(state: np.ndarray | None, silent_since_trip: float | None) -> str | None:
    """Why ``~/reset_fault`` cannot clear a fault now (None: it can). ``state``: the last
    drive state (None: none yet); ``silent_since_trip``: seconds since the state watchdog
    tripped with no drive state since (None: a state came, or it did not trip)."""
    if state is None:
        return C.refusal(C.NO_DRIVE_STATE, 'refused: no drive state yet')
    if not (math.isfinite(state[2]) and math.isfinite(state[3])):
        # holding a position needs a sane measurement: the drive is still broken
        return C.refusal(
            C.STATE_NOT_FINITE,
            f'refused: the last drive state is not finite (theta_meas='
            f'{state[2]!r}, omega_meas={state[3]!r}); check '
            'the drive',
        )
    if silent_since_trip is not None:
        # Holding needs a drive that answers: after the state watchdog, wait for one.
        return C.refusal(
            C.NO_DRIVE_STATE,
            f'refused: no drive state since the watchdog tripped '
            f'{silent_since_trip:.1f} s ago (is the '
            'drive running?)',
        )
    return None


def change_refusal(changes: list[tuple[str, object]], runner: ExperimentRunner) -> str | None:
    """Why a parameter change ((name, value) pairs: one parameter or an atomic set) cannot be
    applied now, before its values are validated (None: validate them): tunables change
    only between experiments, and every float must be finite."""
    tunable = any(is_tunable(name) for name, _ in changes)
    if tunable and runner.running:
        return C.refusal(
            C.BUSY,
            f'experiment {runner.experiment_id} is running: gains and '
            'experiment parameters change only between experiments (refused, '
            'not deferred; set them again after the result arrives)',
        )
    if tunable and not (runner.ready or runner.faulted):
        # After a supervisor stop the fallback gains finish the move: new gains now
        # would replace them mid-move (and at a wall-clock-dependent step).
        return C.refusal(
            C.FINISHING_MOVE,
            'still finishing the stopped move with the fallback gains: gains and '
            'experiment parameters change once it ends (refused; retry shortly)',
        )
    for name, value in changes:
        if isinstance(value, float) and not math.isfinite(value):
            return C.refusal(C.INVALID, f'{name} must be finite, got {value!r}')
    return None
