"""Every optimiser's name, default, start handling and options, without importing any.

The single source of the command-line flags (``OPTIONS[algo][name]``: type, default, help,
range or choices) and of the constructors' checks (each class's ``OPTIONS`` is its entry
here).  Pure: numpy and :mod:`.base` only.  An algorithm's own module -- and pycma
(cmaes), optuna (tpe), scipy (rcga) with it -- is imported only when one is built
(:func:`algorithm_class`, from ``make_optimizer`` and ``Optimizer.from_state``), so a
tool that only parses its command line (the tuner refusing bad input) stays fast.
"""

from __future__ import annotations

import importlib
import math
from typing import TYPE_CHECKING

from .base import OptionSpec

if TYPE_CHECKING:
    from .base import Optimizer

__all__ = [
    'ALGOS',
    'DEFAULT_ALGO',
    'GAIN_PRESETS',
    'MODULES',
    'NO_START_ALGOS',
    'OPTIONS',
    'TAKES_START',
    'algorithm_class',
]

#: Every algorithm name accepted by make_optimizer (and ``--algo``).
ALGOS: tuple[str, ...] = ('spsa', 'necga', 'cga', 'pecga', 'rcga', 'cmaes', 'tpe', 'safe')
#: the tuner's optimiser when none is named: the fewest experiments and aborted ones from
#: a hand-tuned start (issue 19; docs/tuner.md, "Which algorithm")
DEFAULT_ALGO = 'safe'
#: algo -> (module of this package, class): imported by :func:`algorithm_class` only
MODULES: dict[str, tuple[str, str]] = {
    'spsa': ('spsa', 'SPSA'),
    'necga': ('cga', 'NECGA'),
    'cga': ('cga', 'CGA'),
    'pecga': ('cga', 'PECGA'),
    'rcga': ('rcga', 'RCGA'),
    'cmaes': ('cmaes', 'CMAES'),
    'tpe': ('tpe', 'TPE'),
    'safe': ('safe', 'SAFE'),
}
#: algorithms that use ``start`` (the compact GAs start from their distribution): SPSA's
#: iterate, CMA-ES's mean, TPE's first (enqueued) trial, safe's first incumbent.
TAKES_START: frozenset[str] = frozenset({'spsa', 'cmaes', 'tpe', 'safe'})
#: algorithms the tuner runs without the start point (``--no-start``): SPSA and CMA-ES
#: from a uniform random point, TPE with random trials first.  Not safe: a local search
#: around gains known to be stable, whose first experiment would be an untested random
#: controller; not the compact GAs, which take no start at all.
NO_START_ALGOS: frozenset[str] = frozenset({'spsa', 'cmaes', 'tpe'})

#: (alpha, gamma) of each of SPSA's ``gains`` presets.
GAIN_PRESETS: dict[str, tuple[float, float]] = {'paper': (0.3, 0.3), 'spall': (0.602, 0.101)}

#: spsa (optim/spsa.py)
SPSA_OPTIONS: dict[str, OptionSpec] = {
    'a': OptionSpec(
        float,
        0.0183,
        'step gain a of a_k = a/(k+1+A)^alpha (normalised units per unit of loss gradient)',
        low=0.0,
        high=math.inf,
        low_strict=True,
        high_strict=True,
    ),
    'c': OptionSpec(
        float,
        0.03,
        'perturbation size c of c_k = c/(k+1)^gamma '
        '(normalised units, fraction of each parameter range)',
        low=0.0,
        high=0.5,
        low_strict=True,
        high_strict=True,
    ),
    'A': OptionSpec(
        float,
        20.0,
        'stability constant A of a_k (iterations; ~10% of the expected iterations)',
        low=0.0,
        high=math.inf,
        high_strict=True,
    ),
    'alpha': OptionSpec(
        float,
        None,
        "decay exponent of a_k (default: 0.3 with gains='paper', 0.602 with gains='spall')",
        low=0.0,
        high=1.0,
        low_strict=True,
    ),
    'gamma': OptionSpec(
        float,
        None,
        "decay exponent of c_k (default: 0.3 with gains='paper', 0.101 with gains='spall')",
        low=0.0,
        high=1.0,
    ),
    'gains': OptionSpec(
        str,
        'paper',
        "alpha/gamma preset: 'paper' (0.3/0.3) or 'spall' (0.602/0.101)",
        choices=tuple(GAIN_PRESETS),
    ),
    'max_step': OptionSpec(
        float,
        0.1,
        'largest change of any normalised parameter in '
        'one iteration (the step vector is scaled down to it); '
        'inf disables the cap',
        low=0.0,
        high=math.inf,
        low_strict=True,
    ),
}

#: the binary compact GAs cga and pecga (optim/cga.py)
CGA_OPTIONS: dict[str, OptionSpec] = {
    'n': OptionSpec(
        int,
        25,
        'virtual population size n: each competition moves a probability by 1/n',
        low=2,
        high=1_000_000,
    ),
    'bits': OptionSpec(
        int,
        16,
        'bits per parameter (resolution 1/(2^bits - 1) of the normalised range)',
        low=1,
        high=32,
    ),
    'coding': OptionSpec(
        str,
        'binary',
        "gene coding: 'binary' (plain, most significant bit first) or 'gray' (reflected Gray code)",
        choices=('binary', 'gray'),
    ),
}

