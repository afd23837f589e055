"""The per-step experiment kernel (numba): cascade, trajectory, load, online loss,
supervisor and safety limits for one drive state. What the node calls once per state and
what the offline bench fuses with the drive kernels."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from . import layout as L
from .control import O_E_THETA, O_ISQ, O_OMEGA_REF, O_SAT, control_step
from .trajectory import traj_pos

#: One of the kernels' arrays (float64, 1-D, C-contiguous; ``layout`` names its words; the
#: answer words ``W`` are int64): the short name keeps the long kernel signatures on a line.
Vec = np.ndarray


@njit(cache=True)
def finish_experiment(R: Vec, Q: Vec, status: float, reason: float, time_ns: float) -> None:
    """End the experiment in ``R``: its result (``status``, ``reason`` code), the steps it
    ran, its end time [ns] (one period after ``time_ns``, the last state's), the trip step."""
    R[L.R_RESULT] = status
    R[L.R_REASON] = reason
    R[L.R_STEPS] = R[L.R_N]
    R[L.R_END_NS] = time_ns + Q[L.Q_TS_NS]
    R[L.R_TRIP_STEP] = R[L.R_N] - 1.0 if status == L.STATUS_ABORTED else -1.0


@njit(cache=True)
def ripple_step(R: Vec, Q: Vec, n: float, isq: float) -> None:
    """The standstill ripple's sums: isq* [A] of local step ``n`` into its window's count,
    sum, sum of squares, min and max (``R_RIP``), if ``n`` lies in one (``Q_RIP*``)."""
    if Q[L.Q_RIP1_A] <= n < Q[L.Q_RIP1_B]:
        j = L.R_RIP
    elif Q[L.Q_RIP2_A] <= n < Q[L.Q_RIP2_B]:
        j = L.R_RIP + 5
    else:
        return
    if R[j] == 0.0 or isq < R[j + 3]:
        R[j + 3] = isq
    if R[j] == 0.0 or isq > R[j + 4]:
        R[j + 4] = isq
    R[j] += 1.0
    R[j + 1] += isq
    R[j + 2] += isq * isq


@njit(cache=True)
def motion_step(R: Vec, Q: Vec, n: float, th: float, w: float, state: Vec) -> None:
    """The motion sums (layout ``R_ID_*``) with local step ``n``'s state: blocks of K =
    ``Q_ID_K`` periods, each pair one row J z0 = Kt z1 - B z2 - Tc z3 - z4 (z0 the change
    of the encoder's mean speed, z1..z4 triangle-weighted integrals), summed as z z^T
    (docs/controller.md, "The motion sums")."""
    K = Q[L.Q_ID_K]
    blk = math.floor(n / K)
    m = n - K * blk  # this step's place in its block
    if blk >= R[L.R_ID_NB]:  # the first state of a block this experiment sees
        if m == 0.0 and blk == R[L.R_ID_NB]:
            if R[L.R_ID_CHAIN] >= 2.0:
                ts = Q[L.Q_TS]
                z0 = ((th - R[L.R_ID_THB]) - (R[L.R_ID_THB] - R[L.R_ID_THA])) / (K * ts)
                z = (
                    z0,
                    ts * (R[L.R_ID_RISE] + R[L.R_ID_S0] - R[L.R_ID_S1] / K),
                    ts * (R[L.R_ID_RISE + 1] + R[L.R_ID_S0 + 1] - R[L.R_ID_S1 + 1] / K),
                    ts * (R[L.R_ID_RISE + 2] + R[L.R_ID_S0 + 2] - R[L.R_ID_S1 + 2] / K),
                    ts * (R[L.R_ID_RISE + 3] + R[L.R_ID_S0 + 3] - R[L.R_ID_S1 + 3] / K),
                )
                j = L.R_ID_M
                for a in range(5):
                    for b in range(a, 5):
                        R[j] += z[a] * z[b]
                        j += 1
                R[L.R_ID_ROWS] += 1.0
            for q in range(4):
                R[L.R_ID_RISE + q] = R[L.R_ID_S1 + q] / K
            R[L.R_ID_THA] = R[L.R_ID_THB]
            R[L.R_ID_THB] = th
            R[L.R_ID_CHAIN] += 1.0
        else:  # a block's first state went by unseen: its sums would be short
            R[L.R_ID_CHAIN] = 0.0
        for q in range(4):
            R[L.R_ID_S0 + q] = 0.0
            R[L.R_ID_S1 + q] = 0.0
        R[L.R_ID_NB] = blk + 1.0
    if R[L.R_ID_CHAIN] == 0.0:
        return
    sgn = 0.0
    if w > Q[L.Q_ID_WDEAD]:
        sgn = 1.0
    elif w < -Q[L.Q_ID_WDEAD]:
        sgn = -1.0
    x0 = state[L.S_ISQ]
    x3 = state[L.S_LOAD]
    mh = m + 0.5
    R[L.R_ID_S0] += x0
    R[L.R_ID_S0 + 1] += w
    R[L.R_ID_S0 + 2] += sgn
    R[L.R_ID_S0 + 3] += x3
    R[L.R_ID_S1] += mh * x0
    R[L.R_ID_S1 + 1] += mh * w
    R[L.R_ID_S1 + 2] += mh * sgn
    R[L.R_ID_S1 + 3] += mh * x3


@njit(cache=True)
def experiment_step(
    R: Vec, Q: Vec, X: Vec, C: Vec, CF: Vec, state: Vec, cout: Vec, eout: Vec
) -> int:
    """Process drive state k (``STATE_FIELDS``) and return the status; the command is
    ``eout[E_ISQ]`` [A], ``eout[E_LOAD]`` [N m]; a repeated step_index gets the previous
    answer.  R, Q, X, C, CF (the fallback gains' C), cout, eout: ``layout``'s arrays.
    No allocation."""
    k = state[0]
    if k == R[L.R_LAST_STEP]:
        eout[L.E_ISQ] = R[L.R_LAST_ISQ]
        eout[L.E_LOAD] = R[L.R_LAST_LOAD]
        eout[L.E_STATUS] = R[L.R_LAST_STATUS]
        return int(R[L.R_LAST_STATUS])
    th = state[2]
    w = state[3]
    running = R[L.R_MODE] == L.MODE_RUN
    settling = R[L.R_MODE] == L.MODE_SETTLE
    if settling:
        # The experiment's standstill settle: Q_SETTLE_N periods on the drive's timeline
        # from the first state after the start, holding with the fallback gains; its
        # step 0 is the first state at or after that (so the time between experiments,
        # and what the previous one left, does not reach the loss).
        if R[L.R_START_STEP] < 0.0:
            R[L.R_START_STEP] = k + Q[L.Q_SETTLE_N]
        if k >= R[L.R_START_STEP]:
            R[L.R_MODE] = L.MODE_RUN
            R[L.R_N] = 0.0
            running = True
            settling = False
    ended_unseen = False
    # The command the drive applied over the period that ended at this state (-1: none),
    # and its declared command delay d: its answer to state k - d drove this period fresh.
    applied = state[L.S_APPLIED]
    delay = state[L.S_CMD_DELAY]
    if running:
        # The experiment runs on the drive's timeline: local step n = k - (first step),
        # so a state the controller never answered still counts as a period. Each of
        # its periods (the one ending at each of its states, which the loss integrates)
        # was driven by a fresh answer (to state k - 1), a late one (a new command
        # answering an older state) or a held one (no new command, or a state the
        # controller never saw).
        if R[L.R_N] == 0.0:
            R[L.R_START_STEP] = k
            R[L.R_START_NS] = state[1]
            R[L.R_FRESH] = 0.0
            R[L.R_LATE] = 0.0
            R[L.R_HELD] = 0.0
        last = R[L.R_START_STEP] + Q[L.Q_N] - 1.0  # the experiment's last state
        if k > last:
            # Its last state(s) went by unseen: it ended there, exactly N periods after
            # its start (the unseen periods count as held); this state is the hold's.
            R[L.R_HELD] += last - R[L.R_SEEN]
            R[L.R_N] = Q[L.Q_N]
            t_last = R[L.R_START_NS] + (Q[L.Q_N] - 1.0) * Q[L.Q_TS_NS]
            finish_experiment(R, Q, L.STATUS_DONE, L.REASON_NONE, t_last)
            R[L.R_HOLD_REF] = R[L.R_TARGET]
            R[L.R_MODE] = L.MODE_HOLD
            running = False
            ended_unseen = True
        else:
            if R[L.R_N] != 0.0:
                R[L.R_HELD] += k - R[L.R_SEEN] - 1.0
            if applied == k - delay:
                R[L.R_FRESH] += 1.0
            elif applied > R[L.R_APPLIED] and R[L.R_SEEN] == k - 1.0:
                # a command newer than the one the previous state showed (after an
                # unseen state the two cannot be told apart: held)
                R[L.R_LATE] += 1.0
            else:
                R[L.R_HELD] += 1.0
    R[L.R_SEEN] = k
    R[L.R_APPLIED] = applied
    status = L.STATUS_HOLD
    reason = L.REASON_NONE
    isq = 0.0
    load = 0.0
    n = -1.0
    f1 = 0.0
    f2 = 0.0
    f3 = 0.0
    counted = 0.0
    isqf = 0.0
    ref = 0.0
    if R[L.R_MODE] == L.MODE_FAULT:
        status = L.STATUS_FAULT
        reason = R[L.R_FAULT_REASON]
        cout[O_ISQ] = 0.0
        cout[O_SAT] = 0.0
    else:
        safety = L.REASON_NONE
        if not (math.isfinite(th) and math.isfinite(w)):
            safety = L.REASON_NONFINITE
        else:
            if running:
                n = k - R[L.R_START_STEP]
                ref = R[L.R_THETA0] + R[L.R_DIR] * traj_pos(n * Q[L.Q_TS], Q)
                if n >= Q[L.Q_LOAD_N]:
                    load = Q[L.Q_LOAD] if Q[L.Q_LOAD_FIXED] != 0.0 else R[L.R_DIR] * Q[L.Q_LOAD]
            elif settling:
                n = k - R[L.R_START_STEP]  # < 0: the settle's steps
                ref = R[L.R_HOLD_REF]
            elif R[L.R_MODE] == L.MODE_RETURN:
                # after a supervisor stop: the fallback gains finish the move along the
                # unchanged trajectory (no reference jump), then hold the target
                nn = k - R[L.R_START_STEP]
                ref = R[L.R_THETA0] + R[L.R_DIR] * traj_pos(nn * Q[L.Q_TS], Q)
                R[L.R_N] = nn + 1.0
                if nn * Q[L.Q_TS] >= Q[L.Q_TEND]:
                    R[L.R_MODE] = L.MODE_HOLD
                    R[L.R_HOLD_REF] = R[L.R_TARGET]
            else:
                ref = R[L.R_HOLD_REF]
            isq = control_step(X, CF if settling else C, ref, th, w, cout)
            if abs(cout[O_E_THETA]) > Q[L.Q_MAX_ERR]:
                safety = L.REASON_POSITION
            elif abs(w) > Q[L.Q_MAX_SPEED]:
                safety = L.REASON_SPEED
        if safety != L.REASON_NONE:
            # Hard limit: torque off (drive-level safe state) until an explicit reset.
            R[L.R_MODE] = L.MODE_FAULT
            R[L.R_FAULT_REASON] = safety
            isq = 0.0
            load = 0.0
            cout[O_ISQ] = 0.0
            cout[O_SAT] = 0.0
            reason = safety
            if running:
                if n < 0.0:
                    n = k - R[L.R_START_STEP]
                R[L.R_N] = n + 1.0
                finish_experiment(R, Q, L.STATUS_ABORTED, safety, state[1])
                status = L.STATUS_ABORTED
            elif settling:
                # a fault in the settle ends the experiment before its step 0: aborted,
                # no step measured
                R[L.R_START_STEP] = k
                R[L.R_START_NS] = state[1]
                R[L.R_N] = 0.0
                finish_experiment(R, Q, L.STATUS_ABORTED, safety, state[1])
                R[L.R_TRIP_STEP] = -1.0
                status = L.STATUS_ABORTED
            else:
                status = L.STATUS_FAULT
        elif running:
            isq_max = Q[L.Q_ISQ_MAX]
            if n == 0.0:
                R[L.R_ISQF] = isq
            isqf = R[L.R_ISQF]
            f1 = abs(ref - th)
            f2 = abs(cout[O_OMEGA_REF] - w)
            f3 = abs(isqf - isq)
            if abs(isq) / isq_max < Q[L.Q_SAT_RATIO]:
                counted = 1.0
                R[L.R_S1] += f1
                R[L.R_S2] += f2
                R[L.R_S3] += f3
            a = Q[L.Q_ISQF_A]
            R[L.R_ISQF] = a * isqf + (1.0 - a) * isq
            ripple_step(R, Q, n, isq)
            motion_step(R, Q, n, th, w, state)
            ts = Q[L.Q_TS]
            R[L.R_TERM1] = Q[L.Q_A1] * ts * R[L.R_S1]
            R[L.R_TERM2] = Q[L.Q_A2] * ts * R[L.R_S2]
            R[L.R_TERM3] = Q[L.Q_A3] * ts * R[L.R_S3]
            trip = L.REASON_NONE
            if R[L.R_TERM1] > Q[L.Q_THR1]:
                trip = L.REASON_TERM1
            elif R[L.R_TERM2] > Q[L.Q_THR2]:
                trip = L.REASON_TERM2
            elif R[L.R_TERM3] > Q[L.Q_THR3]:
                trip = L.REASON_TERM3
            R[L.R_N] = n + 1.0
            if trip != L.REASON_NONE:
                finish_experiment(R, Q, L.STATUS_ABORTED, trip, state[1])
                # Stop at once: this step's command already comes from the position hold
                # at the measured position with the fallback gains (bumpless: references
                # = theta_meas, integrator 0); the load is removed.
                for j in range(C.shape[0]):
                    C[j] = CF[j]
                R[L.R_MODE] = L.MODE_RETURN
                isq = control_step(X, C, ref, th, w, cout)
                load = 0.0
                status = L.STATUS_ABORTED
                reason = trip
            elif R[L.R_N] >= Q[L.Q_N]:
                finish_experiment(R, Q, L.STATUS_DONE, L.REASON_NONE, state[1])
                R[L.R_HOLD_REF] = R[L.R_TARGET]
                R[L.R_MODE] = L.MODE_HOLD
                status = L.STATUS_DONE
            else:
                status = L.STATUS_RUNNING
        elif settling:
            status = L.STATUS_RUNNING
    if ended_unseen and status == L.STATUS_HOLD:
        status = L.STATUS_DONE  # the result of the experiment that ended unseen is ready
    eout[L.E_ISQ] = isq
    eout[L.E_LOAD] = load
    eout[L.E_STATUS] = status
    eout[L.E_REASON] = reason
    eout[L.E_N] = n
    eout[L.E_F1] = f1
    eout[L.E_F2] = f2
    eout[L.E_F3] = f3
    eout[L.E_ISQF] = isqf
    eout[L.E_COUNTED] = counted
    eout[L.E_T1] = R[L.R_TERM1]
    eout[L.E_T2] = R[L.R_TERM2]
    eout[L.E_T3] = R[L.R_TERM3]
    R[L.R_LAST_STEP] = k
    R[L.R_LAST_STATUS] = status
    R[L.R_LAST_ISQ] = isq
    R[L.R_LAST_LOAD] = load
    return status


#: The words of :func:`answer_state`'s ``W`` (int64): the newest state answered, the
#: states answered, the internals decimation, and whether this answer made internals due.
W_ANSWERED, W_N_ANSWERED, W_DECIMATION, W_INTERNALS_DUE = range(4)
N_ANSWER_WORDS = 4


@njit(cache=True)
def answer_state(
    R: Vec, Q: Vec, X: Vec, C: Vec, CF: Vec, state: Vec, cout: Vec, eout: Vec,
    cmd: Vec, internals: Vec, W: Vec,
) -> int:  # fmt: skip
    """The controller's answer to one state (``ControllerNode.answer``; a composed real-time
    loop calls it without the GIL): the command (k, isq* [A], load [N m]) into ``cmd``, and every
    ``W[W_DECIMATION]``-th answer the internals [k, cout, eout] into ``internals``
    (``W[W_INTERNALS_DUE]`` = 1).  Returns the experiment status."""
    k = state[0]
    st = experiment_step(R, Q, X, C, CF, state, cout, eout)
    cmd[0] = k
    cmd[1] = eout[L.E_ISQ]
    cmd[2] = eout[L.E_LOAD]
    if k > W[W_ANSWERED]:
        W[W_ANSWERED] = np.int64(k)
    W[W_N_ANSWERED] += 1
    W[W_INTERNALS_DUE] = 0
    if W[W_N_ANSWERED] % W[W_DECIMATION] == 0:
        nc = cout.shape[0]
        internals[0] = k
        for j in range(nc):
            internals[1 + j] = cout[j]
        for j in range(eout.shape[0]):
            internals[1 + nc + j] = eout[j]
        W[W_INTERNALS_DUE] = 1
    return st
