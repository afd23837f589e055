"""Array layouts of the experiment kernel: status and reason codes, runner modes, the
experiment parameters Q, the runner state R and the per-step outputs E (numba kernels
index plain float64 arrays by these constants). Pure: no rclpy, no numba."""

from __future__ import annotations

from im_drive_sim.contract import STATE_FIELDS, STATE_INDEX

CONTROL_FIELDS: tuple[str, ...] = (
    'theta_ref',
    'theta_sm',
    'theta_m',
    'omega_ff',
    'omega_ref',
    'e_theta',
    'e_omega',
    'p_term',
    'i_term',
    'isq_ref',
    'saturated',
)
"""Internals written per step (units: rad, rad, rad, rad/s, rad/s, rad, rad/s, A, A, A, 0/1)."""

STATUS_HOLD = 0  # holding position between experiments
STATUS_RUNNING = 1  # experiment step processed, experiment continues
STATUS_DONE = 2  # this step completed the experiment; result() is ready
STATUS_ABORTED = 3  # this step stopped the experiment (supervisor or safety); result ready
STATUS_FAULT = 4  # safety fault: isq* = 0 and load 0 until reset()

REASON_NONE = 0
REASON_TERM1 = 1
REASON_TERM2 = 2
REASON_TERM3 = 3
REASON_POSITION = 4
REASON_SPEED = 5
REASON_NONFINITE = 6
REASON_DRIVE_TIMEOUT = 7  # set by the node's watchdog (ExperimentRunner.abort_external)
REASON_TUNER_LOST = 8  # set by the node's tuner watchdog (its client's heartbeat stopped)
REASONS: tuple[str, ...] = (
    '',
    'term1',
    'term2',
    'term3',
    'max_position_error',
    'max_speed',
    'non_finite_measurement',
    'drive_state_timeout',
    'tuner_lost',
)
"""Reason strings by reason code (LossResult.reason, ExperimentRunner.fault_reason)."""
SAFETY_REASONS: tuple[str, ...] = REASONS[REASON_POSITION:REASON_TUNER_LOST]
"""The drive's safety reasons: they put the runner in FAULT (the rest are supervisor
stops, and the link's ``LINK_REASONS``)."""
LINK_REASONS: tuple[str, ...] = (REASONS[REASON_TUNER_LOST],)
"""Reasons that put the runner in FAULT for the link, not the drive: the client that
tunes it went silent (``tuner_timeout``). Its experiment is lost, not a drive fault."""

MODE_HOLD = 0.0
MODE_RUN = 1.0
MODE_FAULT = 2.0
MODE_RETURN = 3.0  # hold after a supervisor stop, still following the trajectory
MODE_SETTLE = 4.0  # an experiment's standstill settle (fallback gains, no load, no loss)

Q_TS = 0
Q_TS_NS = 1
Q_N = 2  # steps per experiment
Q_LOAD_N = 3  # first local step with the load on
Q_LOAD = 4  # load magnitude [N m]
Q_LOAD_FIXED = 5  # 1: fixed sign, 0: opposes the move
Q_A1 = 6
Q_A2 = 7
Q_A3 = 8
Q_THR1 = 9
Q_THR2 = 10
Q_THR3 = 11
Q_ISQ_MAX = 12
Q_SAT_RATIO = 13
Q_ISQF_A = 14
Q_DIST = 15
Q_AMAX = 16
Q_VPEAK = 17
Q_TACC = 18  # end of acceleration [s]
Q_TDEC = 19  # start of deceleration [s]
Q_TEND = 20  # end of the move [s]
Q_MAX_ERR = 21
Q_MAX_SPEED = 22
Q_SETTLE_N = 23  # periods of standstill settle before an experiment's step 0
# the standstill windows of the current ripple (local steps [A, B)): after the move has
# settled and before the load step; after the load step has settled to the end
Q_RIP1_A = 24
Q_RIP1_B = 25
Q_RIP2_A = 26
Q_RIP2_B = 27
Q_ID_K = 28  # periods per block of the motion sums (MOTION_BLOCK seconds)
Q_ID_WDEAD = 29  # |omega_meas| [rad/s] below which the shaft counts as at rest
N_QPARAMS = 30

#: The ripple windows, relative to the experiment: from RIPPLE_AFTER_MOVE after the move's
#: end to the load step, and from RIPPLE_AFTER_LOAD after the load step to the end [s]
#: (0.300-0.700 s and 0.900-1.125 s for the paper's experiment: its Fig. 8's flat parts).
RIPPLE_AFTER_MOVE = 0.155
RIPPLE_AFTER_LOAD = 0.2
#: The motion sums' block [s] and dead band (a fraction of the move's peak speed: above
#: one encoder count per period after the speed filter, 1.4 rad/s on the paper's drive).
#: (20 ms: shorter blocks let the encoder's quantisation bias J low, docs/controller.md)
MOTION_BLOCK = 0.02
MOTION_DEAD_BAND = 0.1

