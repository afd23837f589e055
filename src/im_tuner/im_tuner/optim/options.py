"""Every optimiser's name, default, start handling and options, without importing any.

The single source of ``--opt``: an algorithm's hyperparameters (``OPTIONS[algo][name]``;
each class's ``OPTIONS`` is its entry here) and the run's policies it takes
(``POLICIES[algo][name]``: the tuning run's, never a constructor's).  Pure: no
algorithm's module is imported here (docs/optimisers.md, "How the code is cut").
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

from .checks import OptimizerError, OptionSpec, check_options


@dataclass(frozen=True)
class Algorithm:
    """What the tuning loop, the tuner's checks and the study read of an algorithm, declared
    once: its module and class, whether it uses a start point (whether it may run without
    one: its ``start`` policy), whether its runs keep the ripple limit by default."""

    module: str
    cls: str
    takes_start: bool = False
    ripple_limited: bool = False


#: Every algorithm accepted by make_optimizer (and ``--algo``); ``ALGOS``: their names.
ALGORITHMS: dict[str, Algorithm] = {
    'spsa': Algorithm('spsa', 'SPSA', takes_start=True),
    'necga': Algorithm('cga', 'NECGA'),
    'cga': Algorithm('cga', 'CGA'),
    'pecga': Algorithm('cga', 'PECGA'),
    'rcga': Algorithm('rcga', 'RCGA'),
    'cmaes': Algorithm('cmaes', 'CMAES', takes_start=True),
    'tpe': Algorithm('tpe', 'TPE', takes_start=True),
    'safe': Algorithm('safe', 'SAFE', takes_start=True, ripple_limited=True),
}
ALGOS: tuple[str, ...] = tuple(ALGORITHMS)
#: the tuner's optimiser when none is named: the fewest experiments and aborted ones from
#: a hand-tuned start (docs/tuner.md, "Which algorithm")
DEFAULT_ALGO = 'safe'
TAKES_START: frozenset[str] = frozenset(a for a, d in ALGORITHMS.items() if d.takes_start)
RIPPLE_LIMITED: frozenset[str] = frozenset(a for a, d in ALGORITHMS.items() if d.ripple_limited)

#: (alpha, gamma) of each of SPSA's ``gains`` presets.
GAIN_PRESETS: dict[str, tuple[float, float]] = {'paper': (0.3, 0.3), 'spall': (0.602, 0.101)}


def _spec(kind: type, default: Any, interval: str, text: str) -> OptionSpec:
    """A numeric option accepting ``interval``, written as in mathematics: '(0, 0.5)',
    '[2, 1000000]', '(0, inf]' (a round bracket excludes its bound; 'inf' included
    means +inf is accepted)."""
    lo, hi = (b.strip() for b in interval[1:-1].split(','))
    return OptionSpec(
        kind,
        default,
        text,
        low=kind(lo),
        high=kind(hi),
        low_strict=interval[0] == '(',
        high_strict=interval[-1] == ')',
    )


#: a float / an int option: ``real(default, interval, text)`` (default None: derived from
#: other options, ``text`` says how)
real = functools.partial(_spec, float)
integer = functools.partial(_spec, int)


def choice(default: str | None, choices: tuple[str, ...], text: str) -> OptionSpec:
    return OptionSpec(str, default, text, choices=choices)


#: the upper bound of the counts (population, inheritance length, trials...)
_MANY = 1_000_000

#: the binary compact GAs cga and pecga (optim/cga.py)
_CGA: dict[str, OptionSpec] = {
    'n': integer(
        25,
        f'[2, {_MANY}]',
        'virtual population size n: each competition moves a probability by 1/n',
    ),
    'bits': integer(
        16, '[1, 32]', 'bits per parameter (resolution 1/(2^bits - 1) of the normalised range)'
    ),
    'coding': choice(
        'binary',
        ('binary', 'gray'),
        "gene coding: 'binary' (plain, most significant bit first) or 'gray' (reflected Gray code)",
    ),
}

#: algo -> option name -> OptionSpec (names are python identifiers, usable as flags);
#: each algorithm's class takes its entry as ``OPTIONS``.
OPTIONS: dict[str, dict[str, OptionSpec]] = {
    'spsa': {
        'a': real(
            0.0183,
            '(0, inf)',
            'step gain a of a_k = a/(k+1+A)^alpha (normalised units per unit of loss gradient)',
        ),
        'c': real(
            0.03,
            '(0, 0.5)',
            'perturbation size c of c_k = c/(k+1)^gamma '
            '(normalised units, fraction of each parameter range)',
        ),
        'A': real(
            20.0,
            '[0, inf)',
            'stability constant A of a_k (iterations; ~10% of the expected iterations)',
        ),
        'alpha': real(
            None,
            '(0, 1]',
            "decay exponent of a_k (default: 0.3 with gains='paper', 0.602 with gains='spall')",
        ),
        'gamma': real(
            None,
            '[0, 1]',
            "decay exponent of c_k (default: 0.3 with gains='paper', 0.101 with gains='spall')",
        ),
        'gains': choice(
            'paper',
            tuple(GAIN_PRESETS),
            "alpha/gamma preset: 'paper' (0.3/0.3) or 'spall' (0.602/0.101)",
        ),
        'max_step': real(
            0.1,
            '(0, inf]',
            'largest change of any normalised parameter in '
            'one iteration (the step vector is scaled down to it); '
            'inf disables the cap',
        ),
    },
    'necga': {
        **_CGA,
        'eta': integer(
            12,
            f'[1, {_MANY}]',
            'allowed length of inheritance eta: after eta '
            'consecutive wins the elite is replaced (must be < n)',
        ),
        'elite_replacement': choice(
            'sample',
            ('sample', 'newcomer'),
            "what replaces an elite that won eta times in a row: 'sample' "
            "(a fresh PV sample, one extra evaluation; the paper's Fig. 3) or 'newcomer' "
            "(the newcomer just evaluated; the authors' Java code)",
        ),
    },
    'cga': dict(_CGA),
    'pecga': dict(_CGA),
    'rcga': {
        'n': integer(
            25, f'[2, {_MANY}]', 'virtual population size n: a competition moves mu by (w - l)/n'
        ),
        'elitism': choice(
            'ne',
            ('ne', 'pe'),
            "'ne' (elite replaced by the newcomer after eta "
            "consecutive wins) or 'pe' (persistent elite)",
        ),
        'eta': integer(
            12,
            f'[1, {_MANY}]',
            "allowed length of inheritance with elitism='ne' (consecutive elite wins; must be < n)",
        ),
        'sigma0': real(
            10.0,
            '(0, 1e6]',
            'initial spread of every variable on x in '
            '[-1, 1] (10: nearly uniform; 0.577: a uniform population)',
        ),
    },
    'cmaes': {
        'sigma0': real(
            0.1,
            '(0, 1]',
            'initial step size sigma0 (normalised units: a fraction of each parameter range)',
        ),
        'popsize': integer(
            None,
            '[2, 10000]',
            "population size lambda per generation (default: pycma's 4 + floor(3 ln dim), "
            '8 for 5 gains)',
        ),
    },
    'tpe': {
        'n_startup_trials': integer(
            10,
            f'[0, {_MANY}]',
            'evaluations sampled at random before TPE models the losses (the start counts)',
        ),
        'n_ei_candidates': integer(
            24,
            f'[1, {_MANY}]',
            'candidates drawn from the good-loss density per ask; the best l(x)/g(x) is asked',
        ),
        'multivariate': choice(
            'yes',
            ('yes', 'no'),
            "'yes': one joint Parzen density over the gains (optuna 5's default); "
            "'no': one per gain",
        ),
    },
    'safe': {
        'sigma0': real(0.05, '(0, 1]', 'initial step size (normalised units)'),
        'grow': real(1.5, '(1, 10]', 'step-size factor after a success'),
        'abort_shrink': real(0.3, '(0, 1]', 'step-size factor after an aborted experiment'),
        'sigma_max': real(
            0.08,
            '[0.005, 1]',
            'largest step size (normalised units): the trust region around the incumbent',
        ),
        'remeasure_every': integer(
            10,
            f'[0, {_MANY}]',
            'measure the incumbent again every this many evaluations (0: never)',
        ),
        'model_every': integer(
            2,
            f'[0, {_MANY}]',
            'take a descent step on the local linear model every this many evaluations '
            '(0: never, a plain (1+1)-ES)',
        ),
    },
}


#: the run's start: the algorithms that can run without the parameter file's start point
_START = choice(
    'hand',
    ('hand', 'none'),
    "'hand': from the parameter file's start point (the hand-tuned gains); 'none': without "
    'it (spsa, cmaes: a uniform random point; tpe: random trials first), the reference '
    'experiment still measures it',
)

#: algo -> policy name -> OptionSpec: what the tuning run does around the optimiser for
#: that algorithm, given with ``--opt`` as a hyperparameter is and kept in run.yaml's
#: ``options``, never a constructor's option (:func:`split_policies`).  An algorithm
#: without ``start`` here is never run without its start (safe: a local search whose
#: first experiment would be an untested random controller).
POLICIES: dict[str, dict[str, OptionSpec]] = {
    'spsa': {'start': _START},
    'cmaes': {'start': _START},
    'tpe': {'start': _START},
    'safe': {
        'first': choice(
            None,
            ('identify', 'model', 'none'),
            "the first step after the start: 'identify' (the best point of an offline "
            "tuning on the drive file's model with the mechanics the start's two "
            "experiments identify), 'model' (the same on the drive file's nominal model, "
            "computed at start-up), 'none' (a local step); default 'identify' where the "
            'tuner knows the drive (--drive-config or a simulated bench, also the one '
            "--bench auto starts), else 'none' "
            '(docs/tuner.md, "Start and first step")',
        )
    },
}
#: the algorithms the tuner may run without a start point (``start=none``)
NO_START_ALGOS: frozenset[str] = frozenset(a for a, p in POLICIES.items() if 'start' in p)
#: the algorithms that measure a model's point right after the start (``first``:
#: ``make_optimizer(first=...)``, ``Optimizer.wants_first``/``set_first``)
TAKES_FIRST: frozenset[str] = frozenset(a for a, p in POLICIES.items() if 'first' in p)


def option_specs(algo: str) -> dict[str, OptionSpec]:
    """Everything ``--opt`` takes for ``algo``: its hyperparameters, then its policies."""
    return {**OPTIONS[algo], **POLICIES.get(algo, {})}


def split_policies(algo: str, opts: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``--opt``'s values (:func:`read_options`) as (hyperparameters, policies): the
    policies checked against their choices and every one of ``algo``'s filled in with its
    default (None: the run decides, its help says how)."""
    policies = POLICIES.get(algo, {})
    hyper = {k: v for k, v in opts.items() if k not in policies}
    given = {k: v for k, v in opts.items() if k in policies}
    return hyper, check_options(algo, policies, given)


