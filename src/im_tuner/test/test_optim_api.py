"""The optimiser API (im_tuner.optim): options and their validation, the ask/tell
contract, JSON state round trips that continue bit-identically, no rclpy.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import im_tuner.optim as optim
from im_tuner.optim import (
    ALGOS,
    OPTIONS,
    TAKES_START,
    Optimizer,
    OptimizerError,
    OptionSpec,
    make_optimizer,
)

EXPECTED_OPTIONS = {
    'spsa': {'a', 'c', 'A', 'alpha', 'gamma', 'gains', 'max_step'},
    'cga': {'n', 'bits', 'coding'},
    'pecga': {'n', 'bits', 'coding'},
    'necga': {'n', 'bits', 'coding', 'eta', 'elite_replacement'},
    'rcga': {'n', 'elitism', 'eta', 'sigma0'},
    'cmaes': {'sigma0', 'popsize'},
    'tpe': {'n_startup_trials', 'n_ei_candidates', 'multivariate'},
    'safe': {'sigma0', 'grow', 'abort_shrink', 'sigma_max', 'remeasure_every', 'model_every'},
}


def test_algos_and_option_table():
    assert ALGOS == ('spsa', 'necga', 'cga', 'pecga', 'rcga', 'cmaes', 'tpe', 'safe')
    assert set(OPTIONS) == set(ALGOS)
    for algo, specs in OPTIONS.items():
        assert set(specs) == EXPECTED_OPTIONS[algo]
        for name, spec in specs.items():
            assert name.isidentifier()
            assert isinstance(spec, OptionSpec) and spec.type in (int, float, str)
            assert spec.help and spec.allowed()
            if spec.default is not None:
                assert spec.check(name, spec.default) == spec.default
            if spec.type is str:
                assert spec.choices and spec.default in spec.choices


def _defaults(algo: str, names: str) -> tuple:
    """The defaults of an algorithm's options, in the order named (space-separated)."""
    return tuple(OPTIONS[algo][name].default for name in names.split())


def test_paper_defaults():
    assert _defaults('spsa', 'a c A gains max_step') == (0.0183, 0.03, 20.0, 'paper', 0.1)
    assert _defaults('spsa', 'alpha gamma') == (None, None)  # from the preset
    assert _defaults('necga', 'n eta bits coding elite_replacement') == (
        25,
        12,
        16,
        'binary',
        'sample',
    )
    assert _defaults('rcga', 'elitism sigma0') == ('ne', 10.0)


BAD = [
    ('spsa', {'a': 0}),
    ('spsa', {'a': -1.0}),
    ('spsa', {'a': 'x'}),
    ('spsa', {'a': True}),
    ('spsa', {'a': math.nan}),
    ('spsa', {'a': math.inf}),
    ('spsa', {'c': 0.5}),
    ('spsa', {'c': 0.0}),
    ('spsa', {'A': -1}),
    ('spsa', {'alpha': 0.0}),
    ('spsa', {'alpha': 1.5}),
    ('spsa', {'gamma': -0.1}),
    ('spsa', {'gains': 'fast'}),
    ('spsa', {'gains': 1}),
    ('spsa', {'max_step': 0.0}),
    ('spsa', {'max_step': -math.inf}),
    ('spsa', {'max_step': math.nan}),
    ('spsa', {'bounded': False}),
    ('spsa', {'n': 25}),
    ('necga', {'n': 1}),
    ('necga', {'n': 25.0}),
    ('necga', {'n': True}),
    ('necga', {'bits': 0}),
    ('necga', {'bits': 33}),
    ('necga', {'coding': 'ascii'}),
    ('necga', {'eta': 25}),
    ('necga', {'eta': 0}),
    ('necga', {'eta': 12.0}),
    ('necga', {'elite_replacement': 'random'}),
    ('necga', {'sigma0': 1.0}),
    ('cga', {'eta': 3}),
    ('cga', {'n': np.float64(10)}),
    ('pecga', {'elite_replacement': 'sample'}),
    ('rcga', {'elitism': 'xx'}),
    ('rcga', {'sigma0': 0.0}),
    ('rcga', {'eta': 25}),
    ('rcga', {'n': 1}),
    ('rcga', {'bits': 16}),
    ('rcga', {'sigma0': 'wide'}),
]


