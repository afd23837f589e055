"""The outcome of one experiment (:class:`LossResult`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from .config import Gains


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
