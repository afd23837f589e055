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
    """Outcome of one experiment; its fields: docs/controller.md, section 6 (``loss`` is
    the sum of ``terms``, times ``penalty`` if aborted; ``motion`` is () where not
    measured)."""

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
