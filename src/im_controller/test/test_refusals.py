"""Refusals and parameters, pure: which code a start, a fault reset or a parameter change
is refused with in each runner state, and the parameters -> configuration step."""

from __future__ import annotations

import math

import numpy as np
import pytest

from im_controller.config import ExperimentConfig, Gains
from im_controller.contract import (
    BUSY,
    FINISHING_MOVE,
    INVALID,
    NO_DRIVE_STATE,
    SAFETY_FAULT,
    STATE_NOT_FINITE,
    refusal_code,
)
from im_controller.layout import MODE_RETURN, R_MODE, REASON_DRIVE_TIMEOUT
from im_controller.parameters import (
    READ_ONLY_SECTIONS,
    TUNABLE_SECTIONS,
    ControllerError,
    check_isq_max,
    configuration,
    section_defaults,
)
from im_controller.refusals import change_refusal, reset_refusal, start_refusal
from im_controller.runner import ExperimentRunner


def code(message: str | None) -> str | None:
    return None if message is None else refusal_code(message)


def test_start_refusals_by_runner_state():
    r = ExperimentRunner()
    assert code(start_refusal(r, False, 'x')) == NO_DRIVE_STATE
    assert start_refusal(r, True, 'x') is None
    r.start(0)
    assert code(start_refusal(r, True, 'x')) == BUSY
    r.abort_external(REASON_DRIVE_TIMEOUT, 0)
    refused = start_refusal(r, True, '`the reset`')
    assert code(refused) == SAFETY_FAULT
    assert 'drive_state_timeout' in refused and '`the reset`' in refused


def test_a_change_of_tunables_waits_for_the_experiment_but_structure_checks_do_not():
    r = ExperimentRunner()
    assert change_refusal([('k_pw', 1.0), ('loss.a1', 2.0)], r) is None
    assert code(change_refusal([('k_pw', math.nan)], r)) == INVALID
    r.start(0)
    assert code(change_refusal([('trajectory.a_max', 500.0)], r)) == BUSY
    # not a tunable: only the value checks apply while an experiment runs
    assert change_refusal([('safety.max_speed', 50.0)], r) is None
    assert code(change_refusal([('safety.max_speed', math.inf)], r)) == INVALID


def test_a_tunable_change_after_a_supervisor_stop_waits_for_the_move():
    r = ExperimentRunner()
    r.R[R_MODE] = MODE_RETURN  # the fallback gains finish a stopped move
    assert not (r.running or r.ready or r.faulted)
    assert code(change_refusal([('k_iw', 10.0)], r)) == FINISHING_MOVE
    assert code(start_refusal(r, True, 'x')) == FINISHING_MOVE


def test_reset_refusals():
    sane = np.array([5.0, 1e6, 0.25, 0.0])
    assert code(reset_refusal(None, None)) == NO_DRIVE_STATE
    assert code(reset_refusal(np.array([5.0, 1e6, math.nan, 0.0]), None)) == STATE_NOT_FINITE
    assert code(reset_refusal(np.array([5.0, 1e6, 0.0, -math.inf]), None)) == STATE_NOT_FINITE
    silent = reset_refusal(sane, 1.25)
    assert code(silent) == NO_DRIVE_STATE and '1.2 s ago' in silent
    assert reset_refusal(sane, None) is None


def test_the_default_parameters_make_the_default_configuration():
    values = dict(section_defaults({**TUNABLE_SECTIONS, **READ_ONLY_SECTIONS}))
    values.update(
        zip(('k_pw', 'k_iw', 'k_pos', 'tau_sm', 'tau_eq'), Gains().as_tuple(), strict=True)
    )
    d = ExperimentConfig()
    cfg, gains = configuration(values.__getitem__, d.control.Ts, d.control.isq_max)
    assert cfg == d and gains == Gains()
    assert 'control.Ts' not in values and 'control.isq_max' not in values  # from the drive


def test_the_isq_clamp_can_only_be_tightened():
    assert check_isq_max(5.0, 6.0) == 5.0
    for bad in (6.5, 0.0, math.nan, 5):
        with pytest.raises(ControllerError, match=r'safety\.isq_max'):
            check_isq_max(bad, 6.0)
