"""The loss experiment of the paper: trajectory, load step, online loss, supervisor.

One experiment (paper, "The loss function"; docs/controller.md):

* reference: minimum-time trajectory over ``distance`` = pi rad under ``a_max`` = 600 rad/s^2
  and ``v_max`` = 40 rad/s (0.145 s trapezoid; triangular if v_max is not reached),
  starting at the current hold reference; experiment n moves by +pi if n is even, -pi if odd;
* load: 0 -> ``load_torque`` (1.75 N m) from 0.7 s after the reference change to the end
  (1.125 s, 5625 steps); sign 'oppose_move' (default) or 'fixed';
* online loss (eq. 4-7), per step n = 0..N-1 with c_n = [|isq*_n|/isq_max < 0.99]::

      f1 = |theta*_n - theta_meas_n|        (raw trajectory reference)
      f2 = |omega*_n - omega_meas_n|        (omega* = the speed controller's reference)
      f3 = |isqF_n - isq*_n|,  isqF_0 = isq*_0,  isqF_{n+1} = a isqF_n + (1-a) isq*_n,
           a = exp(-Ts/0.02 s)  (exact for the held isq*)
      term_j = a_j Ts sum_n c_n f_j,n ;   L = term1 + term2 + term3

* supervisor: after each step, if term_j > threshold_j the experiment stops at once:
  L is multiplied by ``penalty``, the result names the term and the step; from that very
  step the fallback gains (the hand-tuned start) take over, finish the move along the
  unchanged trajectory (no reference jump, load removed) and hold the target.  Hard safety limits
  (|theta_m - theta_meas| > max_position_error, |omega_meas| > max_speed, non-finite
  samples) are checked every step in every mode and put the runner in FAULT
  (isq* = 0, load 0) until ``reset``.

The per-step kernel :func:`experiment_step` is what the ROS node calls (one call per
received state); :func:`run_experiment_offline` runs the same kernel fused with the drive
kernels in one numba loop (the oracle for the ROS tests and the engine of offline studies).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from im_drive_sim import kernels as DK
from im_drive_sim.sim import DriveSim

from .config import ExperimentConfig, Gains, validate_experiment_config, validate_gains
from .control import (
    CONTROL_FIELDS,
    N_CONTROL_FIELDS,
    N_CSTATE,
    O_E_THETA,
    O_ISQ,
    O_OMEGA_REF,
    O_SAT,
    control_reset,
    control_step,
    fill_control_params,
    make_control_params,
)

__all__ = [
    'EXP_FIELDS',
    'INTERNALS_FIELDS',
    'REASONS',
    'SAFETY_REASONS',
    'STATUS_ABORTED',
    'STATUS_DONE',
    'STATUS_FAULT',
    'STATUS_HOLD',
    'STATUS_RUNNING',
    'Experiment',
    'ExperimentRunner',
    'LossResult',
    'experiment_step',
    'finish_stopped_move',
    'hold_offline',
    'run_experiment_offline',
    'trajectory',
    'trajectory_times',
]

# ----------------------------------------------------------------- status and reasons
STATUS_HOLD = 0  # holding position between experiments
STATUS_RUNNING = 1  # experiment step processed, experiment continues
STATUS_DONE = 2  # this step completed the experiment; result() is ready
STATUS_ABORTED = 3  # this step stopped the experiment (supervisor or safety); result ready
STATUS_FAULT = 4  # safety fault: isq* = 0 and load 0 until reset()
STATUS_NAMES = ('hold', 'running', 'done', 'aborted', 'fault')

REASON_NONE = 0
REASON_TERM1 = 1
REASON_TERM2 = 2
REASON_TERM3 = 3
REASON_POSITION = 4
REASON_SPEED = 5
REASON_NONFINITE = 6
REASON_DRIVE_TIMEOUT = 7  # set by the node's watchdog (ExperimentRunner.abort_external)
REASONS: tuple[str, ...] = (
    '',
    'term1',
    'term2',
    'term3',
    'max_position_error',
    'max_speed',
    'non_finite_measurement',
    'drive_state_timeout',
)
"""Reason strings by reason code (LossResult.reason, ExperimentRunner.fault_reason)."""
SAFETY_REASONS: tuple[str, ...] = REASONS[REASON_POSITION:]
"""Reasons that put the runner in FAULT (the rest are supervisor stops)."""

MODE_HOLD = 0.0
MODE_RUN = 1.0
MODE_FAULT = 2.0
MODE_RETURN = 3.0  # hold after a supervisor stop, still following the trajectory

# ------------------------------------------------------------ experiment parameters Q
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
N_QPARAMS = 23

# -------------------------------------------------------------------- runner state R
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
N_RSTATE = 25

# ----------------------------------------------------------------- per-step outputs E
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


# ------------------------------------------------------------------------ trajectory
def trajectory_times(
    distance: float, a_max: float, v_max: float
) -> tuple[float, float, float, float]:
    """Minimum-time rest-to-rest move under |a| <= a_max, |v| <= v_max.

    Returns (t_acc, t_dec, t_end, v_peak) [s, s, s, rad/s]: acceleration until t_acc,
    cruise at v_peak until t_dec, deceleration until t_end.  Trapezoid if
    distance >= v_max^2/a_max (t_acc = v_max/a_max, cruise (distance - v_max^2/a_max)/v_max),
    else triangle (t_acc = sqrt(distance/a_max), v_peak = a_max t_acc, no cruise).
    Default pi rad, 600 rad/s^2, 40 rad/s: t_acc = 0.0667, t_end = 0.1452 s.
    """
    if distance >= v_max * v_max / a_max:
        t_acc = v_max / a_max
        t_cruise = (distance - v_max * v_max / a_max) / v_max
        v_peak = v_max
    else:
        t_acc = math.sqrt(distance / a_max)
        t_cruise = 0.0
        v_peak = a_max * t_acc
    return t_acc, t_acc + t_cruise, 2.0 * t_acc + t_cruise, v_peak


@njit(cache=True)
def traj_pos(t: float, Q: np.ndarray) -> float:
    """Distance travelled s(t) [rad] of the move (0 before, exactly ``distance`` after)."""
    a = Q[Q_AMAX]
    if t <= 0.0:
        return 0.0
    if t < Q[Q_TACC]:
        return 0.5 * a * t * t
    if t < Q[Q_TDEC]:
        ta = Q[Q_TACC]
        return 0.5 * a * ta * ta + Q[Q_VPEAK] * (t - ta)
    if t < Q[Q_TEND]:
        r = Q[Q_TEND] - t
        return Q[Q_DIST] - 0.5 * a * r * r
    return Q[Q_DIST]


@njit(cache=True)
def _traj_arrays(
    t: np.ndarray, Q: np.ndarray, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray
) -> None:
    a = Q[Q_AMAX]
    for i in range(t.shape[0]):
        ti = t[i]
        pos[i] = traj_pos(ti, Q)
        if ti <= 0.0 or ti >= Q[Q_TEND]:
            vel[i] = 0.0
            acc[i] = 0.0
        elif ti < Q[Q_TACC]:
            vel[i] = a * ti
            acc[i] = a
        elif ti < Q[Q_TDEC]:
            vel[i] = Q[Q_VPEAK]
            acc[i] = 0.0
        else:
            vel[i] = a * (Q[Q_TEND] - ti)
            acc[i] = -a


def make_experiment_params(cfg: ExperimentConfig) -> np.ndarray:
    """Kernel parameter vector ``Q`` from a validated config."""
    c, lo, tr, sf = cfg.control, cfg.loss, cfg.trajectory, cfg.safety
    Q = np.zeros(N_QPARAMS)
    Q[Q_TS] = c.Ts
    Q[Q_TS_NS] = float(round(c.Ts * 1e9))
    Q[Q_N] = float(round(tr.duration / c.Ts))
    # ceil: the load is on from the first sample at or after load_delay (0.7 s -> n = 3500)
    Q[Q_LOAD_N] = float(math.ceil(tr.load_delay / c.Ts - 1e-9))
    Q[Q_LOAD] = tr.load_torque
    Q[Q_LOAD_FIXED] = 1.0 if tr.load_sign == 'fixed' else 0.0
    Q[Q_A1], Q[Q_A2], Q[Q_A3] = lo.a1, lo.a2, lo.a3
    Q[Q_THR1], Q[Q_THR2], Q[Q_THR3] = lo.threshold1, lo.threshold2, lo.threshold3
    Q[Q_ISQ_MAX] = c.isq_max
    Q[Q_SAT_RATIO] = lo.sat_ratio
    Q[Q_ISQF_A] = math.exp(-c.Ts / lo.isqf_tau)
    t_acc, t_dec, t_end, v_peak = trajectory_times(tr.distance, tr.a_max, tr.v_max)
    Q[Q_DIST] = tr.distance
    Q[Q_AMAX] = tr.a_max
    Q[Q_VPEAK] = v_peak
    Q[Q_TACC], Q[Q_TDEC], Q[Q_TEND] = t_acc, t_dec, t_end
    Q[Q_MAX_ERR] = sf.max_position_error
    Q[Q_MAX_SPEED] = sf.max_speed
    return Q


def trajectory(
    t: np.ndarray, cfg: ExperimentConfig | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Move profile at times ``t`` [s] after the reference change: (s [rad], ds/dt [rad/s],
    d2s/dt2 [rad/s^2]) for a positive move of ``trajectory.distance``."""
    cfg = validate_experiment_config(ExperimentConfig() if cfg is None else cfg)
    Q = make_experiment_params(cfg)
    tt = np.ascontiguousarray(np.asarray(t, dtype=np.float64).ravel())
    pos, vel, acc = np.empty_like(tt), np.empty_like(tt), np.empty_like(tt)
    _traj_arrays(tt, Q, pos, vel, acc)
    return pos, vel, acc