@pytest.mark.parametrize('algo, opts', BAD)
def test_bad_option_names_it(algo, opts, monkeypatch):
    created = []
    real = np.random.PCG64
    monkeypatch.setattr(np.random, 'PCG64', lambda *a: created.append(a) or real(*a))
    with pytest.raises(OptimizerError) as ei:
        make_optimizer(algo, 5, 0, **opts)
    msg = str(ei.value)
    ((name, _value),) = opts.items()
    assert name in msg and '\n' not in msg
    spec = OPTIONS[algo].get(name)
    if spec is None:
        assert 'unknown option' in msg and all(o in msg for o in OPTIONS[algo])
    elif spec.choices:
        assert all(repr(c) in msg for c in spec.choices)
    else:
        assert ' in ' in msg or '>' in msg
    assert created == []  # nothing built before the check


@pytest.mark.parametrize(
    'args, word',
    [
        (('genetic', 5, 0), 'algo'),
        ((None, 5, 0), 'algo'),
        (('spsa', 0, 0), 'dim'),
        (('spsa', True, 0), 'dim'),
        (('spsa', 2.0, 0), 'dim'),
        (('cga', 5, -1), 'seed'),
        (('cga', 5, 1.5), 'seed'),
        (('cga', 5, True), 'seed'),
        (('cga', 5, 'x'), 'seed'),
    ],
)
def test_bad_arguments(args, word):
    with pytest.raises(OptimizerError, match=word):
        make_optimizer(*args)


def test_unknown_algo_lists_the_allowed():
    with pytest.raises(OptimizerError) as ei:
        make_optimizer('genetic', 5, 0)
    assert all(a in str(ei.value) for a in ALGOS)


@pytest.mark.parametrize(
    'start',
    [
        [0.5] * 4,
        [0.5] * 5 + [0.1],
        [0.5, 0.5, 0.5, 0.5, 1.5],
        [0.5, 0.5, math.nan, 0.5, 0.5],
        'abc',
        [[0.5] * 5],
    ],
)
def test_bad_start(start):
    with pytest.raises(OptimizerError, match='start'):
        make_optimizer('spsa', 5, 0, start=start)


@pytest.mark.parametrize('algo', [a for a in ALGOS if a not in TAKES_START])
def test_start_only_for_spsa_cmaes_tpe(algo):
    with pytest.raises(OptimizerError, match='start'):
        make_optimizer(algo, 5, 0, start=np.full(5, 0.5))


def test_seed_sequence_and_config():
    ss = np.random.SeedSequence(123).spawn(2)[1]
    for algo in ALGOS:
        opt = make_optimizer(algo, 5, ss)
        cfg = opt.config()
        assert cfg['algo'] == algo and cfg['dim'] == 5
        assert cfg['seed'] == {'entropy': 123, 'spawn_key': [1]}
        json.dumps(cfg)
        a = make_optimizer(algo, 5, np.random.SeedSequence(123).spawn(2)[1])
        np.testing.assert_array_equal(opt.ask(), a.ask())


# ----------------------------------------------------------------- ask/tell contract
def _quad(u: np.ndarray) -> float:
    return float(np.sum((u - np.linspace(0.1, 0.9, u.size)) ** 2))


VARIANTS = [
    ('spsa', {}),
    ('spsa', {'gains': 'spall', 'max_step': math.inf}),
    ('necga', {}),
    ('necga', {'elite_replacement': 'newcomer', 'n': 6, 'eta': 2}),
    ('necga', {'n': 6, 'eta': 2, 'coding': 'gray', 'bits': 7}),
    ('cga', {}),
    ('pecga', {'n': 5}),
    ('rcga', {}),
    ('rcga', {'elitism': 'pe', 'sigma0': 0.5, 'n': 8}),
    ('cmaes', {}),
    ('cmaes', {'sigma0': 0.3, 'popsize': 5}),
    ('tpe', {}),
    ('tpe', {'multivariate': 'no', 'n_startup_trials': 4}),
    ('safe', {}),
    ('safe', {'sigma0': 0.3, 'sigma_max': 0.5, 'remeasure_every': 3}),
    ('safe', {'model_every': 1, 'abort_shrink': 0.5}),
]


