"""The study's plant apart from the drive the tuner is told (``study --plant``,
``--plant-mismatch``), in-process: the runs measure on the plant while the start, the box,
the experiment and ``safe``'s first step are the told drive's; the plant has the physics
the mismatch says; the mismatch's syntax and what it refuses.  Small seeded studies
(2 runs x 6 evaluations, one process)."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from im_drive_sim.sim import DriveSim
from im_tuner.prior import model_prior
from im_tuner.study import runs as R, spec as S
from im_tuner.study.plant import (
    PlantError,
    apply_mismatch,
    mismatch_text,
    parse_mismatch,
    plant_line,
)
from im_tuner.study.worker import init_worker

TOLD = 'im750w-j1'  # the paper's motor, load inertia 1x its own (J 0.0025 kg m^2)
#: the told drive's study: safe blind, with the first step from the drive model and from
#: the identified drive
EXACT = S.StudySpec(runs=2, budget=6, algos=('safe',), drives=(TOLD,), full_grid=False)
J2 = dataclasses.replace(EXACT, mismatch=(('J', 2.0),))


@pytest.fixture(scope='module')
def studies() -> tuple[R.StudyResult, R.StudyResult]:
    """The exact study and the same with the plant's J doubled (the prior computed once:
    cached per told drive in this process)."""
    return R.run_study(EXACT, jobs=1), R.run_study(J2, jobs=1)


def test_the_runs_measure_the_plant_and_the_tuner_knows_the_told_drive(studies):
    exact, j2 = studies
    assert [c.label for c in EXACT.cells] == [
        'defaults',
        'first step from the drive model',
        'first step from the identified drive',
    ]
    # the tuner's side is the told drive's: the same starts, box and first step
    assert np.array_equal(exact.start, j2.start)
    model = EXACT.cells.index(next(c for c in EXACT.cells if c.first == 'model'))
    params = EXACT.params()
    told = EXACT.setup()
    prior = model_prior(told.drive, params.space, told.experiment)
    assert prior is not None
    for r in range(EXACT.runs):
        space_e, opt_e, seed_e = R.prepare_run(EXACT, model, r, params)
        space_j, opt_j, seed_j = R.prepare_run(J2, model, r, J2.params())
        assert space_e == space_j and seed_e == seed_j
        # evaluation 1 the hand-tuned start, evaluation 2 the told drive's model point
        first_e, first_j = opt_e.ask(), opt_j.ask()
        assert np.array_equal(first_e, space_e.start_u) and np.array_equal(first_j, first_e)
        opt_e.tell_measurement(first_e, 1.0, False)
        opt_j.tell_measurement(first_j, 1.0, False)
        u_e, u_j = opt_e.ask(), opt_j.ask()
        assert tuple(u_j.tolist()) == tuple(u_e.tolist()) == prior.u
    # ... and the measurements are the plant's: every run's losses differ
    assert np.isfinite(exact.losses).all() and np.isfinite(j2.losses).all()
    assert not np.any(exact.losses == j2.losses)
    assert not np.any(exact.ref_loss == j2.ref_loss)
    # L_ref is the hand-tuned start on the plant; beside it the same start on the told
    # drive, measured exactly as the exact study's L_ref (bit for bit)
    assert exact.l_ref_told is None and j2.l_ref_told == exact.l_ref
    assert j2.l_ref != exact.l_ref
    # the start's loss on a J x2 plant: the speed loop's gain k_pw Kt/J halves (the
    # loop's bandwidth with it), the move's tracking error grows: a higher loss
    assert j2.l_ref / exact.l_ref > 1.2, (j2.l_ref, exact.l_ref)
    # the reference experiment of every run measures the start on the plant, near L_ref
    np.testing.assert_allclose(j2.ref_loss / j2.l_ref, 1.0, atol=0.02)
    line = plant_line(j2.spec, j2.l_ref, j2.l_ref_told)
    assert line is not None and line.startswith(f'plant: {TOLD} with J x2; the tuner told {TOLD}')
    assert f'{j2.l_ref / exact.l_ref:.3f} x its {exact.l_ref:.5f} on the told drive' in line
    assert plant_line(exact.spec, exact.l_ref, None) is None
    # the identified drive's first step is the plant's: another point on the J x2 plant
    ident = EXACT.cells.index(next(c for c in EXACT.cells if c.first == 'identify'))
    assert not np.array_equal(exact.losses[ident, :, 1], j2.losses[ident, :, 1])


def _j_identified(drive) -> float:
    """J [kg m^2] of a drive's simulated shaft from an open-loop isq step of 1 A at rest,
    50 ms: J = int (T_e - B omega) dt / delta omega (no load, no Coulomb friction)."""
    sim = DriveSim(drive, seed=0)
    sim.reset(omega=0.0, fluxed=True)
    rec = sim.run(np.full(250, 1.0), 0.0)
    omega = rec['omega']
    impulse = float(np.sum(rec['torque'] - drive.machine.B * omega) * drive.Ts)
    return impulse / float(omega[-1])


def test_the_plant_the_worker_builds_has_twice_the_inertia():
    told, _params, told_experiment = init_worker(EXACT)
    plant, params, experiment = init_worker(J2)
    assert plant.machine.J == 2 * told.machine.J == 0.005
    assert experiment == told_experiment and params == EXACT.params()
    # everything else as the drive file says
    assert dataclasses.replace(plant.machine, J=told.machine.J) == told.machine
    # and its shaft accelerates as an inertia of 2 J does
    j_told, j_plant = _j_identified(told), _j_identified(plant)
    assert j_told == pytest.approx(told.machine.J, rel=0.01)
    assert j_plant == pytest.approx(2 * told.machine.J, rel=0.01)
    # --plant im750w-j3 (the same motor with 3x its inertia of load: J 0.005) is the same
    # plant, so a run on it gives the same losses, bit for bit
    j3 = dataclasses.replace(EXACT, plant=('im750w-j3',))
    assert j3.plant_drive() == plant
    a = R.run_one(J2, 1, 0, plant, params, experiment)
    b = R.run_one(j3, 1, 0)
    assert np.array_equal(a.losses, b.losses) and a.remeasured == b.remeasured


def test_coulomb_delay_and_factors_on_the_bench_profile():
    bench = dataclasses.replace(EXACT, realism='bench')
    told = bench.drive()
    mm = parse_mismatch('Rr=x1.3, Lm=x0.85 coulomb=2% delay=2')
    assert mm == (('Rr', 1.3), ('Lm', 0.85), ('coulomb', 2.0), ('delay', 2))
    plant = dataclasses.replace(bench, mismatch=mm).plant_drive()
    m, t = plant.machine, told.machine
    assert m.Rr == t.Rr * 1.3 and m.Lm == t.Lm * 0.85
    assert m.coulomb_torque == pytest.approx(0.02 * t.rated_torque)  # 0.05 N m
    # the Stribeck static torque keeps its excess over Coulomb (0.03 - 0.02 N m on bench)
    assert m.static_torque - m.coulomb_torque == pytest.approx(t.static_torque - t.coulomb_torque)
    assert plant.command_delay == 2 and told.command_delay == 1
    assert plant.sensors == told.sensors and plant.realism == 'bench'
    assert mismatch_text(mm) == (
        'Rr x1.3, Lm x0.85, Coulomb friction 2 % of rated torque, command delay 2 periods'
    )
    assert apply_mismatch(told, ()) is told


@pytest.mark.parametrize(
    ('text', 'expect'),
    [
        ('J=1.5', 'a machine key takes a factor xF with 0.1 <= F <= 10, e.g. J=x1.5'),
        ('J=x0.0001', 'with 0.1 <= F <= 10'),
        ('Rr=x1e6', 'with 0.1 <= F <= 10'),
        ('J=x-1', 'a machine key takes a factor xF'),
        ('J=xnan', 'a machine key takes a factor xF'),
        ('Jx=x2', "unknown key 'Jx'"),
        ('isq_max=x2', "isq_max takes no factor: the controller's current clamp"),
        ('rated_torque=x2', 'a rating the simulated machine does not use'),
        ('pole_pairs=x2', 'an integer'),
        ('coulomb=0.02', 'coulomb takes a percentage of rated torque'),
        ('coulomb=101%', 'in [0, 100]'),
        ('delay=3', 'delay is the command delay in periods, 1 or 2'),
        ('J=x2 J=x3', 'J given twice'),
        ('J', 'KEY=VALUE expected'),
        (' , ', 'nothing given'),
        ('coulomb=1% coulomb_torque=x2', 'give one'),
    ],
)
def test_a_bad_mismatch_is_refused_in_one_line(text, expect):
    with pytest.raises(PlantError) as exc:
        parse_mismatch(text)
    msg = str(exc.value)
    assert msg.startswith('--plant-mismatch') and expect in msg and '\n' not in msg


def test_a_plant_that_cannot_run_the_told_experiment_is_refused(tmp_path):
    fast = tmp_path / 'fast.yaml'
    fast.write_text('base: paper_750w\nTs: 1.0e-4\n')
    enc = tmp_path / 'enc.yaml'  # another encoder and command delay: the controller copes
    enc.write_text('base: paper_750w\nsensors:\n  encoder_counts: 1024\ncommand_delay: 2\n')
    for plant, expect in (
        (str(fast), 'Ts 100 us, the told drive 200 us'),
        ('im3700w-j1', 'machine.isq_max 17.66 A, the told drive 7 A'),
    ):
        with pytest.raises(PlantError, match=re.escape(expect)):
            dataclasses.replace(EXACT, plant=(plant,)).plant_drive()
    with pytest.raises(PlantError, match=r'the plant is not a valid drive.*isq_max'):
        dataclasses.replace(EXACT, mismatch=(('rated_flux_current', 10.0),)).plant_drive()
    with pytest.raises(ValueError, match='plant-mismatch: not a mismatch'):  # out of 0.1-10
        dataclasses.replace(EXACT, mismatch=(('Lm', 0.01),))
    p = dataclasses.replace(EXACT, plant=(str(enc),)).plant_drive()
    assert p.sensors.encoder_counts == 1024 and p.command_delay == 2
    # the spec read back from study.json is checked as the command line is
    with pytest.raises(ValueError, match='plant-mismatch: not a mismatch'):
        dataclasses.replace(EXACT, mismatch=(('J', -2.0),))
    with pytest.raises(ValueError, match='plant: 2 plants for 1 drive'):
        dataclasses.replace(EXACT, plant=('a', 'b'))
    fam = dataclasses.replace(EXACT, drives=(TOLD, 'im750w-j3'), plant=('im750w-j3', TOLD))
    assert [fam.for_drive(d).plant for d in fam.drives] == [('im750w-j3',), (TOLD,)]
