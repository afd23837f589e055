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

Modules, by job: ``layout`` (the kernel's array layouts, status and reason codes),
``trajectory`` (the move and the parameter vector Q), ``kernel`` (:func:`experiment_step`,
what the node calls once per received state), ``result`` (:class:`LossResult`,
:class:`Experiment`) and ``runner`` (:class:`ExperimentRunner`, the node's core). This
module gathers their public names. The same kernel fused with the drive kernels in one
numba loop -- the oracle of the ROS tests and the engine of offline studies -- is a bench:
``im_tuner.offline``.
"""

from __future__ import annotations

from .kernel import experiment_step
from .layout import (
    EXP_FIELDS,
    INTERNALS_FIELDS,
    LINK_REASONS,
    REASON_DRIVE_TIMEOUT,
    REASON_TUNER_LOST,
    REASONS,
    SAFETY_REASONS,
    STATUS_ABORTED,
    STATUS_DONE,
    STATUS_FAULT,
    STATUS_HOLD,
    STATUS_NAMES,
    STATUS_RUNNING,
)
from .result import Experiment, LossResult
from .runner import ExperimentRunner, config_for_drive
from .trajectory import make_experiment_params, trajectory, trajectory_times

__all__ = [
    'EXP_FIELDS',
    'INTERNALS_FIELDS',
    'LINK_REASONS',
    'REASONS',
    'REASON_DRIVE_TIMEOUT',
    'REASON_TUNER_LOST',
    'SAFETY_REASONS',
    'STATUS_ABORTED',
    'STATUS_DONE',
    'STATUS_FAULT',
    'STATUS_HOLD',
    'STATUS_NAMES',
    'STATUS_RUNNING',
    'Experiment',
    'ExperimentRunner',
    'LossResult',
    'config_for_drive',
    'experiment_step',
    'make_experiment_params',
    'trajectory',
    'trajectory_times',
]
