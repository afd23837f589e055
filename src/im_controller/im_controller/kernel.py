"""The per-step experiment kernel (numba): cascade, trajectory, load, online loss,
supervisor and safety limits for one drive state. What the node calls once per state and
what the offline bench fuses with the drive kernels."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .control import O_E_THETA, O_ISQ, O_OMEGA_REF, O_SAT, control_step
from .layout import (
    E_COUNTED,
    E_F1,
    E_F2,
    E_F3,
    E_ISQ,
    E_ISQF,
    E_LOAD,
    E_N,
    E_REASON,
    E_STATUS,
    E_T1,
    E_T2,
    E_T3,
    MODE_FAULT,
    MODE_HOLD,
    MODE_RETURN,
    MODE_RUN,
    MODE_SETTLE,
    Q_A1,
    Q_A2,
    Q_A3,
    Q_ID_K,
    Q_ID_WDEAD,
    Q_ISQ_MAX,
    Q_ISQF_A,
    Q_LOAD,
    Q_LOAD_FIXED,
    Q_LOAD_N,
    Q_MAX_ERR,
    Q_MAX_SPEED,
    Q_N,
    Q_RIP1_A,
    Q_RIP1_B,
    Q_RIP2_A,
    Q_RIP2_B,
    Q_SAT_RATIO,
    Q_SETTLE_N,
    Q_TEND,
    Q_THR1,
    Q_THR2,
    Q_THR3,
    Q_TS,
    Q_TS_NS,
    R_APPLIED,
    R_DIR,
    R_END_NS,
    R_FAULT_REASON,
    R_FRESH,
    R_HELD,
    R_HOLD_REF,
    R_ID_CHAIN,
    R_ID_M,
    R_ID_NB,
    R_ID_RISE,
    R_ID_ROWS,
    R_ID_S0,
    R_ID_S1,
    R_ID_THA,
    R_ID_THB,
    R_ISQF,
    R_LAST_ISQ,
    R_LAST_LOAD,
    R_LAST_STATUS,
    R_LAST_STEP,
    R_LATE,
    R_MODE,
    R_N,
    R_REASON,
    R_RESULT,
    R_RIP,
    R_S1,
    R_S2,
    R_S3,
    R_SEEN,
    R_START_NS,
    R_START_STEP,
    R_STEPS,
    R_TARGET,
    R_TERM1,
    R_TERM2,
    R_TERM3,
    R_THETA0,
    R_TRIP_STEP,
    REASON_NONE,
    REASON_NONFINITE,
    REASON_POSITION,
    REASON_SPEED,
    REASON_TERM1,
    REASON_TERM2,
    REASON_TERM3,
    S_APPLIED,
    S_CMD_DELAY,
    S_ISQ,
    S_LOAD,
    STATUS_ABORTED,
    STATUS_DONE,
    STATUS_FAULT,
    STATUS_HOLD,
    STATUS_RUNNING,
)
from .trajectory import traj_pos

#: One of the kernels' arrays (float64, 1-D, C-contiguous; ``layout`` names its words; the
#: answer words ``W`` are int64): the short name keeps the long kernel signatures on a line.
Vec = np.ndarray


# ---------------------------------------------------------------------- the kernel
@njit(cache=True)
def finish_experiment(R: Vec, Q: Vec, status: float, reason: float, time_ns: float) -> None:
    """End the experiment in ``R``: its result (``status``, ``reason`` code), the steps it
    ran, its end time [ns] (one period after ``time_ns``, the last state's), the trip step."""
    R[R_RESULT] = status
    R[R_REASON] = reason
    R[R_STEPS] = R[R_N]
    R[R_END_NS] = time_ns + Q[Q_TS_NS]
    R[R_TRIP_STEP] = R[R_N] - 1.0 if status == STATUS_ABORTED else -1.0


@njit(cache=True)
def ripple_step(R: Vec, Q: Vec, n: float, isq: float) -> None:
    """The standstill ripple's sums: isq* [A] of local step ``n`` into its window's count,
    sum, sum of squares, min and max (``R_RIP``), if ``n`` lies in one (``Q_RIP*``)."""
    if Q[Q_RIP1_A] <= n < Q[Q_RIP1_B]:
        j = R_RIP
    elif Q[Q_RIP2_A] <= n < Q[Q_RIP2_B]:
        j = R_RIP + 5
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
    """The motion sums (layout ``R_ID_*``) with local step ``n``'s state.

    Blocks b of K = ``Q_ID_K`` periods; the mean speed of block b is
    wbar_b = (theta(b+1) - theta(b)) / (K Ts) from the encoder (no filter lag).  Their
    change is exactly the acceleration under a triangle: wbar_b - wbar_{b-1} =
    int alpha(t) h(t) dt, h rising 0 -> 1 over block b - 1 and falling 1 -> 0 over block b,
    so with J alpha = Kt isq - B omega - Tc sign(omega) - T_load each pair of blocks
    gives one row J z0 = Kt z1 - B z2 - Tc z3 - z4, z1..z4 the h-weighted integrals of
    isq, omega_meas, sign(omega_meas) (0 within the dead band ``Q_ID_WDEAD``) and
    load_torque.  The rows are summed as z z^T (least squares needs no more)."""
    K = Q[Q_ID_K]
    blk = math.floor(n / K)
    m = n - K * blk  # this step's place in its block
    if blk >= R[R_ID_NB]:  # the first state of a block this experiment sees
        if m == 0.0 and blk == R[R_ID_NB]:
            if R[R_ID_CHAIN] >= 2.0:
                ts = Q[Q_TS]
                z0 = ((th - R[R_ID_THB]) - (R[R_ID_THB] - R[R_ID_THA])) / (K * ts)
                z = (
                    z0,
                    ts * (R[R_ID_RISE] + R[R_ID_S0] - R[R_ID_S1] / K),
                    ts * (R[R_ID_RISE + 1] + R[R_ID_S0 + 1] - R[R_ID_S1 + 1] / K),
                    ts * (R[R_ID_RISE + 2] + R[R_ID_S0 + 2] - R[R_ID_S1 + 2] / K),
                    ts * (R[R_ID_RISE + 3] + R[R_ID_S0 + 3] - R[R_ID_S1 + 3] / K),
                )
                j = R_ID_M
                for a in range(5):
                    for b in range(a, 5):
                        R[j] += z[a] * z[b]
                        j += 1
                R[R_ID_ROWS] += 1.0
            for q in range(4):
                R[R_ID_RISE + q] = R[R_ID_S1 + q] / K
            R[R_ID_THA] = R[R_ID_THB]
            R[R_ID_THB] = th
            R[R_ID_CHAIN] += 1.0
        else:  # a block's first state went by unseen: its sums would be short
            R[R_ID_CHAIN] = 0.0
        for q in range(4):
            R[R_ID_S0 + q] = 0.0
            R[R_ID_S1 + q] = 0.0
        R[R_ID_NB] = blk + 1.0
    if R[R_ID_CHAIN] == 0.0:
        return
    sgn = 0.0
    if w > Q[Q_ID_WDEAD]:
        sgn = 1.0
    elif w < -Q[Q_ID_WDEAD]:
        sgn = -1.0
    x0 = state[S_ISQ]
    x3 = state[S_LOAD]
    mh = m + 0.5
    R[R_ID_S0] += x0
    R[R_ID_S0 + 1] += w
    R[R_ID_S0 + 2] += sgn
    R[R_ID_S0 + 3] += x3
    R[R_ID_S1] += mh * x0
    R[R_ID_S1 + 1] += mh * w
    R[R_ID_S1 + 2] += mh * sgn
    R[R_ID_S1 + 3] += mh * x3


@njit(cache=True)
def experiment_step(
    R: Vec, Q: Vec, X: Vec, C: Vec, CF: Vec, state: Vec, cout: Vec, eout: Vec
) -> int:
    """Process drive state k (``state``: step_index, time_ns, theta_meas, omega_meas, ...)
    and return the status; the command is ``eout[E_ISQ]`` [A], ``eout[E_LOAD]`` [N m].

    A repeated step_index returns the previous answer unchanged (lock-step re-sends).
    R: runner state, Q: experiment parameters, X/C: controller state/parameters,
    CF: fallback controller parameters (copied into C after a supervisor stop),
    cout: controller internals (``CONTROL_FIELDS``), eout: ``EXP_FIELDS``.  No allocation.
    """
    k = state[0]
    if k == R[R_LAST_STEP]:
        eout[E_ISQ] = R[R_LAST_ISQ]
        eout[E_LOAD] = R[R_LAST_LOAD]
        eout[E_STATUS] = R[R_LAST_STATUS]
        return int(R[R_LAST_STATUS])
    th = state[2]
    w = state[3]
    running = R[R_MODE] == MODE_RUN
    settling = R[R_MODE] == MODE_SETTLE
    if settling:
        # The experiment's standstill settle: Q_SETTLE_N periods on the drive's timeline
        # from the first state after the start, holding with the fallback gains; its
        # step 0 is the first state at or after that (so the time between experiments,
        # and what the previous one left, does not reach the loss).
        if R[R_START_STEP] < 0.0:
            R[R_START_STEP] = k + Q[Q_SETTLE_N]
        if k >= R[R_START_STEP]:
            R[R_MODE] = MODE_RUN
            R[R_N] = 0.0
            running = True
            settling = False
    ended_unseen = False
    # The command the drive applied over the period that ended at this state (-1: none),
    # and its declared command delay d: its answer to state k - d drove this period fresh.
    applied = state[S_APPLIED]
    delay = state[S_CMD_DELAY]
    if running:
        # The experiment runs on the drive's timeline: local step n = k - (first step),
        # so a state the controller never answered still counts as a period. Each of
        # its periods (the one ending at each of its states, which the loss integrates)
        # was driven by a fresh answer (to state k - 1), a late one (a new command
        # answering an older state) or a held one (no new command, or a state the
        # controller never saw).
        if R[R_N] == 0.0:
            R[R_START_STEP] = k
            R[R_START_NS] = state[1]
            R[R_FRESH] = 0.0
            R[R_LATE] = 0.0
            R[R_HELD] = 0.0
        last = R[R_START_STEP] + Q[Q_N] - 1.0  # the experiment's last state
        if k > last:
            # Its last state(s) went by unseen: it ended there, exactly N periods after
            # its start (the unseen periods count as held); this state is the hold's.
            R[R_HELD] += last - R[R_SEEN]
            R[R_N] = Q[Q_N]
            finish_experiment(
                R, Q, STATUS_DONE, REASON_NONE, R[R_START_NS] + (Q[Q_N] - 1.0) * Q[Q_TS_NS]
            )
            R[R_HOLD_REF] = R[R_TARGET]
            R[R_MODE] = MODE_HOLD
            running = False
            ended_unseen = True
        else:
            if R[R_N] != 0.0:
                R[R_HELD] += k - R[R_SEEN] - 1.0
            if applied == k - delay:
                R[R_FRESH] += 1.0
            elif applied > R[R_APPLIED] and R[R_SEEN] == k - 1.0:
                # a command newer than the one the previous state showed (after an
                # unseen state the two cannot be told apart: held)
                R[R_LATE] += 1.0
            else:
                R[R_HELD] += 1.0
    R[R_SEEN] = k
    R[R_APPLIED] = applied
    status = STATUS_HOLD
    reason = REASON_NONE
    isq = 0.0
    load = 0.0
    n = -1.0
    f1 = 0.0
    f2 = 0.0
    f3 = 0.0
    counted = 0.0
    isqf = 0.0
    ref = 0.0
    if R[R_MODE] == MODE_FAULT:
        status = STATUS_FAULT
        reason = R[R_FAULT_REASON]
        cout[O_ISQ] = 0.0
        cout[O_SAT] = 0.0
    else:
        safety = REASON_NONE
        if not (math.isfinite(th) and math.isfinite(w)):
            safety = REASON_NONFINITE
        else:
            if running:
                n = k - R[R_START_STEP]
                ref = R[R_THETA0] + R[R_DIR] * traj_pos(n * Q[Q_TS], Q)
                if n >= Q[Q_LOAD_N]:
                    load = Q[Q_LOAD] if Q[Q_LOAD_FIXED] != 0.0 else R[R_DIR] * Q[Q_LOAD]
            elif settling:
                n = k - R[R_START_STEP]  # < 0: the settle's steps
                ref = R[R_HOLD_REF]
            elif R[R_MODE] == MODE_RETURN:
                # after a supervisor stop: the fallback gains finish the move along the
                # unchanged trajectory (no reference jump), then hold the target
                nn = k - R[R_START_STEP]
                ref = R[R_THETA0] + R[R_DIR] * traj_pos(nn * Q[Q_TS], Q)
                R[R_N] = nn + 1.0
                if nn * Q[Q_TS] >= Q[Q_TEND]:
                    R[R_MODE] = MODE_HOLD
                    R[R_HOLD_REF] = R[R_TARGET]
            else:
                ref = R[R_HOLD_REF]
            isq = control_step(X, CF if settling else C, ref, th, w, cout)
            if abs(cout[O_E_THETA]) > Q[Q_MAX_ERR]:
                safety = REASON_POSITION
            elif abs(w) > Q[Q_MAX_SPEED]:
                safety = REASON_SPEED
        if safety != REASON_NONE:
            # Hard limit: torque off (drive-level safe state) until an explicit reset.
            R[R_MODE] = MODE_FAULT
            R[R_FAULT_REASON] = safety
            isq = 0.0
            load = 0.0
            cout[O_ISQ] = 0.0
            cout[O_SAT] = 0.0
            reason = safety
            if running:
                if n < 0.0:
                    n = k - R[R_START_STEP]
                R[R_N] = n + 1.0
                finish_experiment(R, Q, STATUS_ABORTED, safety, state[1])
                status = STATUS_ABORTED
            elif settling:
                # a fault in the settle ends the experiment before its step 0: aborted,
                # no step measured
                R[R_START_STEP] = k
                R[R_START_NS] = state[1]
                R[R_N] = 0.0
                finish_experiment(R, Q, STATUS_ABORTED, safety, state[1])
                R[R_TRIP_STEP] = -1.0
                status = STATUS_ABORTED
            else:
                status = STATUS_FAULT
        elif running:
            isq_max = Q[Q_ISQ_MAX]
            if n == 0.0:
                R[R_ISQF] = isq
            isqf = R[R_ISQF]
            f1 = abs(ref - th)
            f2 = abs(cout[O_OMEGA_REF] - w)
            f3 = abs(isqf - isq)
            if abs(isq) / isq_max < Q[Q_SAT_RATIO]:
                counted = 1.0
                R[R_S1] += f1
                R[R_S2] += f2
                R[R_S3] += f3
            a = Q[Q_ISQF_A]
            R[R_ISQF] = a * isqf + (1.0 - a) * isq
            ripple_step(R, Q, n, isq)
            motion_step(R, Q, n, th, w, state)
            ts = Q[Q_TS]
            R[R_TERM1] = Q[Q_A1] * ts * R[R_S1]
            R[R_TERM2] = Q[Q_A2] * ts * R[R_S2]
            R[R_TERM3] = Q[Q_A3] * ts * R[R_S3]
            trip = REASON_NONE
            if R[R_TERM1] > Q[Q_THR1]:
                trip = REASON_TERM1
            elif R[R_TERM2] > Q[Q_THR2]:
                trip = REASON_TERM2
            elif R[R_TERM3] > Q[Q_THR3]:
                trip = REASON_TERM3
            R[R_N] = n + 1.0
            if trip != REASON_NONE:
                finish_experiment(R, Q, STATUS_ABORTED, trip, state[1])
                # Stop at once: this step's command already comes from the position hold
                # at the measured position with the fallback gains (bumpless: references
                # = theta_meas, integrator 0); the load is removed.
                for j in range(C.shape[0]):
                    C[j] = CF[j]
                R[R_MODE] = MODE_RETURN
                isq = control_step(X, C, ref, th, w, cout)
                load = 0.0
                status = STATUS_ABORTED
                reason = trip
            elif R[R_N] >= Q[Q_N]:
                finish_experiment(R, Q, STATUS_DONE, REASON_NONE, state[1])
                R[R_HOLD_REF] = R[R_TARGET]
                R[R_MODE] = MODE_HOLD
                status = STATUS_DONE
            else:
                status = STATUS_RUNNING
        elif settling:
            status = STATUS_RUNNING
    if ended_unseen and status == STATUS_HOLD:
        status = STATUS_DONE  # the result of the experiment that ended unseen is ready
    eout[E_ISQ] = isq
    eout[E_LOAD] = load
    eout[E_STATUS] = status
    eout[E_REASON] = reason
    eout[E_N] = n
    eout[E_F1] = f1
    eout[E_F2] = f2
    eout[E_F3] = f3
    eout[E_ISQF] = isqf
    eout[E_COUNTED] = counted
    eout[E_T1] = R[R_TERM1]
    eout[E_T2] = R[R_TERM2]
    eout[E_T3] = R[R_TERM3]
    R[R_LAST_STEP] = k
    R[R_LAST_STATUS] = status
    R[R_LAST_ISQ] = isq
    R[R_LAST_LOAD] = load
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
    """``ControllerNode.answer`` compiled (a composed real-time loop calls it without the
    GIL, ``im_tuner.bench.compiled_loop``): :func:`experiment_step` on drive state k, the
    command (k, isq* [A], load [N m]) written into ``cmd`` (the command message's
    values), and every ``W[W_DECIMATION]``-th answer the internals [k, cout, eout] into
    ``internals`` (``W[W_INTERNALS_DUE]`` = 1). Returns the experiment status; the node
    takes the words back (``ControllerNode.set_answer_words``)."""
    k = state[0]
    st = experiment_step(R, Q, X, C, CF, state, cout, eout)
    cmd[0] = k
    cmd[1] = eout[E_ISQ]
    cmd[2] = eout[E_LOAD]
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
