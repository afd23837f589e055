"""The example drive's period around a power stage called by address (``hardware_abi``: a
C library, a compiled class), compiled: ``ExampleDrive.period`` as numba functions the
composed loop calls without the GIL (``im_tuner.bench.compiled_loop``).

As ``period_kernel`` for the simulator: the node owns the logic (``period_words``,
``set_period_words``), ``test/test_hardware_loop.py`` holds the two to the same bits,
and the command's take and the latch are ``period_kernel``'s. ``D`` (float64,
:data:`WORDS`): ``period_kernel``'s first words, then the example drive's; ``DC``:
``period_kernel.COUNTERS``; ``E``: the stage's entry (``hardware_abi.entry_words``).

A negative return of the stage is a fault: zero current is written (its return not
looked at), the safe stop latched, :data:`FAULT` returned, and ``F`` holds the code,
the call and the step.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

from . import period_kernel as PK
from .hardware_abi import call_elapse, call_read, call_write

#: the words of ``D``: period_kernel's first nine (take_command and latch_labels use
#: them at the same places), then the example drive's
WORDS: tuple[str, ...] = (
    *PK.WORDS[: PK.D_DELAY + 1],
    'joint_state_decimation',  # joint_states every n states
    'ts_ns',  # the period [ns]
    'isq_max',  # the clamp [A]
    'k',  # the step index of the latest state
    'acting',  # applied_step of the command that acted over the period that just ended
)
D_JOINT_DEC, D_TS_NS, D_ISQ_MAX, D_K, D_ACTING = range(PK.D_DELAY + 1, len(WORDS))
N_WORDS = len(WORDS)
assert WORDS[PK.D_DELAY] == 'command_delay' and WORDS[PK.D_STOPPED] == 'safe_stopped'

#: ``F``: the fault (int64): the code, which call (F_WRITE, F_READ, F_ELAPSE), the step
F_CODE, F_CALL, F_STEP = range(3)
CALL_NAMES = ('', 'write', 'read', 'elapse')
F_WRITE, F_READ, F_ELAPSE = 1, 2, 3
FAULT = -1  #: :func:`hardware_period`'s result on a fault

MSG_STATE, MSG_JOINT = PK.MSG_STATE, PK.MSG_JOINT
F_APPLIED = PK.F_APPLIED


@njit(cache=True, nogil=True)
def _fault(E: np.ndarray, D: np.ndarray, F: np.ndarray, code: int, call: int) -> int:
    """A negative return: zero current now (what that write returns is not looked at),
    the safe stop latched, the fault kept in ``F``."""
    F[F_CODE] = code
    F[F_CALL] = call
    F[F_STEP] = np.int64(D[D_K])
    safe_stop(E, D)
    return FAULT


@njit(cache=True, nogil=True)
def hardware_missed(E: np.ndarray, D: np.ndarray, DC: np.ndarray, F: np.ndarray, n: int) -> int:
    """``n`` periods a late loop skipped (``ExampleDrive.period``'s ``missed``): the
    power stage held the last command over them (a stand-in plant is told: ``elapse``);
    counted held and missed, the step index advanced. 0, or :data:`FAULT`."""
    if n <= 0:
        return 0
    rc = call_elapse(E, n)
    if rc < 0:
        return _fault(E, D, F, rc, F_ELAPSE)
    D[D_ACTING] = PK.hold_labels(D)  # the stage held what it was last written
    D[D_K] += n
    DC[PK.C_STEPS] += n
    DC[PK.C_HELD] += n
    DC[PK.C_MISSED] += n
    return 0


@njit(cache=True, nogil=True)
def hardware_period(
    E: np.ndarray,
    D: np.ndarray,
    DC: np.ndarray,
    F: np.ndarray,
    m: np.ndarray,
    state: np.ndarray,
    joint: Any,
) -> int:
    """One period at its start (``ExampleDrive.period`` after the missed periods and the
    commands): the safe-stop latch, the command latch, the clamped write, the read into
    ``m``, state k+1 into ``state`` and joint_states (``joint``:
    ``period_kernel.put_joint``) when due. Returns the messages due
    (``MSG_STATE`` | ``MSG_JOINT``), or :data:`FAULT`."""
    stopped = D[PK.D_STOPPED] != 0.0
    if stopped:  # zero was applied, not a command
        D[PK.D_APPLIED] = -1.0
        D[PK.D_FRESH] = 0.0
    acting, fresh = PK.latch_labels(D, D[PK.D_APPLIED], D[PK.D_FRESH])
    D[D_ACTING] = acting
    if fresh != 0.0:
        DC[PK.C_FRESH] += 1
    else:
        DC[PK.C_HELD] += 1
    D[PK.D_FRESH] = 0.0
    if stopped:
        isq, load = 0.0, 0.0
    else:
        lim = D[D_ISQ_MAX]
        isq = max(-lim, min(lim, D[PK.D_ISQ]))
        load = D[PK.D_LOAD]
    rc = call_write(E, isq, load)
    if rc < 0:
        return _fault(E, D, F, rc, F_WRITE)
    k = D[D_K] + 1.0
    D[D_K] = k
    rc = call_read(E, m)
    if rc < 0:
        return _fault(E, D, F, rc, F_READ)
    state[0] = k
    ts_ns = np.int64(D[D_TS_NS])
    ki = np.int64(k)
    state[1] = float(ki * ts_ns)
    for i in range(8):
        state[2 + i] = m[i]
    state[10] = m[0]
    state[11] = m[1]
    state[F_APPLIED] = acting
    state[13] = D[PK.D_DELAY]
    DC[PK.C_STEPS] += 1
    due = MSG_STATE
    if ki % np.int64(D[D_JOINT_DEC]) == 0:
        PK.put_joint(joint, ki * ts_ns, m[0], m[1], m[2])
        due |= MSG_JOINT
    return due


@njit(cache=True, nogil=True)
def safe_stop(E: np.ndarray, D: np.ndarray) -> None:
    """``ExampleDrive.safe_stop``: zero current and no load now (a write of zero, what it
    returns not looked at) and in every later period, latched."""
    D[PK.D_STOPPED] = 1.0
    D[PK.D_ISQ] = 0.0
    D[PK.D_LOAD] = 0.0
    D[PK.D_APPLIED] = -1.0
    call_write(E, 0.0, 0.0)
