"""``safe``'s first step from the identified drive (the tuner's ``--opt first=identify``).

After the start's two measurements (opposite directions) the tuning loop calls
:class:`IdentifiedFirstStep` with the records: the drive identified from their motion
sums (``identify``), the first step of its model (``prior.identified_prior``) or None.
Deterministic in the records, so a resumed run asks the same point.  Pure.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from im_controller.config import ExperimentConfig
from im_drive_sim.params import DriveConfig

from .identify import Identified, identify, same_gains, start_motions
from .prior import RIPPLE_MARGIN, SCREEN_J, AbortScreen, Prior, identified_prior
from .space import SearchSpace


class IdentifiedFirstStep:
    """The hook ``TuningRun(first_step=...)`` calls before safe's evaluation 2."""

    def __init__(
        self,
        drive: DriveConfig,
        space: SearchSpace,
        experiment: ExperimentConfig | None,
        say: Callable[[str], None] | None = None,
        ripple_limit: float | None = None,
    ) -> None:
        """``say``: where to print what was identified and the step taken (None: nothing);
        ``ripple_limit``: the run's (None: off), which the step keeps on the models."""
        self.drive, self.space, self.experiment = drive, space, experiment
        self._say = say or (lambda _text: None)
        self.ripple_limit = ripple_limit
        self.prior: Prior | None = None  #: the last point's prior (None: none)
        self._screen: AbortScreen | None = None
        self._screen_tried = False

    def identified(self, records: list[Any]) -> Identified | None:
        """The drive identified from the start's experiments among ``records``."""
        return identify(start_motions(records), self.drive.machine)

    def screen(self, records: list[Any]) -> AbortScreen | None:
        """The abort screen (``prior.AbortScreen``) of the drive identified from the
        records before the search left the start: the first step's identification, on
        resume too (None: not identified)."""
        if not self._screen_tried:
            self._screen_tried = True
            idf = self.identified(_before_search(records))
            if idf is not None:
                self._screen = AbortScreen(self.drive, self.space, self.experiment, idf)
                js = ' and '.join(f'{j:g} J' for j in SCREEN_J)
                self._say(
                    'abort screen: each candidate runs first on the identified model (at '
                    f'{js}); one that aborts there is not run on the drive'
                )
        return self._screen

    def __call__(self, records: list[Any]) -> list[float] | None:
        idf = self.identified(records)
        if idf is None:
            self.prior = None
            self._say("identification: too few rows in the start's experiments; no first step")
            return None
        self._say(f'identified from the start: {idf.line()}')
        self.prior = identified_prior(
            self.drive, self.space, self.experiment, idf, self.ripple_limit
        )
        if self.prior is None:
            within = '' if self.ripple_limit is None else ' within the ripple limit'
            self._say(
                'first step: none (the identified model finds nothing better than the start'
                f'{within})'
            )
            return None
        p = self.prior
        quiet = (
            ''
            if p.ripple_ratio is None
            else f"; its standstill rms predicted {p.ripple_ratio:.2f}x the start's, within "
            f'the ripple limit {self.ripple_limit:g} by {RIPPLE_MARGIN:.0%}'
        )
        self._say(
            f"first step: the identified model's best point (its loss {p.model_ratio:.2f}x the "
            f"start's on the model, at most {p.worst_ratio:.2f}x over J and Rr errors{quiet}; "
            f'{p.experiments} offline experiments, {p.seconds:.1f} s)'
        )
        return list(p.u)


def _before_search(records: list[Any]) -> list[Any]:
    """``records`` up to the first evaluation whose gains are not the reference's."""
    ref = next((r for r in records if r.kind == 'reference'), None)
    if ref is None:
        return []
    out = []
    for r in records:
        if r.kind == 'eval' and not same_gains(r.gains, ref.gains):
            break
        out.append(r)
    return out