# ---------------------------------------------------------------------- the kernel
@njit(cache=True)
def _finish(R: np.ndarray, Q: np.ndarray, status: float, reason: float, time_ns: float) -> None:
    R[R_RESULT] = status
    R[R_REASON] = reason
    R[R_STEPS] = R[R_N]
    R[R_END_NS] = time_ns + Q[Q_TS_NS]
    R[R_TRIP_STEP] = R[R_N] - 1.0 if status == STATUS_ABORTED else -1.0


@njit(cache=True)
def experiment_step(
    R: np.ndarray,
    Q: np.ndarray,
    X: np.ndarray,
    C: np.ndarray,
    CF: np.ndarray,
    state: np.ndarray,
    cout: np.ndarray,
    eout: np.ndarray,
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
                n = R[R_N]
                if n == 0.0:
                    R[R_START_STEP] = k
                    R[R_START_NS] = state[1]
                ref = R[R_THETA0] + R[R_DIR] * traj_pos(n * Q[Q_TS], Q)
                if n >= Q[Q_LOAD_N]:
                    load = Q[Q_LOAD] if Q[Q_LOAD_FIXED] != 0.0 else R[R_DIR] * Q[Q_LOAD]
            elif R[R_MODE] == MODE_RETURN:
                # after a supervisor stop: the fallback gains finish the move along the
                # unchanged trajectory (no reference jump), then hold the target
                nn = R[R_N]
                ref = R[R_THETA0] + R[R_DIR] * traj_pos(nn * Q[Q_TS], Q)
                R[R_N] = nn + 1.0
                if nn * Q[Q_TS] >= Q[Q_TEND]:
                    R[R_MODE] = MODE_HOLD
                    R[R_HOLD_REF] = R[R_TARGET]
            else:
                ref = R[R_HOLD_REF]
            isq = control_step(X, C, ref, th, w, cout)
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
                    n = R[R_N]
                R[R_N] = n + 1.0
                _finish(R, Q, STATUS_ABORTED, safety, state[1])
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
                _finish(R, Q, STATUS_ABORTED, trip, state[1])
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
                _finish(R, Q, STATUS_DONE, REASON_NONE, state[1])
                R[R_HOLD_REF] = R[R_TARGET]
                R[R_MODE] = MODE_HOLD
                status = STATUS_DONE
            else:
                status = STATUS_RUNNING
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


N_REC = DK.N_STATE_FIELDS + N_CONTROL_FIELDS + N_EXP_FIELDS
REC_FIELDS: tuple[str, ...] = DK.STATE_FIELDS + CONTROL_FIELDS + EXP_FIELDS


@njit(cache=True)
def run_fused(
    S: np.ndarray,
    P: np.ndarray,
    noise: np.ndarray,
    R: np.ndarray,
    Q: np.ndarray,
    X: np.ndarray,
    C: np.ndarray,
    CF: np.ndarray,
    state: np.ndarray,
    cout: np.ndarray,
    eout: np.ndarray,
    rec: np.ndarray,
    row0: int,
    n_max: int,
    record: bool,
    stop_at_end: bool,
) -> int:
    """Controller/experiment kernel and drive kernel in one loop, at most ``n_max`` steps.

    Per step: ``experiment_step`` on ``state`` (the drive state k), the drive steps with
    the command (exactly ``DriveSim.step_into``), ``state`` <- state k+1.  Row
    ``row0 + i`` of ``rec`` gets [state k, controller internals, experiment outputs].
    Stops after a DONE/ABORTED/FAULT step if ``stop_at_end``.  Returns the steps done.
    """
    ns = DK.N_STATE_FIELDS
    nc = N_CONTROL_FIELDS
    for i in range(n_max):
        st = experiment_step(R, Q, X, C, CF, state, cout, eout)
        if record:
            row = rec[row0 + i]
            for j in range(ns):
                row[j] = state[j]
            for j in range(nc):
                row[ns + j] = cout[j]
            for j in range(N_EXP_FIELDS):
                row[ns + nc + j] = eout[j]
        DK.step_model(S, P, noise, eout[E_ISQ], eout[E_LOAD])
        DK.write_out(S, P, state)
        if stop_at_end and st >= STATUS_DONE:
            return i + 1
    return n_max


# ------------------------------------------------------------------------- results
@dataclass(frozen=True)
class LossResult:
    """Outcome of one experiment.

    loss: term1 + term2 + term3, times ``penalty`` if aborted.
    terms: (a1 int f1 dt, a2 int f2 dt, a3 int f3 dt) up to the last step run (unpenalised).
    reason: '' (completed), 'term1'..'term3' (supervisor), 'max_position_error',
        'max_speed', 'non_finite_measurement' (safety; the runner is then in FAULT).
    trip_step: local step (0-based) that stopped it, -1 if none; trip_time = trip_step Ts [s].
    t_start, t_end: sim time [ns] of the first step's state and of the end of the last step.
    steps: steps run; direction: +1 / -1.
    """

    experiment_id: int
    loss: float
    terms: tuple[float, float, float]
    aborted: bool
    reason: str
    trip_step: int
    trip_time: float
    gains: Gains
    t_start: int
    t_end: int
    steps: int
    direction: int


@dataclass(frozen=True)
class Experiment:
    """Description of experiment ``experiment_id`` starting at reference ``theta0`` [rad]."""

    experiment_id: int
    theta0: float
    config: ExperimentConfig

    @property
    def direction(self) -> int:
        """+1 for even ids, -1 for odd ids (0 -> pi -> 0 ...)."""
        return 1 if self.experiment_id % 2 == 0 else -1

    @property
    def target(self) -> float:
        return self.theta0 + self.direction * self.config.trajectory.distance

    @property
    def steps(self) -> int:
        return round(self.config.trajectory.duration / self.config.control.Ts)

    def reference(self) -> dict[str, np.ndarray]:
        """theta* [rad], its speed [rad/s] and the load command [N m] for n = 0..steps-1."""
        cfg = validate_experiment_config(self.config)
        Q = make_experiment_params(cfg)
        n = np.arange(self.steps)
        t = n * cfg.control.Ts
        pos, vel, _ = trajectory(t, cfg)
        sign = 1.0 if cfg.trajectory.load_sign == 'fixed' else float(self.direction)
        load = np.where(n >= Q[Q_LOAD_N], sign * cfg.trajectory.load_torque, 0.0)
        return {
            't': t,
            'theta_ref': self.theta0 + self.direction * pos,
            'omega_traj': self.direction * vel,
            'load': load,
        }


# -------------------------------------------------------------------------- runner
class ExperimentRunner:
    """Position hold + experiments, one kernel call per drive state (the node's core).

    Usage (ROS node or offline)::

        runner = ExperimentRunner(cfg, gains)
        runner.reset(theta_meas)                  # hold here (also clears a FAULT)
        runner.start(experiment_id, gains)        # the next step() is experiment step 0
        isq, load, status = runner.step(state)    # state: STATE_FIELDS (uses fields 0-3)
        if status in (STATUS_DONE, STATUS_ABORTED): res = runner.result()

    Between experiments (and after DONE) it holds the last target with the current gains;
    after a supervisor stop ``fallback_gains`` finish the move along the trajectory and
    hold the target (``ready`` is False until the move's end time has passed).
    Safety limits are active in every mode.
    """

    def __init__(self, config: ExperimentConfig | None = None, gains: Gains | None = None) -> None:
        self.config: ExperimentConfig = validate_experiment_config(
            ExperimentConfig() if config is None else config
        )
        self.gains: Gains = validate_gains(Gains() if gains is None else gains)
        self.Q: np.ndarray = make_experiment_params(self.config)
        self.C: np.ndarray = make_control_params(self.gains, self.config.control)
        self.CF: np.ndarray = make_control_params(self.config.fallback_gains, self.config.control)
        self.X: np.ndarray = np.zeros(N_CSTATE)
        self.R: np.ndarray = np.zeros(N_RSTATE)
        self.cout: np.ndarray = np.zeros(N_CONTROL_FIELDS)
        self.eout: np.ndarray = np.zeros(N_EXP_FIELDS)
        self.experiment_id: int = -1
        self._exp_gains: Gains = self.gains
        self.reset(0.0)

    # -- modes
    def reset(self, theta_meas: float) -> None:
        """Hold ``theta_meas`` [rad] (references = theta_meas, integrator 0); clears FAULT
        and any running experiment (without a result)."""
        if not math.isfinite(theta_meas):
            raise ValueError(f'theta_meas must be finite, got {theta_meas!r}')
        control_reset(self.X, float(theta_meas))
        self.R[:] = 0.0
        self.R[R_MODE] = MODE_HOLD
        self.R[R_HOLD_REF] = float(theta_meas)
        self.R[R_TARGET] = float(theta_meas)
        self.R[R_LAST_STEP] = -1.0
        self.R[R_TRIP_STEP] = -1.0

    def set_gains(self, gains: Gains) -> None:
        """Apply new gains now (validated, atomic).  Refused while an experiment runs."""
        g = validate_gains(gains)
        if self.running:
            raise RuntimeError('cannot change gains while an experiment is running')
        c = self.config.control
        fill_control_params(self.C, g, c.Ts, c.isq_max, c.feedforward)
        self.gains = g

    def set_config(self, config: ExperimentConfig) -> None:
        """Apply a new experiment configuration (loss, trajectory, ...), validated and
        atomic.  Refused while an experiment runs.  Ts, isq_max and the safety limits
        are structural: a config that changes them is refused too."""
        cfg = validate_experiment_config(config)
        if self.running:
            raise RuntimeError(
                'cannot change the experiment configuration while an experiment is running'
            )
        if cfg.control != self.config.control or cfg.safety != self.config.safety:
            raise RuntimeError(
                'control structure (Ts, isq_max, feedforward) and safety '
                'limits cannot change at run time'
            )
        self.Q[:] = make_experiment_params(cfg)
        fill_control_params(
            self.CF,
            cfg.fallback_gains,
            cfg.control.Ts,
            cfg.control.isq_max,
            cfg.control.feedforward,
        )
        self.config = cfg

    def abort_external(self, reason: int, time_ns: int) -> None:
        """Torque off from outside (e.g. the drive-state watchdog): FAULT with ``reason``
        (a ``REASON_*`` code); a running experiment ends aborted (penalised) at sim time
        ``time_ns`` [ns] of the last state seen.  ``reset()`` clears the fault."""
        R = self.R
        if self.running:
            _finish(R, self.Q, float(STATUS_ABORTED), float(reason), float(time_ns))
        R[R_MODE] = MODE_FAULT
        R[R_FAULT_REASON] = float(reason)

    def start(self, experiment_id: int, gains: Gains | None = None) -> None:
        """Arm experiment ``experiment_id`` (int >= 0) with ``gains`` (None: current);
        the next ``step`` is its step 0.  It starts at the current hold reference and moves
        by +distance (even id) or -distance (odd id)."""
        if (
            isinstance(experiment_id, bool)
            or not isinstance(experiment_id, (int, np.integer))
            or experiment_id < 0
        ):
            raise ValueError(f'experiment_id must be an integer >= 0, got {experiment_id!r}')
        if self.R[R_MODE] == MODE_FAULT:
            raise RuntimeError(f'runner in FAULT ({self.fault_reason}); call reset() first')
        if self.running:
            raise RuntimeError('an experiment is already running')
        if not self.ready:
            raise RuntimeError('still finishing the stopped move; wait until ready')
        if gains is not None:
            self.set_gains(gains)
        R = self.R
        d = 1.0 if experiment_id % 2 == 0 else -1.0
        R[R_DIR] = d
        R[R_THETA0] = R[R_HOLD_REF]
        R[R_TARGET] = R[R_THETA0] + d * self.Q[Q_DIST]
        R[R_N] = 0.0
        for j in (R_S1, R_S2, R_S3, R_TERM1, R_TERM2, R_TERM3, R_ISQF, R_RESULT, R_REASON, R_STEPS):
            R[j] = 0.0
        R[R_TRIP_STEP] = -1.0
        R[R_MODE] = MODE_RUN
        self.experiment_id = int(experiment_id)
        self._exp_gains = self.gains

    def step(self, state: np.ndarray) -> tuple[float, float, int]:
        """One drive state (float64 array, ``STATE_FIELDS`` order; fields 0-3 used) ->
        (isq* [A], load torque command [N m], status)."""
        st = experiment_step(self.R, self.Q, self.X, self.C, self.CF, state, self.cout, self.eout)
        if st == STATUS_ABORTED and self.R[R_REASON] < REASON_POSITION:
            self.gains = self.config.fallback_gains  # the kernel switched to them
        return float(self.eout[E_ISQ]), float(self.eout[E_LOAD]), int(st)

    # -- queries
    @property
    def running(self) -> bool:
        return bool(self.R[R_MODE] == MODE_RUN)

    @property
    def ready(self) -> bool:
        """True in plain position hold: ``start`` may be called."""
        return bool(self.R[R_MODE] == MODE_HOLD)

    @property
    def faulted(self) -> bool:
        return bool(self.R[R_MODE] == MODE_FAULT)

    @property
    def fault_reason(self) -> str:
        return REASONS[int(self.R[R_FAULT_REASON])] if self.faulted else ''

    @property
    def hold_reference(self) -> float:
        """Position [rad] held between experiments (the next experiment starts here)."""
        return float(self.R[R_TARGET] if self.R[R_MODE] == MODE_RETURN else self.R[R_HOLD_REF])

    @property
    def target(self) -> float:
        """End position [rad] of the current / last experiment."""
        return float(self.R[R_TARGET])

    def result(self) -> LossResult | None:
        """The result of the last experiment, or None while running / before any."""
        R = self.R
        if R[R_RESULT] == 0.0 or self.running:
            return None
        aborted = R[R_RESULT] == STATUS_ABORTED
        terms = (float(R[R_TERM1]), float(R[R_TERM2]), float(R[R_TERM3]))
        loss = terms[0] + terms[1] + terms[2]
        if aborted:
            loss *= self.config.loss.penalty
        trip = int(R[R_TRIP_STEP])
        return LossResult(
            experiment_id=self.experiment_id,
            loss=float(loss),
            terms=terms,
            aborted=bool(aborted),
            reason=REASONS[int(R[R_REASON])],
            trip_step=trip,
            trip_time=trip * self.config.control.Ts if trip >= 0 else -1.0,
            gains=self._exp_gains,
            t_start=int(R[R_START_NS]),
            t_end=int(R[R_END_NS]),
            steps=int(R[R_STEPS]),
            direction=int(R[R_DIR]),
        )


# ------------------------------------------------------------------------- offline
def config_for_drive(cfg: ExperimentConfig | None, sim: DriveSim) -> ExperimentConfig:
    """``cfg`` with Ts and isq_max taken from the drive (they are drive properties)."""
    cfg = ExperimentConfig() if cfg is None else cfg
    ctl = dataclasses.replace(
        cfg.control, Ts=float(sim.config.Ts), isq_max=float(sim.config.machine.isq_max)
    )
    return validate_experiment_config(dataclasses.replace(cfg, control=ctl))


def _run(
    sim: DriveSim,
    runner: ExperimentRunner,
    n: int,
    record: bool,
    stop_at_end: bool,
    python_loop: bool,
) -> tuple[int, np.ndarray]:
    state = np.zeros(DK.N_STATE_FIELDS)
    sim.read_into(state)
    rec = np.zeros((n if record else 1, N_REC))
    done = 0
    if python_loop:
        # The ROS node's path, step by step through the public APIs (for equivalence tests).
        ns, nc = DK.N_STATE_FIELDS, N_CONTROL_FIELDS
        for i in range(n):
            isq, load, st = runner.step(state)
            if record:
                rec[i, :ns] = state
                rec[i, ns : ns + nc] = runner.cout
                rec[i, ns + nc :] = runner.eout
            sim.step_into(isq, load, state)
            done += 1
            if stop_at_end and st >= STATUS_DONE:
                break
        return done, rec[:done]
    while done < n:
        # Chunks end on the drive's noise-block boundaries, exactly as DriveSim.run does.
        cnt = min(n - done, sim._left)
        k = run_fused(
            sim.S,
            sim.P,
            sim._noise,
            runner.R,
            runner.Q,
            runner.X,
            runner.C,
            runner.CF,
            state,
            runner.cout,
            runner.eout,
            rec,
            done if record else 0,
            cnt,
            record,
            stop_at_end,
        )
        sim._left -= k
        if sim._left == 0:
            sim._refill()
        done += k
        if k < cnt or (stop_at_end and runner.eout[E_STATUS] >= STATUS_DONE):
            break
    if runner.eout[E_STATUS] == STATUS_ABORTED and runner.R[R_REASON] < REASON_POSITION:
        runner.gains = runner.config.fallback_gains
    return done, rec[:done]


def _signals(rec: np.ndarray, Ts: float, t0_step: float) -> dict[str, np.ndarray]:
    sig = {name: rec[:, j].copy() for j, name in enumerate(REC_FIELDS)}
    sig['t'] = (sig['step_index'] - t0_step) * Ts
    return sig


def run_experiment_offline(
    sim: DriveSim,
    gains: Gains,
    config: ExperimentConfig | None = None,
    experiment_id: int = 0,
    runner: ExperimentRunner | None = None,
    record: bool = True,
    python_loop: bool = False,
) -> tuple[LossResult, dict[str, np.ndarray]]:
    """Run one whole experiment against the pure drive core (no ROS).

    sim: the drive, in whatever state it is (nothing is reset: state carries over).
    gains: the candidate; config: experiment config (Ts, isq_max are taken from ``sim``).
    runner: pass the same runner for consecutive experiments (it carries the controller
        state and the hold reference); None creates one holding ``sim.theta_meas``.
    record: return per-step signals (``REC_FIELDS`` + 't' [s from the start]); row n is
        drive state n (before its command) with the controller internals and the
        experiment outputs computed from it.
    python_loop: step through ``ExperimentRunner.step``/``DriveSim.step_into`` in Python
        (the node's path) instead of the fused numba loop; results are bit-identical.

    Returns (LossResult, signals).  Same inputs -> bit-identical results.
    """
    if runner is None:
        runner = ExperimentRunner(config_for_drive(config, sim), gains)
        runner.reset(sim.theta_meas)
    finish_stopped_move(sim, runner, python_loop)
    runner.start(experiment_id, gains)
    n = int(runner.Q[Q_N])
    k0 = float(sim.step_index)
    _done, rec = _run(sim, runner, n, record, True, python_loop)
    res = runner.result()
    assert res is not None, 'experiment did not finish'
    sig = _signals(rec, runner.config.control.Ts, k0) if record else {}
    return res, sig


def finish_stopped_move(sim: DriveSim, runner: ExperimentRunner, python_loop: bool = False) -> int:
    """After a supervisor stop the fallback gains finish the move (``ready`` is False):
    run exactly the steps until it ends, or until a safety fault stops it -- what the
    lock-step node does (it steps while not ready and pauses once ready or faulted).
    Returns the steps run (0 if no stopped move is being finished)."""
    R, Q = runner.R, runner.Q
    if R[R_MODE] != MODE_RETURN:
        return 0
    # the steps left: the kernel ends the move on the step whose local index nn has
    # nn Ts >= t_end (same float expression, so the same step)
    nn, steps = R[R_N], 1
    while not nn * Q[Q_TS] >= Q[Q_TEND]:
        nn += 1.0
        steps += 1
    done, _ = _run(sim, runner, steps, False, True, python_loop)
    assert R[R_MODE] in (MODE_HOLD, MODE_FAULT), 'the stopped move did not end'
    return done


def hold_offline(
    sim: DriveSim,
    runner: ExperimentRunner,
    steps: int,
    record: bool = False,
    python_loop: bool = False,
) -> dict[str, np.ndarray]:
    """Run ``steps`` steps of whatever the runner is doing (normally the hold)."""
    k0 = float(sim.step_index)
    _done, rec = _run(sim, runner, int(steps), record, False, python_loop)
    return _signals(rec, runner.config.control.Ts, k0) if record else {}
