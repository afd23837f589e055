"""Identification from the start's experiments (im_tuner.identify) and the kernel's sums
behind it (im_controller.kernel.motion_step, ripple_step): against exact synthetic motion,
and against the simulated plant with the drive file wrong (J, Rr, Lm, Coulomb friction)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from im_controller import layout as L
from im_controller.config import ExperimentConfig
from im_controller.kernel import motion_step, ripple_step
from im_controller.runner import motion_of, ripple_of
from im_controller.trajectory import make_experiment_params
from im_tuner.family import drive_setup
from im_tuner.identify import MIN_ROWS, MODEL_ERROR, identify, sum_motion
from im_tuner.offline import OfflineBench


def _synthetic(J: float, Kt: float, skip: set[int] = frozenset()) -> tuple[float, ...]:
    """The kernel's sums over an exact motion: constant acceleration a from rest for the
    first 0.2 s, then constant speed, isq = J a / Kt, no friction, no load; the states
    in ``skip`` never reach the kernel (unseen in real time)."""
    Q = make_experiment_params(ExperimentConfig())
    R = np.zeros(L.N_RSTATE)
    state = np.zeros(14)
    ts, a = Q[L.Q_TS], 300.0
    for n in range(int(Q[L.Q_N])):
        if n in skip:
            continue
        t = n * ts
        acc = a if t < 0.2 else 0.0
        t1 = min(t, 0.2)
        th = 0.5 * a * t1 * t1 + a * 0.2 * (t - t1)
        state[L.S_ISQ] = J * acc / Kt
        motion_step(R, Q, float(n), th, a * t1, state)
    return motion_of(R)


def test_the_sums_of_an_exact_motion_hold_its_equation_in_every_row():
    J, Kt = 0.0025, 0.71
    mo = _synthetic(J, Kt)
    M, rows, _ = sum_motion([mo])
    # 5625 steps, 20 ms blocks: 57 start (n = 0, 100, .., 5600), a row at each after two
    assert rows == 57 - 2
    c = np.array([J, -Kt, 0.0, 0.0, 1.0])  # residual z.c of J z0 = Kt z1 - z4 (no load)
    assert c @ M @ c < 1e-12 * M[0, 0] * J * J
    assert M[0, 0] > 0.1  # the move is in the rows


def test_an_unseen_block_start_drops_the_rows_it_would_spoil():
    J, Kt = 0.0025, 0.71
    whole = sum_motion([_synthetic(J, Kt)])
    K = round(L.MOTION_BLOCK / 0.0002)
    skipped = sum_motion([_synthetic(J, Kt, skip={3 * K, 3 * K + 1})])
    # the block starting at 3 K is unseen: it and the two rows that need it are left out
    assert skipped[1] == whole[1] - 3
    M = skipped[0]
    c = np.array([J, -Kt, 0.0, 0.0, 1.0])
    assert c @ M @ c < 1e-12 * M[0, 0] * J * J


def test_the_ripple_sums_are_the_windows_rms_and_peak_to_peak():
    Q = make_experiment_params(ExperimentConfig())
    assert (Q[L.Q_RIP1_A], Q[L.Q_RIP1_B], Q[L.Q_RIP2_A], Q[L.Q_RIP2_B]) == (
        1502.0,
        3500.0,
        4500.0,
        5625.0,
    )
    R = np.zeros(L.N_RSTATE)
    rng = np.random.default_rng(0)
    x = rng.normal(2.0, 0.3, 5625)
    for n in range(5625):
        ripple_step(R, Q, float(n), x[n])
    w1, w2 = x[1502:3500], x[4500:5625]
    got = ripple_of(R)
    np.testing.assert_allclose(got, (w1.std(), np.ptp(w1), w2.std(), np.ptp(w2)), rtol=1e-9)
    assert all(math.isnan(v) for v in ripple_of(np.zeros(L.N_RSTATE)))


def test_too_few_rows_identify_nothing():
    machine = drive_setup('paper_750w').drive.machine
    assert identify([], machine) is None
    assert identify([(float(MIN_ROWS - 1),) + (1.0,) * 15], machine) is None
    assert identify([()], machine) is None  # a controller without the sums


def _start_experiments(
    name: str, realism: str, seed: int = 1, **scale: float
) -> tuple[list, object, object]:
    """The start's three experiments on ``name``'s plant changed by ``scale`` (a machine
    constant's factor, ``coulomb`` in rated torque, ``delay`` the command delay)."""
    setup = drive_setup(name, realism=realism)
    m = setup.drive.machine
    rep = {k: getattr(m, k) * v for k, v in scale.items() if k not in ('coulomb', 'delay')}
    if 'coulomb' in scale:
        rep['coulomb_torque'] = scale['coulomb'] * m.rated_torque
    plant = dataclasses.replace(setup.drive, machine=dataclasses.replace(m, **rep))
    if 'delay' in scale:
        plant = dataclasses.replace(plant, command_delay=int(scale['delay']))
    bench = OfflineBench(plant, seed, setup.experiment)
    start = setup.params.space.to_gains(setup.params.space.start_u)
    results = []
    for _ in range(3):  # the reference (from rest) and the start measured again, twice
        bench.measure(start)
        results.append(bench.runner.result())
    return results, setup.drive.machine, plant.machine


@pytest.mark.parametrize(
    ('name', 'realism', 'scale'),
    [
        ('paper_750w', 'ideal', {}),
        ('paper_750w', 'ideal', {'J': 2.0}),
        ('im750w-j1', 'bench', {'J': 0.5}),
        ('im7500w-j10', 'bench', {'J': 1.5, 'Rr': 1.3, 'Lm': 0.85, 'coulomb': 0.02}),
    ],
)
def test_the_start_identifies_the_plant_not_the_file(name, realism, scale):
    results, told, plant = _start_experiments(name, realism, **scale)
    idf = identify([r.motion for r in results[1:]], told)
    assert idf is not None and idf.experiments == 2
    assert idf.J_file == told.J
    # measured on this machine: |error| 0.0-1.7 % on every case; the issue asks 10 %
    assert abs(idf.J / plant.J - 1.0) < 0.03
    assert abs(idf.Kt / plant.Kt - 1.0) < 0.03
    assert idf.J_sd < 0.05 * idf.J
    if 'coulomb' in scale:  # 2 % of the rated torque, seen against the file's 0.02 N m
        assert abs(idf.Tc - plant.coulomb_torque) < 2.0 * idf.Tc_sd


@pytest.mark.parametrize(
    ('name', 'realism', 'seed', 'scale'),
    [
        # the worst cases without the floor (research/identify_sd.py), J then Kt
        ('im750w-j1', 'bench', 2, {}),
        ('im3700w-j1', 'bench', 1, {'J': 1.5, 'Rr': 1.3, 'Lm': 0.85, 'coulomb': 0.02}),
        # the study's wrong plant on the small and the large drive, command delay 2 too
        ('im750w-j1', 'bench', 1, {'J': 1.5, 'Rr': 1.3, 'Lm': 0.85, 'coulomb': 0.02, 'delay': 2}),
        ('im7500w-j10', 'bench', 1, {'J': 1.5, 'Rr': 1.3, 'Lm': 0.85, 'coulomb': 0.02, 'delay': 2}),
        ('im750w-j10', 'bench', 1, {'J': 2.5}),
        ('im7500w-j1', 'ideal', 1, {'J': 0.5}),
    ],
)
def test_the_plant_is_within_two_standard_deviations(name, realism, seed, scale):
    """The reported sd covers the error: J and Kt of the plant within 2 sd of what the
    start's experiments identify, the model's own error (``MODEL_ERROR``) included."""
    results, told, plant = _start_experiments(name, realism, seed=seed, **scale)
    idf = identify([r.motion for r in results[1:]], told)
    assert idf is not None
    assert idf.J_sd >= MODEL_ERROR * idf.J and idf.Kt_sd >= MODEL_ERROR * idf.Kt
    assert abs(idf.J - plant.J) <= 2.0 * idf.J_sd, (idf.J / plant.J - 1, idf.J_sd / idf.J)
    assert abs(idf.Kt - plant.Kt) <= 2.0 * idf.Kt_sd, (idf.Kt / plant.Kt - 1, idf.Kt_sd / idf.Kt)


def test_the_start_ripple_is_the_papers_fig_8():
    """The hand-tuned start on the paper drive: 1.5 A peak-to-peak, 0.15-0.20 A rms
    (as measured from the report's Fig. 8)."""
    results, _, _ = _start_experiments('paper_750w', 'ideal')
    rms1, pp1, rms2, pp2 = results[1].ripple
    assert 0.12 < rms1 < 0.18 and 0.17 < rms2 < 0.23
    assert 1.4 < pp1 < 1.6 and 1.4 < pp2 < 1.6
