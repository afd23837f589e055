"""safe's first step from the identified drive (``first='identify'``, im_tuner.first_step):
the optimiser's protocol, its state, and a whole run on a plant whose J is twice the
drive file's (the run identifies it, takes the identified model's step, writes both into
summary.json, and a resume without its checkpoint asks the same points)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from im_tuner.family import drive_setup
from im_tuner.first_step import IdentifiedFirstStep
from im_tuner.offline import OfflineBench
from im_tuner.optim import Optimizer, OptimizerError, make_optimizer
from im_tuner.prior import RIPPLE_MARGIN, identified_model, model_prior
from im_tuner.progress import mechanics_lines
from im_tuner.rundir import RunDir
from im_tuner.runlog import MemoryRecord
from im_tuner.runlog.ripple import LIMIT_KEYS, RIPPLE_TOLERANCE, ripple_bound, told_loss
from im_tuner.tuning import TuningRun

POINT = [0.3, 0.35, 0.6, 0.01, 0.02]


def _safe(seed: int = 4):
    setup = drive_setup('im750w-j1')
    return make_optimizer('safe', 5, seed, setup.params.space.start_u, first='identify')


def test_identify_waits_for_the_start_then_measures_the_given_point():
    opt = _safe()
    assert opt.config()['first'] == 'identify' and not opt.wants_first
    u1 = opt.ask()
    opt.tell(u1, 1.0)
    assert opt.wants_first
    opt.set_first(POINT)
    assert not opt.wants_first
    assert opt.ask().tolist() == POINT
    opt.tell(np.array(POINT), 0.5)
    assert opt.x.tolist() == POINT and opt.step is None
    with pytest.raises(OptimizerError, match='once, before it is asked'):
        opt.set_first(POINT)


def test_after_the_identified_point_the_step_is_small_not_grown():
    """The identified model's point sits near the stability edge (on im7500w-j10 a grown
    step of 0.075 from it aborted in 3-5 of 8 runs): after it succeeds the search goes on
    with sigma 0.02; after the file's model's point (first=model) as before, grown."""
    ident = _safe()
    ident.tell(ident.ask(), 1.0)
    ident.set_first(POINT)
    ident.tell(ident.ask(), 0.5)
    model = make_optimizer('safe', 5, 4, _safe().x, first=POINT)
    model.tell(model.ask(), 1.0)
    assert model.ask().tolist() == POINT
    model.tell(np.array(POINT), 0.5)
    assert ident.x.tolist() == model.x.tolist() == POINT and ident.f == model.f == 0.5
    assert ident.sigma == 0.02
    assert model.sigma == pytest.approx(0.05 * 1.5)  # sigma0 grown on a success
    # the next candidate: the same random direction, 0.02/0.075 as far (where neither is
    # clipped at the box's edge)
    y_ident, y_model = ident.ask(), model.ask()
    inside = (y_ident > 0) & (y_model > 0) & (y_ident < 1) & (y_model < 1)
    assert inside.sum() >= 3
    d_ident, d_model = (y - np.array(POINT) for y in (y_ident, y_model))
    assert np.allclose(d_ident[inside], 0.02 / 0.075 * d_model[inside])
    # a later success grows it as any other
    ident.tell(y_ident, 0.4)
    assert ident.sigma == pytest.approx(0.03)


def test_no_point_given_is_the_search_without_a_model():
    a, b = _safe(), make_optimizer('safe', 5, 4, _safe().x)
    for opt in (a, b):
        opt.tell(opt.ask(), 1.0)
    a.set_first(None)  # the identification found nothing: no first step
    for _ in range(5):
        ua, ub = a.ask(), b.ask()
        assert ua.tolist() == ub.tolist()
        a.tell(ua, 0.9)
        b.tell(ub, 0.9)


def test_a_failed_first_point_is_followed_by_the_points_half_way_back():
    """The identified point told no better than the start (a loud point under the ripple
    limit is told so): the next two asks are half-way back to the start, then a quarter;
    the first of them that succeeds is the incumbent with sigma 0.02, as the point
    itself would have been; an aborted point backs off nothing; a checkpoint between
    them resumes the same asks; and a first point that succeeds backs off nothing."""
    x0 = np.array(_safe().x)
    half, quarter = (x0 + np.array(POINT)) / 2, (x0 + (x0 + np.array(POINT)) / 2) / 2

    def after_start(opt):
        opt.tell(opt.ask(), 1.0)
        opt.set_first(POINT)
        assert opt.ask().tolist() == POINT
        return opt

    opt = after_start(_safe())
    opt.tell(np.array(POINT), 1.0)  # not below f: failed
    assert np.allclose(opt.ask(), half)
    twin = Optimizer.from_state(json.loads(json.dumps(opt.state_dict())))
    assert twin.ask().tolist() == opt.ask().tolist()
    opt.tell(opt.ask(), 1.2)  # failed again
    assert np.allclose(opt.ask(), quarter)
    opt.tell(opt.ask(), 0.8)  # success: the incumbent, the identified point's sigma
    assert np.allclose(opt.x, quarter) and opt.f == 0.8 and opt.sigma == 0.02
    assert opt.step is None  # (no pattern move repeats a model's step)
    # two back-offs at most: after three failures the search goes on from the start
    opt = after_start(_safe())
    for _ in range(3):
        opt.tell(opt.ask(), 1.5)
    y = opt.ask()
    assert not np.allclose(y, (x0 + quarter) / 2) and np.allclose(opt.x, x0)
    # an aborted point: no back-off, the search as before
    a, b = after_start(_safe()), after_start(_safe())
    a.tell_measurement(np.array(POINT), 3.0, True)
    b.tell_measurement(np.array(POINT), 3.0, True)
    assert not np.allclose(a.ask(), half) and a.ask().tolist() == b.ask().tolist()
    # a point that succeeds: nothing backs off (the runs of the ideal study, unchanged)
    opt = after_start(_safe())
    opt.tell(np.array(POINT), 0.5)
    assert opt.state_dict()['first_back'] is None and opt.state_dict()['first_backoffs'] == 0


def test_a_checkpoint_keeps_the_given_point_and_whether_it_was_asked():
    opt = _safe(9)
    for step in range(5):
        if opt.wants_first:
            opt.set_first(POINT)
        u = opt.ask()
        twin = Optimizer.from_state(json.loads(json.dumps(opt.state_dict())))
        assert twin.ask().tolist() == u.tolist()
        assert json.dumps(twin.state_dict()) == json.dumps(opt.state_dict())
        opt.tell(u, 1.0 - 0.1 * step)
    assert opt.state_dict()['first_point'] == POINT


def test_the_identified_model_carries_the_mechanics_in_the_files_current_units():
    setup = drive_setup('im750w-j1')
    m = setup.drive.machine

    class Idf:
        J, J_sd, Kt, Kt_file, B, Tc = 2.0 * m.J, 0.01 * m.J, 0.5 * m.Kt, m.Kt, 0.0, 0.05

    model, exp = identified_model(setup.drive, setup.experiment, Idf())  # type: ignore[arg-type]
    # Kt half the file's: J, Tc and the load torque doubled in the file's current units
    assert pytest.approx(4.0 * m.J, rel=0.01) == model.machine.J
    assert model.machine.coulomb_torque == pytest.approx(0.1, abs=0.005 * m.rated_torque)
    assert exp.trajectory.load_torque == pytest.approx(
        2.0 * setup.experiment.trajectory.load_torque
    )
    assert model.realism == 'ideal' and model.machine.Kt == m.Kt


def _run(path, plant, budget: int) -> TuningRun:
    setup = drive_setup('im750w-j1')
    space = setup.params.space
    hook = IdentifiedFirstStep(setup.drive, space, setup.experiment)
    opt = make_optimizer('safe', 5, 3, space.start_u, first='identify')
    rd = RunDir.create(path) if not path.exists() else RunDir(path)
    return TuningRun(
        rd, space, opt, budget=budget, satisfactory_loss=0.9, remeasure=0, first_step=hook
    )


def test_a_run_on_a_plant_with_twice_the_files_inertia(tmp_path):
    setup = drive_setup('im750w-j1')
    m = setup.drive.machine
    plant = dataclasses.replace(setup.drive, machine=dataclasses.replace(m, J=2.0 * m.J))
    run = _run(tmp_path / 'r', plant, budget=3)
    assert run.run(OfflineBench(plant, 5, setup.experiment)) == 'done'
    s = run.summary(outcome='done', wall_s=1.0)
    idf = s.identification
    assert idf is not None and idf['experiments'] == 2 and idf['J_file'] == m.J
    assert abs(idf['J'] / (2.0 * m.J) - 1.0) < 0.03  # the plant's, not the file's
    # the abort screen ran on evaluation 3's candidate (named nothing here)
    assert s.screened == run.opt.screened == 0 and run.opt.screen.experiments >= 2
    assert 'abort screen: 0 candidate(s)' in '\n'.join(mechanics_lines(s))
    # evaluation 2 is the identified model's point, not the file's model's
    first = run.first_step.prior
    assert first is not None
    # found by 300 experiments per seed on the identified model (the file's model: 150)
    assert first.experiments == 1 + 4 * 300 + 6 * (2 + 8)
    evals = [r for r in run.records if r.kind == 'eval']
    assert evals[1].u == list(first.u)
    assert evals[1].u != list(model_prior(setup.drive, setup.params.space, setup.experiment).u)
    # it is a real improvement on this plant: the loss well below the start's
    assert evals[1].loss < 0.75 * evals[0].loss and not evals[1].aborted
    # the ripple of the start and of the applied gains, in A
    assert s.ripple is not None and 0.0 < s.ripple['start']['rms_after_move'] < 1.0
    # a resume whose checkpoint is gone rebuilds the optimiser from results.jsonl: the
    # same identification from the recorded motion sums, the same first point
    (tmp_path / 'r' / 'checkpoint.json').unlink()
    again = _run(tmp_path / 'r', plant, budget=4)
    assert again.restore() == len(run.records)
    assert again.opt.state_dict()['first_point'] == list(first.u)


def test_with_a_ripple_limit_the_model_s_best_point_is_taken_when_predicted_within_it():
    """im750w-j1 on a plant with 1.5x the file's inertia (its own ``ideal`` profile).  The
    identified model's best robust point, the step without a limit, is predicted 1.00x the
    start's standstill rms on the model of the ripple check (within 1.5 by the margin):
    with the run's limit the first step is that point, the prediction stated, at the cost
    of the check alone.  On the ideal plant its one experiment is 1.57x the start's (the
    limit cycle at rest comes and goes with the rest position: the prediction is a mean):
    over the limit by less than the tolerance, so told its loss, and the final choice
    decides on the mean of its experiments."""
    setup = drive_setup('im750w-j1')
    space, m = setup.params.space, setup.drive.machine
    plant = dataclasses.replace(setup.drive, machine=dataclasses.replace(m, J=1.5 * m.J))
    runs, steps = {}, {}
    for name, limit in (('before', None), ('limited', 1.5)):
        said: list[str] = []
        hook = IdentifiedFirstStep(setup.drive, space, setup.experiment, said.append, limit)
        opt = make_optimizer('safe', 5, 3, space.start_u, first='identify')
        run = TuningRun(
            MemoryRecord(), space, opt, budget=2, satisfactory_loss=0.9, remeasure=0,
            first_step=hook, ripple_limit=1.5,
        )  # fmt: skip
        assert run.run(OfflineBench(plant, 5, setup.experiment)) == 'done'
        runs[name] = run
        step = next(x for x in said if x.startswith('first step:'))
        assert step.startswith("first step: the identified model's best point"), said
        steps[name] = step
        assert ('predicted' in step) == (limit is not None), step
    before, limited = (runs[k].first_step.prior for k in ('before', 'limited'))
    assert before is not None and limited is not None
    assert before.ripple_ratio is None and limited.u == before.u
    assert limited.model_ratio == before.model_ratio and limited.worst_ratio < 0.5
    # predicted within the limit by its margin
    assert 0.9 < limited.ripple_ratio <= 1.5 / (1 + RIPPLE_MARGIN)
    line = f"its standstill rms predicted {limited.ripple_ratio:.2f}x the start's, within "
    assert line + 'the ripple limit 1.5 by 10%' in steps['limited']
    # the check: on each of the two models (identified and file friction) the start from
    # rest and 4 times, and each of the 8 candidates 6 times
    assert limited.experiments == before.experiments + 2 * (1 + 4 + 8 * 6)
    for run in runs.values():
        start, step = (r for r in run.records if r.kind == 'eval')
        assert step.u == list(limited.u) and not step.aborted
        bound = ripple_bound(run.records, 1.5)
        assert bound is not None
        over = max(step.ripple[k] / b for k, b in bound.items())
        assert 1.0 < over <= RIPPLE_TOLERANCE
        assert told_loss(run.records[: run.records.index(step)], step, 1.5) == step.loss
        assert step.ripple[LIMIT_KEYS[0]] / start.ripple[LIMIT_KEYS[0]] == pytest.approx(
            1.57, abs=0.01
        )
        assert step.loss < 0.5 * start.loss  # a real improvement


def test_a_screened_candidate_is_learnt_as_an_abort_without_being_asked():
    """The screen (the identified model's abort prediction) is wanted once the start is
    measured and the first point given; a candidate it names is not asked: the model's
    data gets the aborted value, the step shrinks as after an abort, ``screened`` counts
    it (not ``aborts``), and a checkpoint keeps the count; after ``SCREEN_TRIES`` names
    in a row the incumbent is measured again."""
    opt = _safe()
    assert not opt.wants_screen  # (the start not measured yet)
    opt.tell(opt.ask(), 1.0)
    assert opt.wants_first and not opt.wants_screen
    opt.set_first(POINT)
    assert opt.wants_screen
    opt.tell(opt.ask(), 0.5)
    x = opt.x.copy()
    named: list[list[float]] = []

    def screen(u: list[float]) -> bool:  # the half-space above the incumbent's gain 0
        if u[0] > x[0]:
            named.append(u)
            return True
        return False

    opt.screen = screen
    assert not opt.wants_screen
    sigma, asked = opt.sigma, []
    for _ in range(12):
        u = opt.ask()
        asked.append(u)
        assert u[0] <= x[0]
        opt.tell(u, 0.6)  # no better: x stays
    assert named and opt.screened == len(named) and opt.aborts == 0
    assert opt.sigma <= sigma * 0.3  # abort_shrink, to the floor SIGMA_MIN
    assert any(v == 3.0 * opt.f for v in opt._vals)  # ABORT_VALUE x the incumbent's loss
    twin = Optimizer.from_state(json.loads(json.dumps(opt.state_dict())))
    assert twin.screened == opt.screened and twin.screen is None and twin.wants_screen
    # a screen that names every candidate: SCREEN_TRIES of them, then the incumbent
    opt.screen = lambda u: True
    before = opt.screened
    assert opt.ask().tolist() == opt.x.tolist()
    assert opt.screened - before == opt.SCREEN_TRIES
