"""Experiment: trajectory, loss (eq. 4-7), supervisor, safety, runner API, config validation,
determinism.  Everything runs against the pure drive core (no ROS); no sleeps, no timing."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from im_controller.config import (
    ControlConfig,
    ControllerConfigError,
    ExperimentConfig,
    Gains,
    LossConfig,
    SafetyConfig,
    TrajectoryConfig,
    validate_experiment_config,
    validate_gains,
)
from im_controller.control import O_THETA_REF
from im_controller.layout import (
    E_LOAD,
    E_N,
    Q_SETTLE_N,
    R_S1,
    R_S2,
    R_S3,
    STATUS_ABORTED,
    STATUS_DONE,
    STATUS_RUNNING,
)
from im_controller.runner import ExperimentRunner
from im_controller.trajectory import trajectory, trajectory_times
from im_drive_sim.sim import STATE_FIELDS

TS = 2e-4
UNSTABLE = Gains(k_pw=0.05, k_iw=20.0, k_pos=300.0, tau_sm=0.005, tau_eq=0.007)


# ----------------------------------------------------------------------- trajectory
def test_trapezoid_times_and_shape():
    t_acc, _t_dec, t_end, v = trajectory_times(math.pi, 600.0, 40.0)
    assert t_acc == pytest.approx(1 / 15, rel=1e-15)
    assert t_end == pytest.approx(2 / 15 + (math.pi - 8 / 3) / 40, rel=1e-15)
    assert round(t_end, 4) == 0.1452 and v == 40.0
    t = np.arange(0, 1.125, TS)
    pos, vel, acc = trajectory(t)
    assert pos[0] == 0.0 and vel.max() == 40.0
    assert set(np.unique(acc)) == {-600.0, 0.0, 600.0}
    assert np.all(pos[t >= t_end] == math.pi)  # exactly pi, held
    assert np.all(np.diff(pos) >= 0.0)
    # the speed is the derivative of the position (central differences)
    dpos = (pos[2:] - pos[:-2]) / (2 * TS)
    assert np.max(np.abs(dpos - vel[1:-1])) < 600.0 * TS  # one accel step at kinks
    # the sampled distance at t_acc and the cruise area
    assert trajectory(np.array([t_acc]))[0][0] == pytest.approx(40.0**2 / 1200.0, rel=1e-12)


def test_triangular_case():
    cfg = ExperimentConfig(trajectory=TrajectoryConfig(distance=1.0))
    t_acc, t_dec, _t_end, v = trajectory_times(1.0, 600.0, 40.0)
    assert t_acc == t_dec == pytest.approx(math.sqrt(1 / 600), rel=1e-15)
    assert v == pytest.approx(600 * math.sqrt(1 / 600), rel=1e-15) and v < 40.0
    pos, vel, _ = trajectory(np.arange(0, 0.2, TS), cfg)
    assert pos[-1] == 1.0 and vel.max() <= v
    mid = trajectory(np.array([t_acc]), cfg)[0][0]
    assert mid == pytest.approx(0.5, rel=1e-12)


def _reference_and_load(theta0: float, load_sign: str) -> tuple[ExperimentRunner, list, list]:
    """Experiment 1 (odd: a -distance move) from ``theta0`` with the motor held at rest
    (limits and supervisor out of the way): the runner, theta* and the load per step."""
    cfg = ExperimentConfig(
        loss=LossConfig(threshold1=1e12, threshold2=1e12, threshold3=1e12),
        trajectory=TrajectoryConfig(settle=0.0, load_sign=load_sign),
        safety=SafetyConfig(max_position_error=1e3),
    )
    r = ExperimentRunner(cfg)
    r.reset(theta0)
    r.start(1)
    ref, load, status = [], [], []
    for k in range(5625):
        status.append(r.step(_state(k, theta0))[2])
        ref.append(float(r.cout[O_THETA_REF]))
        load.append(float(r.eout[E_LOAD]))
    assert status[-1] == STATUS_DONE and all(s == STATUS_RUNNING for s in status[:-1])
    return r, ref, load


def test_experiment_reference_and_load_profile():
    r, ref, load = _reference_and_load(2.0, 'oppose_move')
    assert r.target == pytest.approx(2.0 - math.pi)
    on = np.nonzero(load)[0]
    assert on[0] == 3500 and len(on) == 2125  # 0.7 s .. 1.125 s
    assert np.all(np.array(load)[on] == -1.75)  # opposes the -pi move
    assert ref[-1] == 2.0 - math.pi
    _r, _ref, fixed = _reference_and_load(0.0, 'fixed')
    assert np.all(np.array(fixed[3500:]) == 1.75)


# ------------------------------------------------------------------------------ loss


# ------------------------------------------------------------------------ supervisor


# ---------------------------------------------------------------------------- safety


def test_repeated_step_index_is_answered_once():
    r = ExperimentRunner(ExperimentConfig(trajectory=TrajectoryConfig(settle=0.0)))
    r.reset(0.0)
    r.start(0)
    st = np.zeros(len(STATE_FIELDS))
    st[:4] = [10, 2_000_000, 0.0, 0.0]
    first = r.step(st)
    assert first[2] == STATUS_RUNNING
    st[3] = 5.0  # a re-sent state must not step the controller
    assert r.step(st) == first
    assert r.R[1] == 1.0  # one experiment step consumed


def _state(k: int, theta: float = 0.0, omega: float = 0.0) -> np.ndarray:
    st = np.zeros(len(STATE_FIELDS))
    st[:4] = [k, k * 200_000, theta, omega]
    st[STATE_FIELDS.index('applied_step')] = k - 1
    return st


def test_the_settle_holds_with_the_fallback_gains_then_step_0_takes_the_candidate():
    """An experiment begins with trajectory.settle (0.5 s = 2500 periods) of standstill on
    the drive's timeline: the fallback gains hold, no load, no loss; the first state after
    it is step 0, from which the candidate acts and the loss counts."""
    cand = Gains(k_pw=2.0, k_iw=100.0, k_pos=60.0, tau_sm=0.0, tau_eq=0.0)
    r = ExperimentRunner()
    r.reset(0.0)
    r.start(0, cand)
    assert r.running and int(r.Q[Q_SETTLE_N]) == 2500
    # during the settle: the hand-tuned (fallback) gains answer a 1 mrad error, status
    # running, the local step negative, no load, nothing summed
    isq, load, status = r.step(_state(100, theta=-1e-3))
    hand = ExperimentRunner()
    hand.reset(0.0)
    assert isq == pytest.approx(hand.step(_state(100, theta=-1e-3))[0], rel=1e-15)
    assert (load, status, r.eout[E_N]) == (0.0, STATUS_RUNNING, -2500.0)
    with pytest.raises(RuntimeError, match='running'):
        r.set_gains(Gains())  # the experiment is under way
    for k in range(101, 2600):
        isq, load, status = r.step(_state(k))
        assert status == STATUS_RUNNING and load == 0.0 and r.eout[E_N] == k - 2600
    assert r.R[R_S1] == r.R[R_S2] == r.R[R_S3] == 0.0
    # state 2600 = 100 + 2500 is step 0: the candidate's proportional gain answers
    r.step(_state(2600, omega=-1e-3))
    assert r.eout[E_N] == 0.0 and r.cout[9] == pytest.approx(r.cout[7] + r.cout[8])
    assert r.cout[7] == pytest.approx(cand.k_pw * r.cout[6], rel=1e-12)  # P = k_pw e_w


def test_a_fault_in_the_settle_ends_the_experiment_aborted_before_step_0():
    r = ExperimentRunner()
    r.reset(0.0)
    r.start(3)
    r.step(_state(50))
    _isq, _load, status = r.step(_state(51, theta=float('nan')))
    assert status == STATUS_ABORTED and r.faulted
    res = r.result()
    assert res is not None and res.aborted and res.reason == 'non_finite_measurement'
    assert res.steps == 0 and res.t_start == 51 * 200_000 and res.trip_step == -1


# -------------------------------------------------------- consecutive experiments


# ---------------------------------------------------------------------- determinism


# ---------------------------------------------------------------------------- config
def _bad_values():
    return [float('nan'), float('inf'), -float('inf'), True, '1.0', None]


GAIN_BAD = [
    ('k_pw', 200.01),
    ('k_pw', -0.1),
    ('k_iw', 20000.1),
    ('k_pos', 301.0),
    ('k_pos', -1.0),
    ('tau_sm', 0.11),
    ('tau_eq', -1e-3),
]


@pytest.mark.parametrize(
    'name,value',
    GAIN_BAD
    + [(n, v) for n in ('k_pw', 'k_iw', 'k_pos', 'tau_sm', 'tau_eq') for v in _bad_values()],
)
def test_bad_gains_rejected_with_name(name, value):
    with pytest.raises(ControllerConfigError, match=rf'gains\.{name} must be'):
        validate_gains(dataclasses.replace(Gains(), **{name: value}))


def test_gain_ranges_contain_the_search_box_and_accept_ints():
    validate_gains(Gains(0.05, 0, 1, 0, 0))
    g = validate_gains(Gains(3, 200, 150, 0.05, 0.05))
    assert isinstance(g.k_iw, float)
    validate_gains(Gains(200.0, 20000.0, 300.0, 0.1, 0.1))


SECTION_BAD = [
    ('control', 'Ts', 0.0),
    ('control', 'Ts', -1e-4),
    ('control', 'isq_max', 0.0),
    ('control', 'feedforward', 'delayed'),
    ('control', 'feedforward', 1),
    ('loss', 'a1', -1.0),
    ('loss', 'a2', -0.1),
    ('loss', 'a3', 1e7),
    ('loss', 'threshold1', 0.0),
    ('loss', 'threshold2', -1.0),
    ('loss', 'threshold3', 0.0),
    ('loss', 'penalty', 0.5),
    ('loss', 'isqf_tau', 0.0),
    ('loss', 'sat_ratio', 1.5),
    ('loss', 'sat_ratio', 0.0),
    ('trajectory', 'distance', 0.0),
    ('trajectory', 'a_max', -600.0),
    ('trajectory', 'v_max', 0.0),
    ('trajectory', 'duration', 0.0),
    ('trajectory', 'load_delay', -0.1),
    ('trajectory', 'load_delay', 2.0),
    ('trajectory', 'load_torque', -1.0),
    ('trajectory', 'load_sign', 'up'),
    ('trajectory', 'duration', 1.12501),
    ('safety', 'max_position_error', 0.0),
    ('safety', 'max_speed', -1.0),
]
NUMERIC = [(s, n) for s, n, v in SECTION_BAD if not isinstance(v, str) and n != 'feedforward']


@pytest.mark.parametrize(
    'section,name,value',
    SECTION_BAD + [(s, n, v) for s, n in dict.fromkeys(NUMERIC) for v in _bad_values()],
)
def test_bad_experiment_config_rejected_with_name(section, name, value):
    cfg = ExperimentConfig()
    sub = dataclasses.replace(getattr(cfg, section), **{name: value})
    bad = dataclasses.replace(cfg, **{section: sub})
    with pytest.raises(ControllerConfigError, match=rf'{section}\.{name} must'):
        validate_experiment_config(bad)


def test_fallback_gains_and_types_checked():
    with pytest.raises(ControllerConfigError, match=r'fallback_gains\.k_pos'):
        validate_experiment_config(ExperimentConfig(fallback_gains=Gains(k_pos=float('nan'))))
    with pytest.raises(ControllerConfigError, match='control must be a ControlConfig'):
        validate_experiment_config(ExperimentConfig(control={'Ts': 2e-4}))  # type: ignore
    with pytest.raises(ValueError):
        ExperimentRunner().start(-1)
    with pytest.raises(ValueError, match='experiment_id'):
        ExperimentRunner().start(True)  # type: ignore[arg-type]


def test_defaults_are_valid_and_documented_values():
    cfg = validate_experiment_config(ExperimentConfig())
    assert cfg == ExperimentConfig()
    assert Gains().as_tuple() == (0.53, 20.0, 30.0, 0.005, 0.007)
    assert (cfg.loss.a1, cfg.loss.a2, cfg.loss.a3) == (8.0, 0.5, 1.1)
    assert ControlConfig().feedforward == 'model'