def check_eta_below_n(algo: str, opts: dict[str, Any]) -> None:
    """The elitist compact GAs' cross-option check: eta < n (an elite can be replaced)."""
    if opts['eta'] >= opts['n']:
        raise OptimizerError(
            f'{algo} option eta must be an integer in [1, n - 1] = '
            f'[1, {opts["n"] - 1}] (eta < n), got {opts["eta"]!r}'
        )


def read_options(algo: str, items: list[str]) -> dict[str, Any]:
    """``algo``'s options from the tuner's ``--opt`` texts: each ``KEY=VALUE`` (a key
    with - or _), or the path of a YAML file mapping keys to values; each value read as
    its declared type.  OptimizerError (one line) for a key ``algo`` does not have, one
    given twice, or a value of the wrong type; the ranges are ``check_options``'s (the
    policies': :func:`split_policies`)."""
    specs = option_specs(algo)
    mine = ', '.join(specs) or 'none'
    out: dict[str, Any] = {}
    for item in items:
        pairs = _pairs(item)
        for key, text in pairs:
            spec = specs.get(key)
            if spec is None:
                owners = [a for a in OPTIONS if key in option_specs(a)]
                where = f'; {key} is an option of {", ".join(owners)}' if owners else ''
                raise OptimizerError(
                    f'--opt {key} does not apply to --algo {algo} (its options: {mine}){where}'
                )
            if key in out:
                raise OptimizerError(f'--opt {key} is given twice')
            try:
                out[key] = text if spec.type is str else spec.type(text)
            except ValueError:
                raise OptimizerError(
                    f'--opt {key}={text}: {algo} option {key} must be {spec.allowed()}'
                ) from None
    return out