@pytest.mark.parametrize('algo, opts', VARIANTS)
def test_state_round_trip_continues_bit_identically(algo, opts):
    pick = np.random.Generator(np.random.PCG64(99))
    for trial in range(3):
        opt = make_optimizer(algo, 5, 10 + trial, **opts)
        cut = int(pick.integers(0, 50))
        mid_ask = bool(pick.integers(0, 2))  # snapshot with a candidate pending, or not
        for _ in range(cut):
            u = opt.ask()
            opt.tell(u, _quad(u))
        if mid_ask:
            opt.ask()
        text = json.dumps(opt.state_dict())
        twin = Optimizer.from_state(json.loads(text))
        assert type(twin) is type(opt) and twin.evaluations == opt.evaluations
        assert json.dumps(twin.state_dict()) == text
        # tpe: ~20 ms an ask, growing with the trials: 15 asks after the restore still cross
        # from the 10 start-up trials into the model's (cut is 0..50)
        for _ in range(15 if algo == 'tpe' else 200 - cut):
            u, v = opt.ask(), twin.ask()
            assert u.tobytes() == v.tobytes()
            opt.tell(u, _quad(u))
            twin.tell(v, _quad(v))
        assert json.dumps(twin.state_dict()) == json.dumps(opt.state_dict())
        assert twin.converged() == opt.converged()


@pytest.mark.parametrize('algo', ['cmaes', 'tpe'])
def test_start_point_and_resume_with_it(algo):
    start = np.array([0.16, 0.1, 0.19, 0.1, 0.14])
    opt = make_optimizer(algo, 5, 4, start=start)
    first = opt.ask()
    if algo == 'tpe':  # the start is the first (enqueued) trial
        assert first.tobytes() == start.tobytes()
    else:  # the first generation is spread around the start with sigma0 = 0.1
        assert np.max(np.abs(first - start)) < 0.5
        np.testing.assert_array_equal(opt.mean, start)
    assert opt.config()['start'] == start.tolist()
    for cut in (0, 1, 3):  # before the start is asked, while it is pending, after it
        a = make_optimizer(algo, 5, 4, start=start)
        for i in range(cut):
            u = a.ask()
            a.tell(u, _quad(u) + i)
        if cut == 1:
            a.ask()
        b = Optimizer.from_state(json.loads(json.dumps(a.state_dict())))
        for i in range(12):
            u, v = a.ask(), b.ask()
            assert u.tobytes() == v.tobytes(), (cut, i)
            a.tell(u, _quad(u))
            b.tell(v, _quad(v))


def test_safe_starts_at_the_start_and_treats_an_abort_as_a_constraint():
    start = np.array([0.16, 0.1, 0.19, 0.1, 0.14])
    opt = make_optimizer(
        'safe', 5, 1, start=start, sigma0=0.1, sigma_max=0.5, remeasure_every=0, model_every=0
    )
    u = opt.ask()
    assert u.tobytes() == start.tobytes()  # evaluation 1: the known-stable start
    opt.tell(u, 1.0)
    assert opt.f == 1.0 and opt.sigma == 0.1
    # a candidate that aborts: however small its (penalised) loss, it is not taken; the
    # step shrinks by abort_shrink (0.3) and the point enters the model at 3 f
    y = opt.ask()
    assert 0 < np.max(np.abs(y - start)) < 0.6
    opt.tell_measurement(y, 0.01, True)
    assert opt.x.tobytes() == start.tobytes() and opt.sigma == pytest.approx(0.03)
    assert opt.aborts == 1 and opt._vals == [1.0, 3.0]
    # a completed better one is: the step grows and is repeated (pattern move)
    y = opt.ask()
    opt.tell(y, 0.8)
    assert opt.x.tobytes() == y.tobytes() and opt.sigma == pytest.approx(0.045)
    z = opt.ask()
    np.testing.assert_allclose(z, np.clip(y + (y - start), 0, 1))
    # a worse one shrinks the step by grow^(-1/4) (the 1/5 success rule)
    opt.tell(z, 0.9)
    assert opt.sigma == pytest.approx(0.045 * 1.5**-0.25)
    for _ in range(400):  # never below the floor
        w = opt.ask()
        opt.tell(w, 5.0)
    assert opt.sigma == pytest.approx(0.005)


