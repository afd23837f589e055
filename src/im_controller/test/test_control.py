"""Control law: hand-computed steps, pass-through, feed-forward readings, clamp, anti-windup."""

from __future__ import annotations

import math

import numpy as np
import pytest

from im_controller.config import (
    ControlConfig,
    ControllerConfigError,
    Gains,
    validate_control_config,
    validate_gains,
)
from im_controller.control import (
    C_KPW,
    CONTROL_FIELDS,
    N_CONTROL_FIELDS,
    N_CSTATE,
    O_SAT,
    control_reset,
    control_step,
    make_control_params,
)
from im_controller.runner import ExperimentRunner

TS = 2e-4
ISQ_MAX = 7.0


class CascadeController:
    """The control kernels on their own arrays (parameters C, state X, internals), with
    ``gains`` (default: the hand-tuned start) and ``control`` (default: Ts 2e-4 s, 7 A)."""

    def __init__(self, gains: Gains | None = None, control: ControlConfig | None = None) -> None:
        ctl = validate_control_config(ControlConfig() if control is None else control)
        self.C = make_control_params(validate_gains(Gains() if gains is None else gains), ctl)
        self.X = np.zeros(N_CSTATE)
        self.internals = np.zeros(N_CONTROL_FIELDS)

    def reset(self, theta_meas: float) -> None:
        control_reset(self.X, theta_meas)

    def step(self, theta_ref: float, theta_meas: float, omega_meas: float) -> float:
        return float(
            control_step(self.X, self.C, theta_ref, theta_meas, omega_meas, self.internals)
        )

    @property
    def saturated(self) -> bool:
        return bool(self.internals[O_SAT] != 0.0)

    def internals_dict(self) -> dict[str, float]:
        return {n: float(self.internals[i]) for i, n in enumerate(CONTROL_FIELDS)}


def hand_steps(g: Gains, refs, meas, ff: str = 'model'):
    """Independent scalar re-implementation of the documented equations."""
    a_sm = math.exp(-TS / g.tau_sm) if g.tau_sm > 0 else 0.0
    a_eq = math.exp(-TS / g.tau_eq) if g.tau_eq > 0 else 0.0
    sm = m = meas[0][0]
    integ = 0.0
    outs = []
    for r, (th, w) in zip(refs, meas, strict=True):
        sm_new = a_sm * sm + (1 - a_sm) * r
        m_new = a_eq * m + (1 - a_eq) * sm_new
        wff = (m_new - m) / TS if ff == 'model' else (sm_new - sm) / TS
        e_th = m_new - th
        wref = g.k_pos * e_th + wff
        ew = wref - w
        p = g.k_pw * ew
        cand = integ + g.k_iw * TS * ew
        if not ((p + cand > ISQ_MAX and ew > 0) or (p + cand < -ISQ_MAX and ew < 0)):
            integ = min(max(cand, -ISQ_MAX), ISQ_MAX)
        u = p + integ
        isq = min(max(u, -ISQ_MAX), ISQ_MAX)
        sm, m = sm_new, m_new
        outs.append(
            {
                'theta_ref': r,
                'theta_sm': sm,
                'theta_m': m,
                'omega_ff': wff,
                'omega_ref': wref,
                'e_theta': e_th,
                'e_omega': ew,
                'p_term': p,
                'i_term': integ,
                'isq_ref': isq,
                'saturated': float(u != isq),
            }
        )
    return outs


def test_three_steps_by_hand_default_gains():
    g = Gains()
    c = CascadeController(g)
    c.reset(0.0)
    # step 0: theta* jumps to 0.01 rad, motor at rest
    a_sm = math.exp(-TS / 0.005)  # 0.960789439152323
    a_eq = math.exp(-TS / 0.007)  # 0.971833136...
    sm1 = (1 - a_sm) * 0.01
    m1 = (1 - a_eq) * sm1
    wff1 = m1 / TS
    wref1 = 30.0 * m1 + wff1
    isq1 = 0.53 * wref1 + 20.0 * TS * wref1
    assert c.step(0.01, 0.0, 0.0) == pytest.approx(isq1, rel=1e-15)
    d = c.internals_dict()
    assert d['theta_sm'] == pytest.approx(3.9210560847677e-4, rel=1e-12)
    assert d['theta_m'] == pytest.approx(sm1 * (1 - a_eq), rel=1e-15)
    assert d['omega_ff'] == pytest.approx(wff1, rel=1e-15)
    assert d['i_term'] == pytest.approx(20.0 * TS * wref1, rel=1e-15)
    assert d['saturated'] == 0.0
    # steps 1, 2 with a moving measurement, against the scalar re-implementation
    refs = [0.01, 0.01, 0.01]
    meas = [(0.0, 0.0), (0.0001, 0.3), (0.0003, 0.6)]
    exp = hand_steps(g, refs, meas)
    c.reset(0.0)
    for r, (th, w), e in zip(refs, meas, exp, strict=True):
        c.step(r, th, w)
        got = c.internals_dict()
        for k in CONTROL_FIELDS:
            assert got[k] == pytest.approx(e[k], rel=1e-14, abs=1e-18), k


