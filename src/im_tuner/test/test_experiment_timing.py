"""The experiment on the drive's timeline: exactly N drive periods counted by step_index,
each classified fresh / late / held from the state's applied_step, and the ``timing``
flag against the tolerance. Pure core (no ROS): the drive core and the runner."""

from __future__ import annotations

import numpy as np
import pytest

from im_controller.config import Gains
from im_controller.layout import Q_SETTLE_N, STATUS_DONE
from im_controller.runner import ExperimentRunner, config_for_drive
from im_drive_sim.contract import STATE_INDEX
from im_drive_sim.sim import STATE_FIELDS, DriveSim
from im_tuner.offline import run_experiment_offline

A = STATE_INDEX['applied_step']
N = 5625


def _run(pattern, tolerance: int = 0):
    """Drive the core in real-time fashion: ``pattern(n)`` says what happens to the
    controller's answer to the experiment's state n (n < 0: its settle): 'fresh' (in
    time), 'late' (applied one period later), 'skip' (the controller never sees that
    state: the drive holds)."""
    sim = DriveSim(seed=1)
    sim.reset(omega=0.0, fluxed=True)
    runner = ExperimentRunner(config_for_drive(None, sim), Gains(), timing_tolerance=tolerance)
    state = np.zeros(len(STATE_FIELDS))
    sim.read_into(state)
    runner.reset(float(state[2]))
    runner.start(0)
    settle = int(runner.Q[Q_SETTLE_N])  # state `settle` is the experiment's step 0
    held = (0.0, 0.0, -1)  # the command the drive holds: isq, load, answers
    pending = None  # a late answer, applied one period later
    res = None
    for _ in range(settle + N + 200):
        k = int(state[0])
        how = pattern(k - settle)
        if pending is not None:
            held, pending = pending, None
        if how != 'skip':
            isq, load, status = runner.step(state)
            if how == 'fresh':
                held = (isq, load, k)
            else:
                pending = (isq, load, k)
            if status >= STATUS_DONE:
                res = runner.result()
                break
        sim.step_into(held[0], held[1], state)
        state[A] = held[2]
    assert res is not None
    return res


def test_all_fresh_is_exactly_n_periods_and_not_flagged():
    r = _run(lambda k: 'fresh')
    assert (r.steps, r.fresh, r.held, r.late, r.timing) == (N, N, 0, 0, False)
    assert r.t_end - r.t_start == N * 200_000


def test_all_fresh_equals_the_lockstep_loss_bit_for_bit():
    sim = DriveSim(seed=1)
    sim.reset(omega=0.0, fluxed=True)
    lock, _ = run_experiment_offline(sim, Gains(), record=False)
    rt = _run(lambda k: 'fresh')
    assert rt.loss == lock.loss and rt.terms == lock.terms
    assert (lock.fresh, lock.held, lock.late, lock.timing) == (N, 0, 0, False)


def test_skipped_states_count_as_held_on_the_drive_timeline():
    # the controller misses 3 states in the middle: the experiment still ends after
    # exactly N drive periods, and the 3 unseen periods plus the 3 periods driven by a
    # held command (the state after each skipped one) are counted
    skipped = {1000, 2000, 3000}
    r = _run(lambda k: 'skip' if k in skipped else 'fresh')
    assert r.steps == N and r.t_end - r.t_start == N * 200_000
    assert (r.fresh, r.held, r.late) == (N - 6, 6, 0)
    assert r.timing


def test_an_experiment_whose_last_state_went_unseen_ends_after_exactly_n_periods():
    # the controller misses the experiment's last two states: the result comes with the
    # next state it sees, still exactly N periods long, the unseen ones counted held
    r = _run(lambda k: 'skip' if k in (N - 2, N - 1) else 'fresh')
    assert r.steps == N and r.t_end - r.t_start == N * 200_000 and not r.aborted
    assert (r.fresh, r.held, r.late) == (N - 2, 2, 0) and r.timing


def test_late_answers_are_counted_late():
    r = _run(lambda k: 'late' if k in (10, 11) else 'fresh')
    # the answer to 10 comes a period late: the drive holds the answer to 9 over 10->11
    # (state 11: held) and applies the late answer to 10 over 11->12 (state 12: late);
    # the late answer to 11 is overtaken by the fresh answer to 12 (state 13: fresh)
    assert (r.fresh, r.held, r.late) == (N - 2, 1, 1)
    assert r.timing


@pytest.mark.parametrize('tol, flagged', [(5, True), (6, False)])
def test_tolerance_decides_the_flag(tol, flagged):
    skipped = {1000, 2000, 3000}
    r = _run(lambda k: 'skip' if k in skipped else 'fresh', tolerance=tol)
    assert r.held + r.late == 6 and r.timing is flagged


def test_tolerance_must_be_a_non_negative_integer():
    for bad in (-1, 1.5, True, '2'):
        with pytest.raises(ValueError, match='timing_tolerance'):
            ExperimentRunner(timing_tolerance=bad)
