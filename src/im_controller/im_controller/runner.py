"""The experiment runner: position hold and experiments, one kernel call per drive state
(the controller node's core), and :func:`config_for_drive`."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from im_drive_sim.sim import DriveSim

from . import layout as L
from .config import ExperimentConfig, Gains, validate_experiment_config, validate_gains
from .control import (
    N_CONTROL_FIELDS,
    N_CSTATE,
    control_reset,
    fill_control_params,
    make_control_params,
)
from .kernel import experiment_step, finish_experiment
from .result import LossResult
from .trajectory import make_experiment_params


class ExperimentRunner:
    """Position hold + experiments, one kernel call per drive state (docs/controller.md,
    section 6): between experiments it holds the last target with the current gains; after
    a supervisor stop ``fallback_gains`` finish the move (``ready`` False until it ends)."""

    def __init__(
        self,
        config: ExperimentConfig | None = None,
        gains: Gains | None = None,
        timing_tolerance: int = 0,
    ) -> None:
        #: periods of an experiment that may be held or late before its result is marked
        #: ``timing`` (a measurement on another timing than the paper's: not a loss)
        tol = timing_tolerance
        if isinstance(tol, bool) or not isinstance(tol, (int, np.integer)) or tol < 0:
            raise ValueError(f'timing_tolerance must be an integer >= 0 [periods], got {tol!r}')
        self.timing_tolerance = int(tol)
        self.config: ExperimentConfig = validate_experiment_config(
            ExperimentConfig() if config is None else config
        )
        self.gains: Gains = validate_gains(Gains() if gains is None else gains)
        self.Q: np.ndarray = make_experiment_params(self.config)
        self.C: np.ndarray = make_control_params(self.gains, self.config.control)
        self.CF: np.ndarray = make_control_params(self.config.fallback_gains, self.config.control)
        self.X: np.ndarray = np.zeros(N_CSTATE)
        self.R: np.ndarray = np.zeros(L.N_RSTATE)
        self.cout: np.ndarray = np.zeros(N_CONTROL_FIELDS)
        self.eout: np.ndarray = np.zeros(L.N_EXP_FIELDS)
        self.experiment_id: int = -1
        self._exp_gains: Gains = self.gains
        self.R[L.R_SEEN] = -1.0  # no state seen yet
        self.R[L.R_APPLIED] = -1.0
        self.reset(0.0)

    # -- modes
    def reset(self, theta_meas: float) -> None:
        """Hold ``theta_meas`` [rad] (references = theta_meas, integrator 0); clears FAULT
        and any running experiment (without a result)."""
        if not math.isfinite(theta_meas):
            raise ValueError(f'theta_meas must be finite, got {theta_meas!r}')
        control_reset(self.X, float(theta_meas))
        # the drive-timeline facts survive a reset: they describe the drive, not the runner
        seen, applied, gstep = self.R[L.R_SEEN], self.R[L.R_APPLIED], self.R[L.R_GAINS_STEP]
        self.R[:] = 0.0
        self.R[L.R_SEEN], self.R[L.R_APPLIED], self.R[L.R_GAINS_STEP] = seen, applied, gstep
        self.R[L.R_MODE] = L.MODE_HOLD
        self.R[L.R_HOLD_REF] = float(theta_meas)
        self.R[L.R_TARGET] = float(theta_meas)
        self.R[L.R_LAST_STEP] = -1.0
        self.R[L.R_TRIP_STEP] = -1.0

    def set_gains(self, gains: Gains) -> None:
        """Apply new gains now (validated, atomic).  Refused while an experiment runs."""
        g = validate_gains(gains)
        if self.running:
            raise RuntimeError('cannot change gains while an experiment is running')
        fill_control_params(self.C, g, self.config.control)
        self.gains = g
        self.R[L.R_GAINS_STEP] = self.R[L.R_SEEN] + 1.0  # they act from the next state on

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
        fill_control_params(self.CF, cfg.fallback_gains, cfg.control)
        self.config = cfg

    def abort_external(self, reason: int, time_ns: int) -> None:
        """Torque off from outside (e.g. the drive-state watchdog): FAULT with ``reason``
        (a ``REASON_*`` code); a running experiment ends aborted (penalised) at sim time
        ``time_ns`` [ns] of the last state seen.  ``reset()`` clears the fault."""
        R = self.R
        if R[L.R_MODE] == L.MODE_SETTLE:  # before its step 0: no step measured
            R[L.R_N] = 0.0
            R[L.R_START_NS] = float(time_ns)
        if self.running:
            finish_experiment(R, self.Q, float(L.STATUS_ABORTED), float(reason), float(time_ns))
        R[L.R_MODE] = L.MODE_FAULT
        R[L.R_FAULT_REASON] = float(reason)

    def start(self, experiment_id: int, gains: Gains | None = None) -> None:
        """Arm experiment ``experiment_id`` (int >= 0) with ``gains`` (None: current): the
        next ``step`` begins its standstill settle (fallback gains, no load, no loss), then
        step 0 moves by +distance (even id) or -distance (odd id) with ``gains``."""
        if (
            isinstance(experiment_id, bool)
            or not isinstance(experiment_id, (int, np.integer))
            or experiment_id < 0
        ):
            raise ValueError(f'experiment_id must be an integer >= 0, got {experiment_id!r}')
        if self.R[L.R_MODE] == L.MODE_FAULT:
            raise RuntimeError(f'runner in FAULT ({self.fault_reason}); call reset() first')
        if self.running:
            raise RuntimeError('an experiment is already running')
        if not self.ready:
            raise RuntimeError('still finishing the stopped move; wait until ready')
        if gains is not None:
            self.set_gains(gains)
        R = self.R
        d = 1.0 if experiment_id % 2 == 0 else -1.0
        R[L.R_DIR] = d
        R[L.R_THETA0] = R[L.R_HOLD_REF]
        R[L.R_TARGET] = R[L.R_THETA0] + d * self.Q[L.Q_DIST]
        R[L.R_N] = 0.0
        for j in L.R_CLEARED_AT_START:
            R[j] = 0.0
        R[L.R_TRIP_STEP] = -1.0
        R[L.R_FRESH] = R[L.R_LATE] = R[L.R_HELD] = 0.0
        # the kernel counts the settle's periods on the drive's timeline
        R[L.R_START_STEP] = -1.0
        R[L.R_MODE] = L.MODE_SETTLE if self.Q[L.Q_SETTLE_N] > 0 else L.MODE_RUN
        self.experiment_id = int(experiment_id)
        self._exp_gains = self.gains

    def step(self, state: np.ndarray) -> tuple[float, float, int]:
        """One drive state (float64 array, the contract's ``STATE_FIELDS``) -> (isq* [A],
        load torque command [N m], status). Another length is a ValueError."""
        if state.size != L.N_STATE_FIELDS:  # (an int: nothing made per state)
            raise ValueError(f'a drive state has {L.N_STATE_FIELDS} values, got {state.shape}')
        st = experiment_step(self.R, self.Q, self.X, self.C, self.CF, state, self.cout, self.eout)
        self.stepped(st)
        return float(self.eout[L.E_ISQ]), float(self.eout[L.E_LOAD]), int(st)

    def stepped(self, status: int) -> None:
        """What follows a kernel step that returned ``status``: a supervisor stop (term1-3)
        left the kernel on the fallback gains."""
        if status == L.STATUS_ABORTED and self.R[L.R_REASON] < L.REASON_POSITION:
            self.gains = self.config.fallback_gains  # the kernel switched to them

    # -- queries
    @property
    def running(self) -> bool:
        """An experiment is under way (its settle or its measured steps)."""
        return bool(self.R[L.R_MODE] == L.MODE_RUN or self.R[L.R_MODE] == L.MODE_SETTLE)

    @property
    def ready(self) -> bool:
        """True in plain position hold: ``start`` may be called."""
        return bool(self.R[L.R_MODE] == L.MODE_HOLD)

    @property
    def faulted(self) -> bool:
        return bool(self.R[L.R_MODE] == L.MODE_FAULT)

    @property
    def fault_reason(self) -> str:
        return L.REASONS[int(self.R[L.R_FAULT_REASON])] if self.faulted else ''

    @property
    def target(self) -> float:
        """End position [rad] of the current / last experiment."""
        return float(self.R[L.R_TARGET])

    def result(self, R: np.ndarray | None = None) -> LossResult | None:
        """The result of the last experiment, or None while running / before any (``R``:
        the kernel's words at an experiment's end, which a compiled loop has run past)."""
        R = self.R if R is None else R
        if R[L.R_RESULT] == 0.0 or R[L.R_MODE] == L.MODE_RUN or R[L.R_MODE] == L.MODE_SETTLE:
            return None
        aborted = R[L.R_RESULT] == L.STATUS_ABORTED
        terms = (float(R[L.R_TERM1]), float(R[L.R_TERM2]), float(R[L.R_TERM3]))
        loss = terms[0] + terms[1] + terms[2]
        if aborted:
            loss *= self.config.loss.penalty
        trip = int(R[L.R_TRIP_STEP])
        held, late = int(R[L.R_HELD]), int(R[L.R_LATE])
        return LossResult(
            experiment_id=self.experiment_id,
            loss=float(loss),
            terms=terms,
            aborted=bool(aborted),
            reason=L.REASONS[int(R[L.R_REASON])],
            trip_step=trip,
            trip_time=trip * self.config.control.Ts if trip >= 0 else -1.0,
            gains=self._exp_gains,
            t_start=int(R[L.R_START_NS]),
            t_end=int(R[L.R_END_NS]),
            steps=int(R[L.R_STEPS]),
            direction=int(R[L.R_DIR]),
            fresh=int(R[L.R_FRESH]),
            held=held,
            late=late,
            timing=held + late > self.timing_tolerance,
            gains_step=int(R[L.R_GAINS_STEP]),
            ripple=ripple_of(R),
            motion=motion_of(R),
        )


def ripple_of(R: np.ndarray) -> tuple[float, float, float, float]:
    """(rms [A], peak-to-peak [A]) of isq* in each standstill window from the kernel's
    sums (``layout.R_RIP``); nan for a window without samples."""
    out: list[float] = []
    for w in range(2):
        n, s1, s2, lo, hi = (float(v) for v in R[L.R_RIP + 5 * w : L.R_RIP + 5 * w + 5])
        if n < 1.0:
            out += [math.nan, math.nan]
            continue
        mean = s1 / n
        out += [math.sqrt(max(0.0, s2 / n - mean * mean)), hi - lo]
    return (out[0], out[1], out[2], out[3])


def motion_of(R: np.ndarray) -> tuple[float, ...]:
    """The motion sums as ``LossResult.motion``: rows, then the 15 sums z_i z_j."""
    return (float(R[L.R_ID_ROWS]), *(float(v) for v in R[L.R_ID_M : L.R_ID_M + 15]))


def config_for_drive(cfg: ExperimentConfig | None, sim: DriveSim) -> ExperimentConfig:
    """``cfg`` with Ts and isq_max taken from the drive (they are drive properties)."""
    cfg = ExperimentConfig() if cfg is None else cfg
    ctl = dataclasses.replace(
        cfg.control, Ts=float(sim.config.Ts), isq_max=float(sim.config.machine.isq_max)
    )
    return validate_experiment_config(dataclasses.replace(cfg, control=ctl))