def test_undelayed_feedforward_reading():
    g = Gains()
    c = CascadeController(g, ControlConfig(feedforward='undelayed'))
    c.reset(0.5)
    refs = [0.6, 0.7, 0.8, 0.8]
    meas = [(0.5, 0.0), (0.5, 1.0), (0.51, 2.0), (0.52, 2.0)]
    exp = hand_steps(g, refs, meas, ff='undelayed')
    for r, (th, w), e in zip(refs, meas, exp, strict=True):
        c.step(r, th, w)
        got = c.internals_dict()
        assert got['omega_ff'] == pytest.approx(e['omega_ff'], rel=1e-14)
        assert got['isq_ref'] == pytest.approx(e['isq_ref'], rel=1e-14)


def test_zero_time_constants_are_pass_through_with_finite_feedforward():
    c = CascadeController(Gains(tau_sm=0.0, tau_eq=0.0))
    c.reset(1.0)
    c.step(1.25, 1.0, 0.0)
    d = c.internals_dict()
    assert d['theta_sm'] == 1.25 and d['theta_m'] == 1.25  # exact pass-through
    assert d['omega_ff'] == pytest.approx(0.25 / TS, rel=1e-12)  # backward difference
    c.step(1.25, 1.0, 0.0)
    assert c.internals_dict()['omega_ff'] == 0.0
    assert all(math.isfinite(v) for v in c.internals)


def test_feedforward_tends_to_model_derivative_for_large_tau():
    # mean derivative over the step -> (theta_sm - theta_m)/tau_eq when tau_eq >> Ts
    c = CascadeController(Gains(tau_sm=0.0, tau_eq=0.05))
    c.reset(0.0)
    c.step(1.0, 0.0, 0.0)
    d = c.internals_dict()
    assert d['omega_ff'] == pytest.approx((1.0 - d['theta_m']) / 0.05, rel=3e-3)


def test_clamp_and_saturated_flag():
    c = CascadeController(Gains(k_pw=1.0, k_iw=0.0))
    c.reset(0.0)
    assert c.step(0.0, 0.0, -100.0) == ISQ_MAX and c.saturated
    assert c.step(0.0, 0.0, 100.0) == -ISQ_MAX and c.saturated
    assert c.step(0.0, 0.0, 1.0) == pytest.approx(-1.0) and not c.saturated


def test_anti_windup_integrator_stops_and_recovers_at_once():
    g = Gains(k_pw=0.5, k_iw=100.0, k_pos=0.0, tau_sm=0.0, tau_eq=0.0)
    c = CascadeController(g)
    c.reset(0.0)
    # speed error +20 rad/s: P = 10 A alone saturates; the integrator must stay frozen at 0
    for _ in range(1000):
        assert c.step(0.0, 0.0, -20.0) == ISQ_MAX
    assert c.internals_dict()['i_term'] == 0.0
    # error reverses: output leaves the clamp in the very first step (naive PI: 0.2 s later)
    out = c.step(0.0, 0.0, 4.0)
    assert out == pytest.approx(-0.5 * 4.0 - 100.0 * TS * 4.0, rel=1e-12)
    assert not c.saturated
    # conditional integration: frozen when the candidate output would pass the clamp
    c.reset(0.0)
    c.step(0.0, 0.0, -13.0)  # P = 6.5, I = 0.26 -> 6.76 (inside)
    assert not c.saturated
    # P + I + k_iw Ts e = 7.02 > isq_max: frozen at 0.26, output stays 6.76 (unclamped)
    assert c.step(0.0, 0.0, -13.0) == pytest.approx(6.76, rel=1e-12)
    assert c.internals_dict()['i_term'] == pytest.approx(0.26, rel=1e-12)


def test_integrator_bounded_after_gain_change():
    c = CascadeController(Gains(k_pw=0.0, k_iw=500.0, k_pos=0.0))
    c.reset(0.0)
    for _ in range(100):
        c.step(0.0, 0.0, -1.0)
    assert c.internals_dict()['i_term'] <= ISQ_MAX


def test_set_gains_rejects_and_keeps_previous():
    r = ExperimentRunner()
    before = r.C.copy()
    with pytest.raises(ControllerConfigError, match=r'gains\.k_pos'):
        r.set_gains(Gains(k_pos=1e4))
    assert np.array_equal(r.C, before) and r.gains == Gains()
    r.set_gains(Gains(k_pw=1.0))
    assert r.gains.k_pw == 1.0 and r.C[C_KPW] == 1.0


def test_reset_rejects_non_finite():
    with pytest.raises(ValueError, match='theta_meas'):
        ExperimentRunner().reset(float('nan'))
