"""safe's first step from the drive model (``im_tuner.prior``, safe's ``first``)."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from im_drive_sim.drive_file import load_config
from im_tuner import prior as P
from im_tuner.offline import OfflineBench
from im_tuner.optim import Optimizer, OptimizerError, make_optimizer
from im_tuner.space import load_params
from im_tuner.study.spec import StudySpec, grid

SPACE = load_params(None).space
START = SPACE.start_u


@pytest.fixture(scope='module')
def bench_drive():
    return load_config(None, overrides={'realism': 'bench'})


@pytest.fixture(scope='module')
def prior(bench_drive):
    p = P.model_prior(bench_drive, SPACE)
    assert p is not None
    return p


def test_the_nominal_model_is_the_file_without_its_bench_effects(bench_drive):
    assert bench_drive.machine.coulomb_torque == 0.02  # (the bench profile is on)
    nominal = P.nominal_model(bench_drive)
    assert nominal == load_config(None)  # the packaged ideal drive, field for field
    wrong = load_config(None, overrides={'realism': 'bench', 'machine.J': 3.5e-3})
    assert P.nominal_model(wrong).machine.J == 3.5e-3  # the nameplate is kept


def test_the_prior_is_deterministic_and_cached(bench_drive, prior):
    assert P.model_prior(bench_drive, SPACE) is prior  # cached: the same object
    # the bench profile and the ideal file share one nominal model: one cache entry
    assert P.model_prior(load_config(None), SPACE) is prior
    again = P._compute(P.nominal_model(bench_drive), None, SPACE)  # (not from the cache)
    assert again is not None
    assert again.u == prior.u  # bit for bit
    assert (
        again.experiments
        == prior.experiments
        == (1 + len(P.SEEDS) * P.MODEL_EVALUATIONS + len(P.PERTURBATIONS) * (2 + P.CANDIDATES))
    )


def test_the_prior_is_in_the_box_and_better_than_the_start_on_every_model(bench_drive, prior):
    u = np.array(prior.u)
    assert u.shape == (SPACE.dim,) and np.all((u >= 0) & (u <= 1))
    assert np.linalg.norm(u - START) > 0.05  # a real step, not the start
    assert 0 < prior.model_ratio < prior.worst_ratio < 0.7
    model = P.nominal_model(bench_drive)
    for j, rr in ((1.0, 1.0), (1.4, 0.8)):  # the nominal model, a perturbed one
        m = P.nominal_model(
            load_config(
                None,
                overrides={'machine.J': model.machine.J * j, 'machine.Rr': model.machine.Rr * rr},
            )
        )
        b = OfflineBench(m, 0)
        b.measure(SPACE.to_gains(START))  # from rest
        f0 = b.measure(SPACE.to_gains(START))
        f1 = b.measure(SPACE.to_gains(u))
        assert not f1.aborted and f1.loss < 0.7 * f0.loss


def test_safe_measures_the_start_then_the_first_point_and_no_pattern_move():
    first = [0.3, 0.35, 0.6, 0.01, 0.02]
    opt = make_optimizer('safe', 5, 4, START, first=first)
    assert opt.config()['first'] == first
    u1 = opt.ask()
    assert u1.tolist() == START.tolist()
    opt.tell(u1, 1.0)
    u2 = opt.ask()
    assert u2.tolist() == first  # the model's point, exactly
    opt.tell(u2, 0.5)
    assert opt.x.tolist() == first and opt.f == 0.5 and opt.step is None
    u3 = opt.ask()  # a step of sigma0 around it, not the long jump again
    assert 0 < np.linalg.norm(u3 - u2) < 0.2


def test_a_failed_first_point_shrinks_the_step_and_keeps_the_start():
    first = [0.9] * 5
    opt = make_optimizer('safe', 5, 4, START, first=first)
    opt.tell(opt.ask(), 1.0)
    opt.tell_measurement(opt.ask(), 50.0, True)  # the model was wrong: aborted
    assert opt.x.tolist() == START.tolist() and opt.aborts == 1
    assert opt.sigma == pytest.approx(0.05 * 0.3)


def test_without_first_safe_is_as_before():
    plain = make_optimizer('safe', 5, 4, START)
    assert 'first' not in plain.config() and 'first_left' not in plain.state_dict()


def test_a_checkpoint_restores_before_and_after_the_first_point():
    opt = make_optimizer('safe', 5, 9, START, first=[0.3, 0.3, 0.5, 0.05, 0.05])
    for step in range(6):
        u = opt.ask()
        state = json.loads(json.dumps(opt.state_dict()))
        twin = Optimizer.from_state(state)
        assert twin.ask().tolist() == u.tolist()
        assert json.dumps(twin.state_dict()) == json.dumps(opt.state_dict())
        opt.tell(u, 1.0 - 0.1 * step)


@pytest.mark.parametrize(
    ('algo', 'first', 'message'),
    [
        ('spsa', [0.5] * 5, 'spsa does not take a first point (only safe does)'),
        ('safe', [0.5] * 4, 'safe: first must be 5 finite numbers in [0, 1]'),
        ('safe', [1.5] * 5, 'safe: first must be 5 finite numbers in [0, 1]'),
    ],
)
def test_a_bad_first_point_is_refused(algo, first, message):
    with pytest.raises(OptimizerError, match=re.escape(message)):
        make_optimizer(algo, 5, 0, START, first=first)


def test_the_study_row_runs_safe_from_the_model(prior):
    from im_tuner.study.runs import first_step_of, prepare_run

    cells = grid(('safe',))
    row = [i for i, c in enumerate(cells) if c.first == 'model']
    assert len(row) == 1 and 'first' not in cells[row[0]].opts
    ident = [i for i, c in enumerate(cells) if c.first == 'identify']
    assert len(ident) == 1 and 'first' not in cells[ident[0]].opts
    assert all(c.first == 'none' for i, c in enumerate(cells) if i not in (row[0], ident[0]))
    spec = StudySpec(runs=1, algos=('safe',))
    space, opt, _seed = prepare_run(spec, row[0], 0, load_params(None))
    assert opt.config()['first'] == list(prior.u)
    # the identified row's first step within the row's ripple limit (safe's default 1.5)
    for given, limit in (('default', 1.5), (2.0, 2.0), (None, None)):
        s = StudySpec(runs=1, algos=('safe',), ripple_limit=given)
        assert s.limit_of(cells[ident[0]]) == limit
        assert first_step_of(s, 'identify', space, limit).ripple_limit == limit


def test_the_study_commands_repeat_safe_with_or_without_the_model(prior, tmp_path):
    """runs.csv's tuner command of each safe row gives the tuner the study's first point
    (the model's, or none), whatever the tuner's own default on its bench."""
    import shlex
    from types import SimpleNamespace

    from im_tuner.study.files import tuner_command
    from im_tuner.study.runs import prepare_run, run_seed

    spec = StudySpec(runs=1, algos=('safe',))
    cells = grid(('safe',))
    res = SimpleNamespace(cells=cells, spec=spec, run_seed=[run_seed(spec.seed, 0)])
    for c, cell in enumerate(cells):
        argv = shlex.split(tuner_command(res, c, 0, tmp_path))[3:]  # from 'tuner'
        assert sum(a.startswith('first=') for a in argv) == 1
        _space, opt, _seed = prepare_run(spec, c, 0, load_params(None))
        first = opt.config().get('first')
        for bench in ((), ('--bench', 'inproc')):  # auto: none by default; inproc: model
            options = _new(*argv[1:], *bench).run.options
            assert options['first'] == ('none' if first is None else first), (cell.label, bench)
        assert (first is not None) == (cell.first in ('model', 'identify'))


def _new(*args: str):
    from im_tuner.tuner_args import parse_options
    from im_tuner.tuner_cli import _new_run_config

    argv = ['tuner', *args]
    return _new_run_config(parse_options(argv[1:]), argv)


def test_the_tuner_takes_the_model_where_it_knows_the_drive(prior, tmp_path):
    from im_drive_sim.cli import UsageError
    from im_tuner.tuner_cli import _first_step_hook

    # a simulated bench, or a drive file given: safe's first step from the identified
    # drive (after the start's experiments), or from the file's model when asked
    for args in (('--bench', 'inproc'), ('--drive-config', str(_bench_file(tmp_path)))):
        assert _new('--seed', '3', *args).run.options == {'first': 'identify'}
        # its first step kept within the run's ripple limit (1.5 by default; off: none)
        for more, limit in (
            ((), 1.5),
            (('--ripple-limit', '2'), 2.0),
            (('--ripple-limit', 'off'), None),
        ):
            new = _new('--seed', '3', *args, *more)
            assert new.run.ripple_limit == limit
            assert _first_step_hook(new.run, new.params).ripple_limit == limit
        got = _new('--seed', '3', *args, '--opt', 'first=model').run.options
        assert got == {'first': list(prior.u)}
    # --bench auto: decided with the bench (first_on_bench): identify on the simulated
    # drive it starts, none beside a controller it found (it may drive another motor)
    from im_tuner.tuner_args import parse_options
    from im_tuner.tuner_cli import first_on_bench

    assert _new('--seed', '3').run.options == {'first': None}
    assert first_on_bench(parse_options(['--seed', '3']), 'inproc') == 'identify'
    assert first_on_bench(parse_options(['--seed', '3']), 'external') == 'none'
    assert _new('--seed', '3', '--no-reference').run.options == {'first': 'none'}
    assert _new('--seed', '3', '--opt', 'first=model').run.options == {'first': list(prior.u)}
    none = _new('--seed', '3', '--bench', 'inproc', '--opt', 'first=none')
    assert none.run.options == {'first': 'none'}
    with pytest.raises(UsageError, match='--opt first does not apply to --algo spsa'):
        _new('--seed', '3', '--algo', 'spsa', '--opt', 'first=model')


def _bench_file(tmp_path):
    from im_drive_sim.params import default_config_path

    text = default_config_path().read_text().replace('\nrealism: ideal ', '\nrealism: bench ')
    assert '\nrealism: bench ' in text
    path = tmp_path / 'bench.yaml'
    path.write_text(text)
    return path


def test_the_searchs_ripple_over_the_limit_skips_a_window_where_the_start_rests():
    """The identified model's search with a ripple limit (``prior._over_limit``): an
    experiment's rms over limit x the start's, the larger window; a window where the start
    rests within an encoder count (rms 0, possible on an ideal model) bounds nothing
    rather than dividing by zero, and with no bounded window the search is told the loss."""
    assert P._over_limit((0.3, 0.2), (0.1, 0.2), 1.5) == pytest.approx(2.0)
    assert P._over_limit((0.3, 0.2), (0.0, 0.2), 1.5) == pytest.approx(0.2 / 0.3)
    assert P._over_limit((0.3, 0.2), (0.0, 0.0), 1.5) is None
    assert P._over_limit((float('nan'), 0.2), (0.1, 0.2), 1.5) is None


def test_with_a_limit_the_search_told_it_runs_when_the_free_one_has_nothing_within(monkeypatch):
    """With a ripple limit the first step is looked for among the best points of the
    model's search told nothing of the ripple; only when none of them is predicted
    within the bound (here: every one called loud) does the search told the bound run,
    and the step is its best point predicted within it (test_first_step.py has the step
    taken from the free search).  (20 experiments per seed: the rule, not the tuned
    figures.)"""
    model, limit, n = P.nominal_model(load_config(None)), 1.5, 20
    bound = limit / (1 + P.RIPPLE_MARGIN)
    told: list[float | None] = []  # each search's bound (None: told nothing)
    points: list[set[tuple[float, ...]]] = []  # each search's measured points
    search, check = P._search, P._ripple_check

    def spy(*args, **kwargs):
        told.append(args[4])
        seen, bench = search(*args, **kwargs)
        points.append({u for _, _, u in seen})
        return seen, bench

    def loud_when_free(m, experiment, space, pts):
        if told[-1] is None:
            return dict.fromkeys(pts, math.inf), 0
        return check(m, experiment, space, pts)

    monkeypatch.setattr(P, '_search', spy)
    monkeypatch.setattr(P, '_ripple_check', loud_when_free)
    prior = P._compute(model, None, SPACE, P.PERTURBATIONS, n, limit, (model,))
    assert prior is not None and prior.ripple_ratio is not None
    assert told == [None, bound]
    assert prior.u in points[-1] and prior.u != tuple(START.tolist())
    assert 0.0 <= prior.ripple_ratio <= bound and prior.worst_ratio < 1.0
    # the free search (1 + 4 x 20), the told one (1 + 4 more of the start + 4 x 20), each
    # batch's perturbed models and ripple checks: more than the searches
    searches = 1 + 4 * n + 5 + 4 * n
    assert prior.experiments > searches + len(P.PERTURBATIONS) * 2