def test_safe_steps_stay_within_the_trust_region_sigma_max():
    # every candidate better than the last: sigma grows by 1.5 a success up to sigma_max
    # (default 0.08), never past it, and so do the steps (pattern and random alike)
    start = np.full(5, 0.5)
    opt = make_optimizer('safe', 5, 3, start=start, remeasure_every=0, model_every=0)
    assert opt.config()['sigma_max'] == 0.08 and opt.sigma == 0.05
    loss, sigmas, steps = 10.0, [], []
    for _ in range(30):
        u = opt.ask()
        steps.append(float(np.linalg.norm(u - opt.x)))
        sigmas.append(opt.sigma)
        loss -= 0.1
        opt.tell(u, loss)
    assert max(sigmas) == 0.08 and sigmas[2] == pytest.approx(0.075)
    # a step is sigma z (z ~ N(0, I_5)) or a repeat of one (pattern move), with sigma
    # <= 0.08; |z| > 8 has a probability below 1e-10 (and the run is seeded)
    assert max(steps) < 8 * 0.08
    with pytest.raises(OptimizerError, match=r'sigma0 0\.1 is larger than sigma_max 0\.08'):
        make_optimizer('safe', 5, 3, sigma0=0.1)


def test_safe_model_step_descends_the_fitted_slope_and_avoids_aborted_points():
    c = np.array([1.0, -2.0, 0.5, 0.0, 0.25])
    start = np.full(5, 0.5)

    def plane(u: np.ndarray) -> float:
        return float(3.0 + c @ (u - start))

    # (abort_shrink 0.9: the model radius, 3 sigma sqrt(5), still holds the aborted point)
    opt = make_optimizer(
        'safe', 5, 2, start=start, remeasure_every=0, model_every=1, abort_shrink=0.9
    )
    assert opt.slope() is None  # no data: no model
    u = opt.ask()
    opt.tell(u, plane(u))
    # measured points around the start, all on the plane (as failed candidates leave them)
    near = start + 0.02 * np.random.default_rng(3).standard_normal((8, 5))
    opt._pts += near.tolist()
    opt._vals += [plane(q) for q in near]
    np.testing.assert_allclose(opt.slope(), c, rtol=1e-9, atol=1e-9)
    y = opt.ask()  # no pattern step pending: a model step, -sigma sqrt(5) c/|c| + noise
    s = y - opt.x
    assert s @ -c / (np.linalg.norm(s) * np.linalg.norm(c)) > 0.9
    assert 0.5 * opt.sigma * 5**0.5 < np.linalg.norm(s) < 2 * opt.sigma * 5**0.5
    # the step was downhill; it aborts: the model sees its point at 3 f, far above the
    # plane there, and the slope along that step turns uphill (away from the instability)
    assert opt.slope() @ s < 0
    opt.tell_measurement(y, 1e6, True)
    assert opt._vals[-1] == 3.0 * opt.f and opt.x.tobytes() == start.tobytes()
    assert opt.slope() @ s > 0


def test_cmaes_ignores_numpy_global_rng_and_refuses_a_state_that_does_not_replay():
    runs = []
    for g in (1, 2):
        np.random.seed(g)
        opt = make_optimizer('cmaes', 5, 8)
        us = []
        for _ in range(20):
            u = opt.ask()
            us.append(u.tobytes())
            opt.tell(u, _quad(u))
        runs.append(us)
    assert runs[0] == runs[1]
    st = opt.state_dict()
    st['told_u'][3][0] += 1e-9
    with pytest.raises(OptimizerError, match='replay'):
        Optimizer.from_state(st)


@pytest.mark.parametrize('algo', ALGOS)
def test_ask_is_idempotent_and_returns_fresh_arrays(algo):
    opt = make_optimizer(algo, 5, 1)
    for i in range(30):
        u = opt.ask()
        assert u.dtype == np.float64 and u.shape == (5,)
        assert np.all((u >= 0) & (u <= 1))
        u[:] = -7.0  # the caller's copy only
        v = opt.ask()
        w = opt.ask()
        assert v.tobytes() == w.tobytes() and v is not w
        assert opt.evaluations == i
        opt.tell(v, _quad(v))
    assert opt.evaluations == 30


