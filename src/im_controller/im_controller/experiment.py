"""The loss experiment of the paper: trajectory, load step, online loss, supervisor.

One experiment (paper, "The loss function"; docs/controller.md, sections 3-5): a
minimum-time move of ``distance`` from the hold reference (+ for even ids, - for odd), a
load step ``load_delay`` after it starts, the loss of eq. 4-7 counted online, a supervisor
that stops the experiment (penalised) once a weighted term passes its threshold and hands
over to the fallback gains, and hard safety limits that put the runner in FAULT.

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