def _pairs(item: str) -> list[tuple[str, str]]:
    """(key, value text) of one ``--opt`` item: ``KEY=VALUE`` or a YAML file's mapping."""
    key, sep, text = item.partition('=')
    if sep:
        if not key.strip():
            raise OptimizerError(f'--opt {item!r}: KEY=VALUE, e.g. --opt sigma0=0.05')
        return [(key.strip().replace('-', '_'), text.strip())]
    import yaml  # (a file of options: rare, so imported then)

    try:
        with open(item, encoding='utf-8') as f:
            data = yaml.safe_load(f)
    except OSError as exc:
        raise OptimizerError(
            f'--opt {item}: KEY=VALUE or a YAML file of options ({exc.strerror or exc})'
        ) from None
    except (yaml.YAMLError, ValueError) as exc:  # (ValueError: not UTF-8 text)
        raise OptimizerError(f'--opt {item}: not YAML ({str(exc).splitlines()[0]})') from None
    if not isinstance(data, dict) or not all(isinstance(k, str) for k in data):
        raise OptimizerError(f'--opt {item}: a YAML mapping of option names to values')
    return [
        # (YAML 1.1 reads yes/no as booleans: the choices are spelled yes/no)
        (k.replace('-', '_'), ('yes' if v else 'no') if isinstance(v, bool) else str(v))
        for k, v in data.items()
    ]


def describe_options(algo: str) -> str:
    """``algo``'s options as ``tuner --algo ALGO --opt help`` prints them: one line each,
    its default, its accepted values and its meaning (the hyperparameters, then the run's
    policies)."""
    specs = option_specs(algo)
    if not specs:
        return f'{algo} has no options'
    lines = [f'{algo} options (--opt KEY=VALUE; docs/optimisers.md):']
    for name, spec in specs.items():
        # (no fixed default: the run or another option decides it, as its text says)
        key = name if spec.default is None else f'{name}={spec.default!r}'
        lines.append(f'  {key}: {spec.help}; {spec.allowed()}')
    return '\n'.join(lines)
