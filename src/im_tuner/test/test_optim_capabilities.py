"""What the tuning loop, the tuner's checks and the study read of an algorithm is declared
once (``optim.options.ALGORITHMS``) and asked of the optimiser, never of its name."""

from __future__ import annotations

import numpy as np
import pytest

from im_tuner.optim import ALGOS, OPTIONS, TAKES_START, OptimizerError, make_optimizer
from im_tuner.optim.options import ALGORITHMS, RIPPLE_LIMITED, TAKES_FIRST


def test_the_algorithms_declare_what_the_tuning_loop_asks_of_them():
    """One declaration per algorithm (options.ALGORITHMS): the sets the tuner and the study
    read come from it, and the first-point hooks the tuning loop calls exist on every
    optimiser, answered by the template for an algorithm that takes none."""
    assert tuple(ALGORITHMS) == ALGOS and set(ALGORITHMS) == set(OPTIONS)
    assert TAKES_FIRST == RIPPLE_LIMITED == {'safe'}
    assert {a for a, d in ALGORITHMS.items() if d.takes_start} == TAKES_START
    start = np.full(5, 0.5)
    for algo in ALGOS:
        opt = make_optimizer(algo, 5, 1, start if algo in TAKES_START else None)
        assert opt.wants_first is False, algo
        if algo in TAKES_FIRST:
            continue
        with pytest.raises(OptimizerError, match=f'{algo} does not take a first point'):
            opt.set_first([0.5] * 5)
        with pytest.raises(OptimizerError, match='only safe does'):
            make_optimizer(algo, 5, 1, first=[0.5] * 5)
    # safe built to be given the identified point asks for it once the start is measured
    opt = make_optimizer('safe', 5, 1, start, first='identify')
    assert opt.wants_first is False  # (nothing measured yet)
    opt.tell(opt.ask(), 1.0)
    assert opt.wants_first is True
    opt.set_first([0.6] * 5)
    assert opt.wants_first is False and opt.ask().tolist() == [0.6] * 5


def test_opt_reads_each_value_as_its_declared_type(tmp_path):
    """The tuner's ``--opt``: KEY=VALUE (- or _ in the key) or a YAML file, each value
    of the type the table declares; one-line refusals that name the option."""
    from im_tuner.optim import describe_options, read_options

    got = read_options('necga', ['n=30', 'eta=12', 'elite-replacement=newcomer'])
    assert got == {'n': 30, 'eta': 12, 'elite_replacement': 'newcomer'}
    assert type(read_options('safe', ['sigma0=1e-2'])['sigma0']) is float
    f = tmp_path / 'opts.yaml'
    f.write_text('sigma0: 0.02\nmultivariate: no\n')
    with pytest.raises(OptimizerError, match='--opt multivariate does not apply to --algo safe'):
        read_options('safe', [str(f)])
    f.write_text('n_startup_trials: 5\nmultivariate: no\n')
    assert read_options('tpe', [str(f)]) == {'n_startup_trials': 5, 'multivariate': 'no'}
    for items, message in (
        (['n=2.5'], '--opt n=2.5: necga option n must be an integer in [2, 1000000]'),
        (['sigma0=0.1'], '--opt sigma0 does not apply to --algo necga (its options: n, '),
        (['n=30', 'n=40'], '--opt n is given twice'),
        (['=3'], "--opt '=3': KEY=VALUE"),
        ([str(tmp_path / 'none.yaml')], 'KEY=VALUE or a YAML file of options'),
    ):
        with pytest.raises(OptimizerError) as ei:
            read_options('necga', items)
        assert message in str(ei.value) and '\n' not in str(ei.value), str(ei.value)
    f.write_text('- a list\n')
    with pytest.raises(OptimizerError, match='a YAML mapping of option names'):
        read_options('necga', [str(f)])
    text = describe_options('safe').splitlines()
    assert text[0].startswith('safe options (--opt KEY=VALUE') and len(text) == 8
    assert text[1] == ('  sigma0=0.05: initial step size (normalised units); a number in (0, 1]')
    # the run's policy after the hyperparameters (optim.POLICIES), read as they are
    assert text[7].startswith('  first: the first step after the start: ')
    assert text[7].endswith("one of 'identify', 'model', 'none'")
    assert read_options('safe', ['first=model', 'grow=2']) == {'first': 'model', 'grow': 2.0}
    f.write_text('start: none\nsigma0: 0.2\n')
    assert read_options('cmaes', [str(f)]) == {'start': 'none', 'sigma0': 0.2}
