"""Optimiser core of the tuner (no rclpy): SPSA and the compact-GA family (numpy), CMA-ES
(pycma) and TPE (optuna).

    from im_tuner.optim import make_optimizer, OPTIONS, ALGOS
    opt = make_optimizer('necga', dim=5, seed=1, n=25, eta=12)
    while opt.evaluations < 200:
        u = opt.ask()                  # normalised parameters in [0, 1]^5
        opt.tell(u, measure(u))        # the loss of one experiment

``OPTIONS[algo][name]`` is an :class:`OptionSpec` (type, default, help, accepted range or
choices), the single source for command-line flags.  The contract of every optimiser
(ask/tell, state_dict/from_state, evaluations, converged, config) is in ``base.py``;
the algorithms, the options and the decisions taken are in docs/optimisers.md.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .base import (
    Optimizer,
    OptimizerError,
    OptionSpec,
    check_dim,
    check_options,
    check_seed,
    check_start,
)
from .cga import CGA, NECGA, PECGA, BinaryCGA
from .cmaes import CMAES
from .rcga import RCGA
from .safe import SAFE
from .spsa import SPSA
from .tpe import TPE

__all__ = [
    'ALGOS',
    'CGA',
    'CLASSES',
    'CMAES',
    'DEFAULT_ALGO',
    'NECGA',
    'OPTIONS',
    'PECGA',
    'RCGA',
    'SAFE',
    'SPSA',
    'TAKES_START',
    'TPE',
    'BinaryCGA',
    'Optimizer',
    'OptimizerError',
    'OptionSpec',
    'make_optimizer',
]

#: Every algorithm name accepted by make_optimizer (and ``--algo``).
ALGOS: tuple[str, ...] = ('spsa', 'necga', 'cga', 'pecga', 'rcga', 'cmaes', 'tpe', 'safe')
#: the tuner's optimiser when none is named: the fewest experiments and aborted ones from
#: a hand-tuned start (issue 19; docs/tuner.md, "Which algorithm")
DEFAULT_ALGO = 'safe'

CLASSES: dict[str, type[Optimizer]] = {
    'spsa': SPSA,
    'necga': NECGA,
    'cga': CGA,
    'pecga': PECGA,
    'rcga': RCGA,
    'cmaes': CMAES,
    'tpe': TPE,
    'safe': SAFE,
}

#: algo -> option name -> OptionSpec (names are python identifiers, usable as flags).
OPTIONS: dict[str, dict[str, OptionSpec]] = {a: dict(CLASSES[a].OPTIONS) for a in ALGOS}

#: algorithms that use ``start`` (the compact GAs start from their distribution): SPSA's
#: iterate, CMA-ES's mean, TPE's first (enqueued) trial.
TAKES_START: frozenset[str] = frozenset({'spsa', 'cmaes', 'tpe', 'safe'})


def make_optimizer(
    algo: str,
    dim: int,
    seed: int | np.random.SeedSequence,
    start: np.ndarray | None = None,
    **options: Any,
) -> Optimizer:
    """Validate everything, then build the optimiser ``algo`` on ``dim`` parameters.

    ``seed``: int >= 0 or SeedSequence (the optimiser's own PCG64 stream).  ``start``:
    normalised start point in [0, 1]^dim (``TAKES_START`` only; None = spsa and cmaes
    draw a uniform random start, tpe starts with random trials).
    ``options``: see ``OPTIONS[algo]``; unset ones take their defaults.  Any problem
    (unknown algo or option, wrong type, bool for a number, out of range, eta >= n, a
    start for a compact GA...) raises OptimizerError with a one-line message naming it
    and the accepted values, before anything is created.
    """
    if not isinstance(algo, str) or algo not in CLASSES:
        raise OptimizerError(f'unknown algo {algo!r} (allowed: {", ".join(ALGOS)})')
    dim = check_dim(dim)
    check_seed(seed)
    check_start(start, dim)
    if start is not None and algo not in TAKES_START:
        raise OptimizerError(
            f'{algo} does not take a start point (only '
            f'{", ".join(sorted(TAKES_START))} does); pass start=None'
        )
    check_options(algo, OPTIONS[algo], options)
    # The constructors repeat these checks and add the cross-option ones (eta < n) before
    # they create anything.
    return CLASSES[algo](dim, seed, start, **options)
