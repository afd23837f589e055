"""``safe``'s first step from the identified drive (the tuner's ``--first identify``).

After the start's two measurements (the reference and evaluation 1, opposite directions)
the tuner calls :class:`IdentifiedFirstStep` with the run's records: it identifies J, Kt,
B and Tc from their motion sums (``im_tuner.identify``), builds the drive file's model
with them and returns that model's first step (``im_tuner.prior.identified_prior``), or
None (too few rows, or the model finds nothing better than the start).  Deterministic
in the records: a resumed run that rebuilds its optimiser from results.jsonl asks the
same point.  Pure: no rclpy.
"""

from __future__ import annotations

from typing import Any

from im_controller.config import ExperimentConfig
from im_drive_sim.params import DriveConfig

from .identify import Identified, identify, start_motions
from .prior import Prior, identified_prior
from .space import SearchSpace

__all__ = ['IdentifiedFirstStep']


class IdentifiedFirstStep:
    """The hook ``TuningRun(first_step=...)`` calls before safe's evaluation 2."""

    def __init__(
        self, drive: DriveConfig, space: SearchSpace, experiment: ExperimentConfig | None
    ) -> None:
        self.drive, self.space, self.experiment = drive, space, experiment
        self.prior: Prior | None = None  #: the last point's prior (None: none)

    def identified(self, records: list[Any]) -> Identified | None:
        """The drive identified from the start's experiments among ``records``."""
        return identify(start_motions(records), self.drive.machine)

    def __call__(self, records: list[Any]) -> list[float] | None:
        idf = self.identified(records)
        if idf is None:
            self.prior = None
            return None
        self.prior = identified_prior(self.drive, self.space, self.experiment, idf)
        return None if self.prior is None else list(self.prior.u)
