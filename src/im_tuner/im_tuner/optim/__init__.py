"""Optimiser core of the tuner (no rclpy): SPSA, safe and the compact-GA family (numpy),
rcGA (scipy), CMA-ES (pycma) and TPE (optuna); docs/optimisers.md.

    opt = make_optimizer('necga', dim=5, seed=1, n=25, eta=12)
    while opt.evaluations < 200:
        u = opt.ask()                  # normalised parameters in [0, 1]^5
        opt.tell(u, measure(u))        # the loss of one experiment

Importing this package imports no algorithm: each module (with pycma, optuna or scipy)
is imported when one is built or restored, so a command line is refused at once.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

import numpy as np

from .base import Optimizer as Optimizer, algorithm_class as algorithm_class
from .checks import (
    OptimizerError as OptimizerError,
    OptionSpec as OptionSpec,
    check_dim,
    check_options,
    check_seed,
    check_start,
)
from .options import (
    ALGORITHMS as ALGORITHMS,
    ALGOS as ALGOS,
    DEFAULT_ALGO as DEFAULT_ALGO,
    NO_START_ALGOS as NO_START_ALGOS,
    OPTIONS as OPTIONS,
    POLICIES as POLICIES,
    RIPPLE_LIMITED as RIPPLE_LIMITED,
    TAKES_FIRST as TAKES_FIRST,
    TAKES_START as TAKES_START,
    Algorithm as Algorithm,
    describe_options as describe_options,
    option_specs as option_specs,
    read_options as read_options,
    split_policies as split_policies,
)

if TYPE_CHECKING:  # the classes are loaded on first use (module __getattr__ below)
    from .cga import CGA as CGA, NECGA as NECGA, PECGA as PECGA, BinaryCGA as BinaryCGA
    from .cmaes import CMAES as CMAES
    from .rcga import RCGA as RCGA
    from .safe import SAFE as SAFE
    from .spsa import SPSA as SPSA
    from .tpe import TPE as TPE


#: class name -> its module (``from im_tuner.optim import CMAES`` imports pycma then)
_CLASS_MODULES = {d.cls: d.module for d in ALGORITHMS.values()} | {'BinaryCGA': 'cga'}


def __getattr__(name: str) -> Any:
    """The optimiser classes, each module imported on first use (PEP 562): importing
    this package costs numpy only, not pycma, optuna or scipy."""
    module = _CLASS_MODULES.get(name)
    if module is None:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    return getattr(importlib.import_module(f'{__name__}.{module}'), name)


def make_optimizer(
    algo: str,
    dim: int,
    seed: int | np.random.SeedSequence,
    start: np.ndarray | None = None,
    *,
    first: Any = None,
    **options: Any,
) -> Optimizer:
    """Validate everything, then build the optimiser ``algo`` on ``dim`` parameters.

    ``seed``: int >= 0 or SeedSequence.  ``start``: a point of [0, 1]^dim
    (``TAKES_START`` only; None: a random start).  ``first``: ``TAKES_FIRST`` only, a
    model's point measured right after the start, or 'identify' (given later,
    ``Optimizer.set_first``).  ``options``: ``OPTIONS[algo]``, unset ones at their
    defaults.  Any problem: OptimizerError (one line), before anything is created (and
    before the algorithm's library is imported).
    """
    if not isinstance(algo, str) or algo not in OPTIONS:
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
    if first is not None:
        if algo not in TAKES_FIRST:
            raise OptimizerError(
                f'{algo} does not take a first point (only {", ".join(sorted(TAKES_FIRST))} does)'
            )
        options = {**options, 'first': first}
    # The constructors repeat these checks and add the cross-option ones (eta < n) before
    # they create anything.
    return algorithm_class(algo)(dim, seed, start, **options)
