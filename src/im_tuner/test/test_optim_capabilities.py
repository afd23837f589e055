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