R_MODE = 0
R_N = 1  # next local step
R_DIR = 2
R_THETA0 = 3
R_TARGET = 4
R_HOLD_REF = 5
R_S1 = 6  # sum of counted f1 (unweighted)
R_S2 = 7
R_S3 = 8
R_ISQF = 9
R_TRIP_STEP = 10
R_REASON = 11  # reason of the last finished experiment
R_RESULT = 12  # 0 none, STATUS_DONE or STATUS_ABORTED
R_START_STEP = 13
R_START_NS = 14
R_END_NS = 15
R_STEPS = 16
R_LAST_STEP = 17
R_LAST_STATUS = 18
R_LAST_ISQ = 19
R_LAST_LOAD = 20
R_FAULT_REASON = 21
R_TERM1 = 22  # weighted terms a_j Ts S_j (kept for the result)
R_TERM2 = 23
R_TERM3 = 24
# the experiment on the drive's timeline (docs/controller.md, "Timing"): periods whose end
# state came from a fresh answer, a late one, or a held (or unseen) one
R_FRESH = 25
R_LATE = 26
R_HELD = 27
R_SEEN = 28  # step index of the last state processed
R_APPLIED = 29  # its applied_step
R_GAINS_STEP = 30  # the first state the current gains acted on (set_gains)
#: The standstill ripple of isq* in the two windows w = 0, 1 (Q_RIP*): the words
#: R_RIP + 5 w + (count, sum [A], sum of squares [A^2], min [A], max [A]).
R_RIP = 31
#: The motion sums (``im_tuner.identify``): blocks b of Q_ID_K periods; at the start of
#: block b + 1 the pair (b - 1, b) gives one row z (MOTION_COLUMNS) and sum z z^T grows.
R_ID_THA = 41  # theta_meas at the start of block b - 1 [rad]
R_ID_THB = 42  # theta_meas at the start of block b [rad]
R_ID_NB = 43  # the next block's index (blocks before it were seen or skipped)
R_ID_RISE = 44  # 4 words: the previous block's rising part, sum (m + 1/2)/K x_q
R_ID_S0 = 48  # 4 words: this block's sum x_q
R_ID_S1 = 52  # 4 words: this block's sum (m + 1/2) x_q
R_ID_M = 56  # 15 words: sum z_i z_j, i <= j, row by row
R_ID_ROWS = 71  # rows in it
R_ID_CHAIN = 72  # consecutive blocks whose first state was seen (a row needs 2 before)
N_RSTATE = 73
#: The motion rows' columns: z = (mean-speed change [rad/s], triangle-weighted integrals
#: of isq [A s], omega_meas [rad], sign(omega_meas) [s] and load_torque [N m s]).  With
#: J d(omega)/dt = Kt isq - B omega - Tc sign(omega) - T_load each row reads
#: J z0 = Kt z1 - B z2 - Tc z3 - z4 (up to the encoder's and the model's errors).
MOTION_COLUMNS: tuple[str, ...] = ('domega', 'isq', 'omega', 'sign', 'load')
N_MOTION = 16  # the rows' count and the 15 sums (LossResult.motion)
#: Words an experiment's start clears: loss sums and terms, the isq* filter, the last result.
R_CLEARED_AT_START = (
    R_S1,
    R_S2,
    R_S3,
    R_TERM1,
    R_TERM2,
    R_TERM3,
    R_ISQF,
    R_RESULT,
    R_REASON,
    R_STEPS,
    *range(R_RIP, N_RSTATE),
)

#: Values in a drive state (the drive contract).
N_STATE_FIELDS = len(STATE_FIELDS)
#: Index of ``applied_step`` in a drive state.
S_APPLIED = STATE_INDEX['applied_step']
#: Index of ``command_delay`` in a drive state.
S_CMD_DELAY = STATE_INDEX['command_delay']
#: Indices of the measured isq and the load machine's torque in a drive state (the motion
#: sums; the control itself uses fields 0-3 only).
S_ISQ = STATE_INDEX['isq']
S_LOAD = STATE_INDEX['load_torque']

EXP_FIELDS: tuple[str, ...] = (
    'isq_cmd',
    'load_cmd',
    'status',
    'reason',
    'exp_step',
    'f1',
    'f2',
    'f3',
    'isq_f',
    'counted',
    'term1',
    'term2',
    'term3',
)
"""Per-step experiment outputs: command [A], load [N m], status, reason code, local step
(-1 in hold), f1 [rad], f2 [rad/s], f3 [A], isqF [A], counted (0/1), running terms."""
(E_ISQ, E_LOAD, E_STATUS, E_REASON, E_N, E_F1, E_F2, E_F3, E_ISQF, E_COUNTED, E_T1, E_T2, E_T3) = (
    range(len(EXP_FIELDS))
)
N_EXP_FIELDS = len(EXP_FIELDS)
#: Layout of the controller node's ``controller/internals`` (Float64MultiArray.data): the
#: drive step index k, then the controller's and the experiment's per-step outputs.
INTERNALS_FIELDS: tuple[str, ...] = ('step_index', *CONTROL_FIELDS, *EXP_FIELDS)
