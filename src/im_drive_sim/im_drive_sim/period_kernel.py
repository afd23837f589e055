"""The simulator's real-time period, compiled: ``DriveSimNode.period`` and
``take_commands`` as numba functions a composed loop calls without the GIL
(``im_tuner.bench.compiled_loop``); run as Python, a period's glue costs more than the
model step and needs the GIL every period.

The node owns the logic: ``period_words``/``set_period_words`` move its held command,
latch and counters to and from ``D`` (float64, :data:`WORDS`) and ``DC`` (int64,
:data:`COUNTERS`, the node's counters of those names). The rules are deliberate copies of
the Python ones (:func:`latch_labels`, :func:`hold_labels`: ``CommandLatch``;
:func:`take_command`, :func:`run_period`: the node's), held to them bit for bit by the
composed bench's replay test. No watchdog here: composed with the controller a command
comes every period; the loop feeds the node's after each call.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from . import contract, kernels as K

#: the words of ``D``, in order
WORDS: tuple[str, ...] = (
    'isq_ref',  # the held command [A]
    'load',  # [N m]
    'applied',  # its answers_step (-1: none, untagged, a safe stop)
    'fresh',  # 1: it answers the latest state and came since the last step
    'held_answers',  # answers_step of the newest tagged command
    'pend_applied',  # command delay 2: the latched command's labels
    'pend_fresh',
    'safe_stopped',  # 1: zero current and no load from now on
    'command_delay',  # 1 or 2 [periods]
    'wall_clock',  # 1: the drive cannot pause (missed periods run held)
    'clock_decimation',  # /clock every n states
    'joint_state_decimation',  # joint_states every n states
    'ts_ns',  # the period [ns]
)
(
    D_ISQ,
    D_LOAD,
    D_APPLIED,
    D_FRESH,
    D_HELD,
    D_PEND_APPLIED,
    D_PEND_FRESH,
    D_STOPPED,
    D_DELAY,
    D_WALL_CLOCK,
    D_CLOCK_DEC,
    D_JOINT_DEC,
    D_TS_NS,
) = range(len(WORDS))
N_WORDS = len(WORDS)

#: the status counters a period does not touch: the pacer's (overruns, max_lateness_us),
#: the publishers' (backpressure), the watchdog's and lock-step's (republished)
_NOT_IN_A_PERIOD = frozenset(
    (
        'overruns',
        'max_lateness_us',
        'backpressure',
        'watchdog_trips',
        'watchdog_steps',
        'republished',
    )
)
#: the counters of ``DC`` (the node's ``Counters`` of the same names), in order
COUNTERS: tuple[str, ...] = tuple(n for n in contract.STATUS_COUNTERS if n not in _NOT_IN_A_PERIOD)
C_STEPS, C_COMMANDS, C_FRESH, C_HELD, C_LATE, C_STALE, C_MISSED = range(len(COUNTERS))

#: the messages a period made due (the bits of :func:`run_period`'s result)
MSG_STATE, MSG_CLOCK, MSG_JOINT = 1, 2, 4

F_APPLIED = contract.STATE_INDEX['applied_step']
#: the state's fields joint_states repeats
F_THETA, F_OMEGA = contract.STATE_INDEX['theta_meas'], contract.STATE_INDEX['omega_meas']
F_TORQUE = contract.STATE_INDEX['torque']
NS_PER_S = contract.NS_PER_S


def pack_words(
    held: Any,
    latch: Any,
    safe_stopped: bool,
    constants: dict[str, Any],
    counters: Any,
    words_of_d: tuple[str, ...] = WORDS,
) -> tuple[np.ndarray, np.ndarray]:
    """``D`` and ``DC`` of a drive's held command (``command_latch.HeldCommand``), its
    latch (``command_latch.CommandLatch``), the safe-stop latch, its ``constants`` (the
    other names of ``words_of_d``: :data:`WORDS`, or a layout that starts as its first
    nine, ``hardware_period.WORDS``) and its counters (:data:`COUNTERS` by name)."""
    pend_applied, pend_fresh = latch.pending
    words = {
        'isq_ref': held.isq_ref,
        'load': held.load,
        'applied': held.applied,
        'fresh': held.fresh,
        'held_answers': held.answers,
        'pend_applied': pend_applied,
        'pend_fresh': pend_fresh,
        'safe_stopped': safe_stopped,
        **constants,
    }
    D = np.array([float(words[n]) for n in words_of_d])
    DC = np.array([getattr(counters, n) for n in COUNTERS], np.int64)
    return D, DC


def unpack_words(D: np.ndarray, DC: np.ndarray, held: Any, latch: Any, counters: Any) -> bool:
    """Back from ``D`` and ``DC`` (:func:`pack_words`) into the held command, the latch and
    the counters; returns the safe-stop latch."""
    held.isq_ref = float(D[D_ISQ])
    held.load = float(D[D_LOAD])
    held.applied = int(D[D_APPLIED])
    held.fresh = bool(D[D_FRESH])
    held.answers = int(D[D_HELD])
    latch.pending = (int(D[D_PEND_APPLIED]), bool(D[D_PEND_FRESH]))
    for i, n in enumerate(COUNTERS):
        setattr(counters, n, int(DC[i]))
    return bool(D[D_STOPPED])


@njit(cache=True)
def latch_labels(D: np.ndarray, applied: float, fresh: float) -> tuple[float, float]:
    """``command_latch.CommandLatch.latch``, compiled (a deliberate copy: the 5 kHz loop
    runs it without the GIL): the labels of the command acting over the coming period
    (delay 2: the one latched a period earlier; this one waits)."""
    if D[D_DELAY] == 2.0:
        acting, was_fresh = D[D_PEND_APPLIED], D[D_PEND_FRESH]
        D[D_PEND_APPLIED] = applied
        D[D_PEND_FRESH] = fresh
        return acting, was_fresh
    return applied, fresh


@njit(cache=True)
def hold_labels(D: np.ndarray) -> float:
    """``command_latch.CommandLatch.hold``, compiled: a period a late loop missed on a
    power stage called by address (``hardware_period.hardware_missed``); the held command
    is fresh no more. Returns the applied_step of the command acting over it."""
    D[D_FRESH] = 0.0
    if D[D_DELAY] == 2.0:
        D[D_PEND_FRESH] = 0.0
        return D[D_PEND_APPLIED]
    return D[D_APPLIED]


@njit(cache=True)
def take_command(
    D: np.ndarray, DC: np.ndarray, k: int, answers: float, isq: float, load: float
) -> bool:
    """``DriveSimNode.take_commands`` for one command (answering state ``answers``; the
    drive's step index is ``k``): the newest becomes the held command; a duplicate or
    out-of-order one is counted ``stale_ignored``, one answering an older state ``late``.
    False (not counted): a non-finite command, which the drive refuses."""
    if not (math.isfinite(isq) and math.isfinite(load)):
        return False
    DC[C_COMMANDS] += 1
    if 0.0 <= answers <= D[D_HELD]:
        DC[C_STALE] += 1
        return True
    D[D_ISQ] = isq
    D[D_LOAD] = load
    D[D_APPLIED] = answers if answers >= 0.0 else -1.0
    if answers >= 0.0:
        D[D_HELD] = answers
    if 0.0 <= answers < k:
        DC[C_LATE] += 1
        D[D_FRESH] = 0.0
    else:
        D[D_FRESH] = 1.0
    return True


@njit(cache=True)
def run_missed(
    S: np.ndarray, P: np.ndarray, noise: np.ndarray, D: np.ndarray, DC: np.ndarray,
    state: np.ndarray, n: int,
) -> None:  # fmt: skip
    """``n`` periods a late loop skipped on a drive that cannot pause: the model runs
    them with the held command, unpublished (``DriveSimNode.period``'s ``missed``)."""
    acting = D[D_APPLIED]
    for _ in range(n):  # periods as any other, unpublished: the first one takes the command
        acting = latch_labels(D, D[D_APPLIED], D[D_FRESH])[0]
        D[D_FRESH] = 0.0
        K.step_into_kernel(S, P, noise, D[D_ISQ], D[D_LOAD], state)
    if n > 0:
        state[F_APPLIED] = acting
        DC[C_STEPS] += n
        DC[C_HELD] += n
        DC[C_MISSED] += n


@njit(cache=True, nogil=True)
def put_joint(joint: Any, t_ns: Any, pos: float, vel: float, eff: float) -> None:
    """A joint_states message's values into its views ``joint`` (sec, nanosec, position,
    velocity, effort: ``period_views``' one-element arrays), stamped ``t_ns`` [ns]."""
    sec_, nsec_, pos_, vel_, eff_ = joint
    sec = t_ns // NS_PER_S
    sec_[0] = sec
    nsec_[0] = t_ns - sec * NS_PER_S
    pos_[0] = pos
    vel_[0] = vel
    eff_[0] = eff


@njit(cache=True)
def run_period(
    S: np.ndarray,
    P: np.ndarray,
    noise: np.ndarray,
    D: np.ndarray,
    DC: np.ndarray,
    state: np.ndarray,
    clock: Any,
    joint: Any,
) -> int:
    """One period at its start (``DriveSimNode.period`` after the missed periods): the
    safe-stop latch, the command latch, one model step with the held command into
    ``state`` (state k+1, ``applied_step`` its command's step), the counters, and the
    /clock (``clock``: sec, nanosec) and joint_states (``joint``, :func:`put_joint`)
    messages patched when due. Returns the messages due
    (:data:`MSG_STATE` | :data:`MSG_CLOCK` | :data:`MSG_JOINT`)."""
    if D[D_STOPPED] != 0.0:  # the model runs on with zero current and no load
        D[D_ISQ] = 0.0
        D[D_LOAD] = 0.0
        D[D_APPLIED] = -1.0
        D[D_FRESH] = 0.0
    acting, fresh = latch_labels(D, D[D_APPLIED], D[D_FRESH])
    if fresh != 0.0:
        DC[C_FRESH] += 1
    else:
        DC[C_HELD] += 1
    K.step_into_kernel(S, P, noise, D[D_ISQ], D[D_LOAD], state)
    state[F_APPLIED] = acting
    DC[C_STEPS] += 1
    D[D_FRESH] = 0.0  # it answered the state before this step
    due = MSG_STATE
    k = np.int64(state[0])
    t_ns = k * np.int64(D[D_TS_NS])
    if k % np.int64(D[D_CLOCK_DEC]) == 0:
        sec = t_ns // NS_PER_S
        clock[0][0] = sec
        clock[1][0] = t_ns - sec * NS_PER_S
        due |= MSG_CLOCK
    if k % np.int64(D[D_JOINT_DEC]) == 0:
        put_joint(joint, t_ns, state[F_THETA], state[F_OMEGA], state[F_TORQUE])
        due |= MSG_JOINT
    return due


@njit(cache=True)
def safe_stop(S: np.ndarray, D: np.ndarray) -> None:
    """``DriveSimNode.safe_stop``: zero current and no load from the next period on,
    latched; no command latched for it runs (delay 2)."""
    D[D_STOPPED] = 1.0
    D[D_ISQ] = 0.0
    D[D_LOAD] = 0.0
    D[D_APPLIED] = -1.0
    D[D_PEND_APPLIED] = -1.0
    D[D_PEND_FRESH] = 0.0
    K.clear_command(S)  # nothing latched, no load step waiting in the load machine