@pytest.mark.parametrize('algo', ALGOS)
def test_bad_tell_changes_nothing(algo):
    opt = make_optimizer(algo, 5, 2)
    with pytest.raises(OptimizerError, match='ask'):
        opt.tell(np.full(5, 0.5), 1.0)  # nothing asked yet
    for _ in range(7):
        u = opt.ask()
        opt.tell(u, _quad(u))
    u = opt.ask()
    before = json.dumps(opt.state_dict())
    other = u.copy()
    other[2] = np.nextafter(other[2], 2.0)  # one ulp away
    for bad_u, loss in [
        (other, 1.0),
        (u[:4], 1.0),
        (u, math.nan),
        (u, math.inf),
        (u, -math.inf),
        (u, True),
        (u, '1.0'),
        (u, None),
        ('x', 1.0),
    ]:
        with pytest.raises(ValueError):
            opt.tell(bad_u, loss)
        assert json.dumps(opt.state_dict()) == before
    assert opt.ask().tobytes() == u.tobytes()
    opt.tell(list(u), 1)  # the same values as a list, an int loss
    assert opt.evaluations == 8
    with pytest.raises(OptimizerError):
        opt.tell(u, 1.0)  # told already: nothing pending


def test_from_state_rejects_garbage():
    for bad in [{}, {'algo': 'nope'}, 'spsa', None]:
        with pytest.raises(OptimizerError):
            Optimizer.from_state(bad)
    st = make_optimizer('necga', 5, 0).state_dict()
    st['version'] = 99
    with pytest.raises(OptimizerError, match='version'):
        Optimizer.from_state(st)
    st = make_optimizer('cga', 5, 0).state_dict()
    st['k'] = [100] * 80
    with pytest.raises(OptimizerError):
        Optimizer.from_state(st)
    st = make_optimizer('rcga', 5, 0).state_dict()
    del st['mu']
    with pytest.raises(OptimizerError):
        Optimizer.from_state(st)


def test_floats_survive_json_exactly():
    opt = make_optimizer('spsa', 5, 3)
    for _ in range(11):
        u = opt.ask()
        opt.tell(u, _quad(u) + 1e-17 * math.pi)
    st = json.loads(json.dumps(opt.state_dict()))
    assert np.array(st['u']).tobytes() == opt.iterate.tobytes()


def test_no_rclpy_anywhere():
    src = Path(optim.__file__).parent
    for f in src.glob('*.py'):
        assert not re.search(r'^\s*(import|from)\s+(rclpy|rosidl)', f.read_text(), re.MULTILINE), f
    code = (
        'import sys, im_tuner.optim as o; o.make_optimizer("necga", 5, 0).ask(); '
        'sys.exit(any(m.split(".")[0] in ("rclpy", "rosidl_runtime_py") '
        'for m in sys.modules))'
    )
    assert subprocess.run([sys.executable, '-c', code], timeout=60).returncode == 0


