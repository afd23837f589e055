"""The outcome of one experiment (:class:`LossResult`) and its description
(:class:`Experiment`: direction, target, reference signals)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import ExperimentConfig, Gains, validate_experiment_config
from .layout import Q_LOAD_N


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
    steps: drive periods run (counted by the drive's step_index); direction: +1 / -1.
    fresh, held, late: of those periods (the one ending at each state the loss integrates),
        how many were driven by the answer to the state before (fresh), by a new command
        answering an older state (late), or by an older command held (held; also a state
        the controller never answered). fresh + held + late = steps.
    timing: held + late exceeded the controller's ``timing_tolerance``: the experiment did
        not run on the paper's timing and its loss is not a measurement of the paper's
        loss (the tuner re-runs it instead of reporting it).
    gains_step: the drive step of the first state the experiment's gains acted on (they
        were set while the controller held the position, or at the start): with t_start
        and the seeds, what a lock-step replay of a real-time plant history needs.
    ripple: the standstill ripple of isq* (rms about its mean [A], peak-to-peak [A]) in
        the window after the move and in the window after the load step (layout
        ``Q_RIP*``: 0.300-0.700 s and 0.900-1.125 s of the paper's experiment); nan where
        the experiment did not reach or fill the window.
    motion: the motion sums of the experiment (``layout.N_MOTION`` values: the number of
        rows, then sum z_i z_j for i <= j over ``layout.MOTION_COLUMNS``), from which
        ``im_tuner.identify`` estimates J, Kt, B and Tc; () where not measured.
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
    fresh: int = 0
    held: int = 0
    late: int = 0
    timing: bool = False
    gains_step: int = 0
    ripple: tuple[float, float, float, float] = (math.nan, math.nan, math.nan, math.nan)
    motion: tuple[float, ...] = ()


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
        from .trajectory import make_experiment_params, trajectory  # numba: when used

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