#: necga: the compact GAs' options and its own
NECGA_OPTIONS: dict[str, OptionSpec] = {
    **CGA_OPTIONS,
    'eta': OptionSpec(
        int,
        12,
        'allowed length of inheritance eta: after eta '
        'consecutive wins the elite is replaced (must be < n)',
        low=1,
        high=1_000_000,
    ),
    'elite_replacement': OptionSpec(
        str,
        'sample',
        "what replaces an elite that won eta times in a row: 'sample' "
        "(a fresh PV sample, one extra evaluation; the paper's Fig. 3) or 'newcomer' "
        "(the newcomer just evaluated; the authors' Java code)",
        choices=('sample', 'newcomer'),
    ),
}

#: rcga (optim/rcga.py)
RCGA_OPTIONS: dict[str, OptionSpec] = {
    'n': OptionSpec(
        int,
        25,
        'virtual population size n: a competition moves mu by (w - l)/n',
        low=2,
        high=1_000_000,
    ),
    'elitism': OptionSpec(
        str,
        'ne',
        "'ne' (elite replaced by the newcomer after eta "
        "consecutive wins) or 'pe' (persistent elite)",
        choices=('ne', 'pe'),
    ),
    'eta': OptionSpec(
        int,
        12,
        "allowed length of inheritance with elitism='ne' (consecutive elite wins; must be < n)",
        low=1,
        high=1_000_000,
    ),
    'sigma0': OptionSpec(
        float,
        10.0,
        'initial spread of every variable on x in '
        '[-1, 1] (10: nearly uniform; 0.577: a uniform population)',
        low=0.0,
        high=1e6,
        low_strict=True,
    ),
}

#: cmaes (optim/cmaes.py)
CMAES_OPTIONS: dict[str, OptionSpec] = {
    'sigma0': OptionSpec(
        float,
        0.1,
        'initial step size sigma0 (normalised units: a fraction of each parameter range)',
        low=0.0,
        high=1.0,
        low_strict=True,
    ),
    'popsize': OptionSpec(
        int,
        None,
        "population size lambda per generation (default: pycma's 4 + floor(3 ln dim), "
        '8 for 5 gains)',
        low=2,
        high=10_000,
    ),
}

#: tpe (optim/tpe.py)
TPE_OPTIONS: dict[str, OptionSpec] = {
    'n_startup_trials': OptionSpec(
        int,
        10,
        'evaluations sampled at random before TPE models the losses (the start counts)',
        low=0,
        high=1_000_000,
    ),
    'n_ei_candidates': OptionSpec(
        int,
        24,
        'candidates drawn from the good-loss density per ask; the best l(x)/g(x) is asked',
        low=1,
        high=1_000_000,
    ),
    'multivariate': OptionSpec(
        str,
        'yes',
        "'yes': one joint Parzen density over the gains (optuna 5's default); 'no': one per gain",
        choices=('yes', 'no'),
    ),
}

#: safe (optim/safe.py)
SAFE_OPTIONS: dict[str, OptionSpec] = {
    'sigma0': OptionSpec(
        float, 0.05, 'initial step size (normalised units)', low=0.0, high=1.0, low_strict=True
    ),
    'grow': OptionSpec(
        float, 1.5, 'step-size factor after a success', low=1.0, high=10.0, low_strict=True
    ),
    'abort_shrink': OptionSpec(
        float,
        0.3,
        'step-size factor after an aborted experiment',
        low=0.0,
        high=1.0,
        low_strict=True,
    ),
    'sigma_max': OptionSpec(
        float,
        0.08,
        'largest step size (normalised units): the trust region around the incumbent',
        low=0.005,
        high=1.0,
    ),
    'remeasure_every': OptionSpec(
        int,
        10,
        'measure the incumbent again every this many evaluations (0: never)',
        low=0,
        high=1_000_000,
    ),
    'model_every': OptionSpec(
        int,
        2,
        'take a descent step on the local linear model every this many evaluations '
        '(0: never, a plain (1+1)-ES)',
        low=0,
        high=1_000_000,
    ),
}

#: algo -> option name -> OptionSpec (names are python identifiers, usable as flags).
OPTIONS: dict[str, dict[str, OptionSpec]] = {
    'spsa': dict(SPSA_OPTIONS),
    'necga': dict(NECGA_OPTIONS),
    'cga': dict(CGA_OPTIONS),
    'pecga': dict(CGA_OPTIONS),
    'rcga': dict(RCGA_OPTIONS),
    'cmaes': dict(CMAES_OPTIONS),
    'tpe': dict(TPE_OPTIONS),
    'safe': dict(SAFE_OPTIONS),
}


def algorithm_class(algo: str) -> type[Optimizer]:
    """The class of ``algo`` (one of ``ALGOS``), its module imported now if it was not."""
    module, name = MODULES[algo]
    cls: type[Optimizer] = getattr(importlib.import_module(f'{__package__}.{module}'), name)
    return cls