def test_algorithm_modules_load_only_when_built():
    """Importing im_tuner.optim (and reading OPTIONS, ALGOS, TAKES_START: what the tuner's
    command line needs) imports no algorithm module and none of pycma, optuna, scipy;
    building one imports its own module only; a state restores in a fresh process (the
    registry loads the module)."""
    state = make_optimizer('cmaes', 5, 1).state_dict()
    code = (
        'import json, sys\n'
        'import im_tuner.optim as o\n'
        'assert o.OPTIONS["cmaes"]["sigma0"].default == 0.1 and "safe" in o.TAKES_START\n'
        'heavy = ("cma", "optuna", "scipy", "im_tuner.optim.cmaes", "im_tuner.optim.tpe",\n'
        '         "im_tuner.optim.rcga", "im_tuner.optim.spsa", "im_tuner.optim.cga",\n'
        '         "im_tuner.optim.safe")\n'
        'first = sorted(m for m in heavy if m in sys.modules)\n'
        'o.make_optimizer("spsa", 5, 0)\n'
        'second = sorted(m for m in heavy if m in sys.modules)\n'
        'opt = o.Optimizer.from_state(json.loads(sys.stdin.read()))\n'
        'print(json.dumps([first, second, type(opt).__name__, "cma" in sys.modules]))\n'
    )
    proc = subprocess.run(
        [sys.executable, '-c', code],
        input=json.dumps(state),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    first, second, name, cma_loaded = json.loads(proc.stdout)
    assert first == [] and second == ['im_tuner.optim.spsa']
    assert name == 'CMAES' and cma_loaded
    assert optim.CMAES is type(make_optimizer('cmaes', 5, 1))
    with pytest.raises(AttributeError):
        optim.NoSuchOptimiser  # noqa: B018
    from im_tuner.optim.options import GAIN_PRESETS, NO_START_ALGOS

    assert tuple(GAIN_PRESETS) == OPTIONS['spsa']['gains'].choices
    assert NO_START_ALGOS < TAKES_START and 'safe' not in NO_START_ALGOS


def test_evaluations_per_generation():
    """Evaluations, not iterations: spsa 2 per iteration, cga 2 per generation, the
    elitist ones 1 (+ the first elite; + 1 per sampled replacement for neCGA)."""
    runs = {}
    for algo, opts in [
        ('spsa', {}),
        ('cga', {}),
        ('pecga', {}),
        ('rcga', {}),
        ('necga', {'elite_replacement': 'newcomer'}),
    ]:
        opt = make_optimizer(algo, 5, 4, **opts)
        for _ in range(200):
            u = opt.ask()
            opt.tell(u, _quad(u))
        runs[algo] = opt
    assert runs['spsa'].iterations == 100
    assert runs['cga'].generation == 100
    assert runs['pecga'].generation == 199 and runs['rcga'].generation == 199
    assert runs['necga'].generation == 199


@pytest.mark.parametrize('algo, opts', VARIANTS)
def test_random_blocks_are_invisible(algo, opts):
    """The uniforms are drawn in blocks (one rng call per many asks, for speed): the asks
    and every state_dict, RNG state included, are those of drawing one candidate's numbers
    at a time (block of 1)."""
    blocked = make_optimizer(algo, 5, 31, **opts)
    single = make_optimizer(algo, 5, 31, **opts)
    single._BLOCK = 1
    for i in range(40 if algo == 'tpe' else 150):  # tpe: 40 asks cover its 10 start-up trials
        u, v = blocked.ask(), single.ask()
        assert u.tobytes() == v.tobytes()
        if i % 7 == 0:
            assert json.dumps(blocked.state_dict()) == json.dumps(single.state_dict())
        blocked.tell(u, _quad(u))
        single.tell(v, _quad(v))
        if i % 11 == 0:
            assert json.dumps(blocked.state_dict()) == json.dumps(single.state_dict())


@pytest.mark.parametrize('algo', ALGOS)
def test_tell_takes_the_same_numbers_in_any_form(algo):
    """u is compared as float64 bytes: a list or another dtype holding the same values is
    the candidate (a numpy loss too); a reshaped or reordered array, or values one float32
    rounding away, are not."""
    for form in (
        np.copy,
        list,
        lambda u: np.asarray(u, dtype=np.longdouble),
        lambda u: np.asarray(u, dtype=object),
    ):
        opt = make_optimizer(algo, 5, 3)
        u = opt.ask()
        opt.tell(form(u), np.float64(1.5))
        assert opt.evaluations == 1
    opt = make_optimizer(algo, 5, 3)
    u = opt.ask()
    for bad in (u.reshape(1, 5), u.reshape(5, 1), u[::-1].copy(), u.astype(np.float32)):
        with pytest.raises(OptimizerError, match='pending'):
            opt.tell(bad, 1.0)
    with pytest.raises(OptimizerError, match='finite'):
        opt.tell(u, np.float64('nan'))
    assert opt.evaluations == 0


def test_the_sign_of_a_pending_zero_counts():
    opt = make_optimizer('cga', 2, 0, n=10, bits=3)
    st = opt.state_dict()
    st['k'] = [-5] * 6  # p = 0: every sample is 000000, u = (0, 0)
    opt = Optimizer.from_state(st)
    u = opt.ask()
    assert u.tolist() == [0.0, 0.0] and not np.signbit(u).any()
    with pytest.raises(OptimizerError, match='bit for bit'):
        opt.tell(np.array([0.0, -0.0]), 1.0)
    opt.tell(np.array([0, 0]), 1.0)  # integers convert to +0.0
    assert opt.evaluations == 1
