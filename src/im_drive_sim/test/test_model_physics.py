"""Physics of the full and reduced models against closed forms (docs/drive-model.md)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from numba import njit

try:  # source checkout without an installed package (the lead's packaging installs it)
    import im_drive_sim  # noqa: F401
except ImportError:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from im_drive_sim import analytic as A, model_layout as L, plant
from im_drive_sim.drive_file import load_config
from im_drive_sim.sim import DriveSim

TS = 200e-6


# ----------------------------------------------------------------- steady state
def _steady_run(slip: float, u_peak: float, ts: float, f: float = 50.0):
    """Bare model fed with balanced voltages, speed held by a huge inertia and a load torque
    equal to the analytic electromagnetic torque (B = 0), run 1 s from de-energised."""
    cfg = load_config(overrides={'machine.J': 1e9, 'machine.B': 0.0, 'Ts': ts})
    ss = A.steady_state(cfg.machine, u_peak, f, slip)
    sim = DriveSim(cfg)
    sim.reset(omega=ss.omega_mech, fluxed=False)
    n = round(1.0 / ts)
    w = 2.0 * math.pi * f
    x = 0.5 * w * ts
    # ZOH staircase sampled at mid-step, amplitude corrected by x/sin(x) so that its
    # fundamental is exactly the wanted sinusoid (average of the phasor over the step).
    amp = u_peak * x / math.sin(x)
    t_mid = (np.arange(n) + 0.5) * ts
    r = sim.run_voltage(amp * np.cos(w * t_mid), amp * np.sin(w * t_mid), ss.torque)
    return sim, r, ss


# At Ts = 20 us the staircase (ZOH) harmonics are negligible (~1e-5) and the comparison tests
# the model equations to 1e-3 as asked; at the production Ts = 200 us the current sampled at
# the step boundaries carries the ZOH ripple (measured 1.2e-3 at rated torque) while the
# slow rotor flux still matches to 1e-7: a looser check documents that.
@pytest.mark.parametrize(
    'torque,ts,rel', [(2.5, 20e-6, 1e-3), (1.0, 20e-6, 1e-3), (2.5, 200e-6, 3e-3)]
)
def test_steady_state_matches_equivalent_circuit(torque: float, ts: float, rel: float) -> None:
    m = load_config().machine
    u = A.phase_peak_from_line_rms(220.0)
    assert u == pytest.approx(179.6, abs=0.05)
    slip = A.slip_for_torque(m, u, 50.0, torque)
    sim, r, ss = _steady_run(slip, u, ts)
    last = slice(-round(0.02 / ts), None)  # one full 50 Hz period
    i_amp = np.hypot(r['i_alpha'][last], r['i_beta'][last])
    te = r['torque'][last]
    # rotating-phasor steady state: amplitude and torque constant, so means are the values
    assert np.mean(i_amp) == pytest.approx(ss.i_s_peak, rel=rel)
    assert np.ptp(i_amp) < 1e-6 * ss.i_s_peak
    assert np.mean(te) == pytest.approx(ss.torque, rel=rel)
    # power factor from the fundamental: angle between the voltage phasor u(t_k) (not the
    # staircase value) and the sampled current at t_k
    t = (np.arange(r['i_alpha'].shape[0]) + 1) * ts
    w = 2.0 * math.pi * 50.0
    cur = r['i_alpha'][last] + 1j * r['i_beta'][last]
    pf = np.mean(np.cos(np.angle(cur * np.exp(-1j * w * t[last]))))
    assert pf == pytest.approx(ss.power_factor, rel=rel)
    assert np.mean(r['psi_r'][last]) == pytest.approx(abs(ss.psi_r), rel=1e-4)
    # speed held: the huge inertia moved it by less than 1e-6 rad/s
    assert abs(sim.omega - ss.omega_mech) < 1e-6


def test_reference_figures_from_notes() -> None:
    m = load_config().machine
    u = A.phase_peak_from_line_rms(220.0)
    s = A.slip_for_torque(m, u, 50.0, m.rated_torque)
    ss = A.steady_state(m, u, 50.0, s)
    assert ss.torque == pytest.approx(2.5, rel=1e-9)
    assert ss.speed_rpm == pytest.approx(2858.0, abs=10.0)  # notes: 2858 rpm
    assert ss.i_s_rms == pytest.approx(3.1, abs=0.1)  # notes: about 3.1 A
    assert ss.power_factor == pytest.approx(0.77, abs=0.01)  # notes: about 0.77
    assert abs(ss.psi_r) == pytest.approx(0.50, abs=0.02)  # rated flux 0.50 Wb
    # circuit power balance: P_in = stator + rotor copper + mechanical
    assert ss.p_in == pytest.approx(ss.p_cu_s + ss.p_cu_r + ss.p_mech, rel=1e-12)
    assert ss.p_cu_r == pytest.approx(s * ss.torque * ss.omega_supply / m.pole_pairs, rel=1e-12)
    fo = A.foc_steady_state(m, m.rated_flux_current, 2.5 / m.Kt, 0.0)
    assert fo['torque'] == pytest.approx(2.5)


# ------------------------------------------------------------------ flux build-up
def test_flux_buildup_follows_rotor_time_constant() -> None:
    sim = DriveSim()
    m = sim.config.machine
    sim.reset(fluxed=False)
    n = 3000  # 0.6 s
    r = sim.run(np.zeros(n), np.zeros(n))
    t = (np.arange(n) + 1) * TS
    psi = r['psi_r']
    isd = np.mean(r['isd'][-500:])
    assert isd == pytest.approx(m.rated_flux_current, rel=1e-4)
    psi_inf = m.Lm * isd
    # closed form with an ideal current step (the current loop adds ~1/wc = 0.67 ms delay)
    ref = np.array([A.flux_buildup(m, isd, ti) for ti in t])
    assert np.max(np.abs(psi - ref)) < 0.01 * psi_inf
    # log-linear fit of the decay on 20 ms .. 400 ms: tau within 2 % of Lr/Rr
    sel = (t > 0.02) & (t < 0.4)
    slope, _ = np.polyfit(t[sel], np.log(psi_inf - psi[sel]), 1)
    tau_fit = -1.0 / slope
    assert tau_fit == pytest.approx(m.tau_r, rel=0.02)
    # the current-model estimator (nominal parameters) tracks the true flux
    psi_hat = np.array([0.0])
    sim.reset(fluxed=False)
    est_err = 0.0
    for _k in range(1000):
        sim.step(0.0, 0.0)
        psi_hat[0] = sim.psi_hat
        est_err = max(est_err, abs(psi_hat[0] - sim.psi_r))
    assert est_err < 0.01 * psi_inf
    assert abs(sim.torque) < 1e-6  # isq* = 0, orientation exact: no torque


# --------------------------------------------------------------- energy balance
@njit
def _plant_powers(x: tuple, ua: float, ub: float, tl: float, P: np.ndarray):
    """Power terms [W] for the energy balance at x = (i_sa, i_sb, psi_ra, psi_rb, omega)
    (amplitude-invariant: factor 1.5).

    Returns (p_in = 1.5 u.i_s, p_cu_s = 1.5 Rs |i_s|^2, p_cu_r = 1.5 Rr |i_r|^2,
    p_friction = T_friction(omega) omega, p_load = T_L omega)
    with the rotor current i_r = (psi_r - Lm i_s)/Lr.
    """
    isa, isb, pa, pb, w = x
    ira = (pa - P[L.P_LM] * isa) / P[L.P_LR]
    irb = (pb - P[L.P_LM] * isb) / P[L.P_LR]
    tf = plant.friction_of(w, P)
    return (
        1.5 * (ua * isa + ub * isb),
        1.5 * P[L.P_RS] * (isa * isa + isb * isb),
        1.5 * P[L.P_RR] * (ira * ira + irb * irb),
        tf * w,
        tl * w,
    )


@njit
def _stored_energy(x: np.ndarray, P: np.ndarray):
    """(magnetic, kinetic) energy [J] of plant state x = [i_sa, i_sb, psi_ra, psi_rb, omega, ...].

    W_mag = 1.5 * 0.5 (Ls |i_s|^2 + 2 Lm i_s.i_r + Lr |i_r|^2),  W_kin = 0.5 J omega^2.
    """
    lm = P[L.P_LM]
    ira = (x[2] - lm * x[0]) / P[L.P_LR]
    irb = (x[3] - lm * x[1]) / P[L.P_LR]
    wm = 0.75 * (
        P[L.P_LS] * (x[0] * x[0] + x[1] * x[1])
        + 2.0 * lm * (x[0] * ira + x[1] * irb)
        + P[L.P_LR] * (ira * ira + irb * irb)
    )
    return wm, 0.5 * P[L.P_J] * x[4] * x[4]


@njit
def _plant_rk4_energy(
    x: np.ndarray, ua: float, ub: float, tl: float, P: np.ndarray, e: np.ndarray
) -> None:
    """RK4 step of the plant augmented with the energy integrals (diagnostics, tests).

    x[0:6] is advanced exactly as ``plant.plant_rk4`` does with the nominal rotor resistance (the
    augmented components do not feed back), e[0:5] += RK4 quadrature of ``_plant_powers``.
    """
    h = P[L.P_TS]
    h2 = 0.5 * h
    x0, x1, x2, x3, x4 = x[0], x[1], x[2], x[3], x[4]
    a0, a1, a2, a3, a4 = plant.plant_deriv(x0, x1, x2, x3, x4, ua, ub, tl, P, 1.0)
    pa_ = _plant_powers((x0, x1, x2, x3, x4), ua, ub, tl, P)
    y0, y1, y2, y3, y4 = x0 + h2 * a0, x1 + h2 * a1, x2 + h2 * a2, x3 + h2 * a3, x4 + h2 * a4
    b0, b1, b2, b3, b4 = plant.plant_deriv(y0, y1, y2, y3, y4, ua, ub, tl, P, 1.0)
    pb_ = _plant_powers((y0, y1, y2, y3, y4), ua, ub, tl, P)
    w2 = y4
    y0, y1, y2, y3, y4 = x0 + h2 * b0, x1 + h2 * b1, x2 + h2 * b2, x3 + h2 * b3, x4 + h2 * b4
    c0, c1, c2, c3, c4 = plant.plant_deriv(y0, y1, y2, y3, y4, ua, ub, tl, P, 1.0)
    pc_ = _plant_powers((y0, y1, y2, y3, y4), ua, ub, tl, P)
    w3 = y4
    y0, y1, y2, y3, y4 = x0 + h * c0, x1 + h * c1, x2 + h * c2, x3 + h * c3, x4 + h * c4
    d0, d1, d2, d3, d4 = plant.plant_deriv(y0, y1, y2, y3, y4, ua, ub, tl, P, 1.0)
    pd_ = _plant_powers((y0, y1, y2, y3, y4), ua, ub, tl, P)
    w4 = y4
    h6 = h / 6.0
    x[0] = x0 + h6 * (a0 + 2.0 * (b0 + c0) + d0)
    x[1] = x1 + h6 * (a1 + 2.0 * (b1 + c1) + d1)
    x[2] = x2 + h6 * (a2 + 2.0 * (b2 + c2) + d2)
    x[3] = x3 + h6 * (a3 + 2.0 * (b3 + c3) + d3)
    x[4] = x4 + h6 * (a4 + 2.0 * (b4 + c4) + d4)
    x[5] = x[5] + h6 * (x4 + 2.0 * (w2 + w3) + w4)
    for j in range(5):
        e[j] += h6 * (pa_[j] + 2.0 * (pb_[j] + pc_[j]) + pd_[j])


def test_energy_balance_closed_loop() -> None:
    """Electrical input = copper losses + d(magnetic energy) + d(kinetic) + friction + load
    work, integrated with the RK4 quadrature of the same step (augmented system)."""
    cfg = load_config(
        overrides={
            'machine.coulomb_torque': 0.03,
            'machine.coulomb_speed': 2.0,
            'disturbance.load_lag_tau': 0.002,
            'disturbance.ripple_amplitude': 0.1,
        }
    )
    sim = DriveSim(cfg)
    sim.reset(fluxed=False)
    x = sim.state_vector()[:6].copy()
    e = np.zeros(5)
    w0 = _stored_energy(x, sim.P)
    n = 2500
    for k in range(n):
        isq_ref = 0.0 if k < 500 else (4.0 if k < 1200 else (-3.0 if k < 1800 else 1.0))
        tl = 1.75 if k >= 1500 else 0.0
        sim.step(isq_ref, tl)
        _plant_rk4_energy(x, sim.u_alpha, sim.u_beta, sim.load_torque, sim.P, e)
        # the production kernel integrates exactly the same ODE with the same RK4
        assert np.array_equal(x, sim.state_vector()[:6])
    w1 = _stored_energy(x, sim.P)
    e_in, cu_s, cu_r, fric, load = e
    d_mag = w1[0] - w0[0]
    d_kin = w1[1] - w0[1]
    resid = e_in - (cu_s + cu_r + d_mag + d_kin + fric + load)
    assert e_in > 10.0 and d_mag > 0.1 and fric > 0.0 and abs(load) > 0.0
    assert abs(resid) < 1e-6 * e_in


# ----------------------------------------------------- full vs reduced closed loop
def _trapezoid(n: int, dist: float, amax: float = 600.0, vmax: float = 40.0) -> np.ndarray:
    """Minimum-time position reference for a move of ``dist`` rad (0.145 s for pi rad)."""
    t_acc = vmax / amax
    d_acc = 0.5 * amax * t_acc**2
    t_flat = (dist - 2.0 * d_acc) / vmax
    t_end = 2.0 * t_acc + t_flat
    t = np.arange(n) * TS
    th = np.where(
        t < t_acc,
        0.5 * amax * t**2,
        np.where(
            t < t_acc + t_flat,
            d_acc + vmax * (t - t_acc),
            np.where(t < t_end, dist - 0.5 * amax * (t_end - t) ** 2, dist),
        ),
    )
    return th


def _position_experiment(model: str, gains=(0.53, 20.0, 30.0, 0.005, 0.007)):
    """Notes' structure: smoothing tau_sm, closed-loop model tau_eq, speed feed-forward
    (theta_sm - theta_m)/tau_eq, P position, anti-windup PI speed -> isq*.  Python loop over
    5625 steps with a 1.75 N m load step at 0.7 s.  Returns (theta, loss, quadratic loss);
    loss is the paper's absolute-value form, the quadratic one squares each term."""
    k_pw, k_iw, k_pos, tau_sm, tau_eq = gains
    sim = DriveSim(load_config(overrides={'model': model}))
    sim.reset(fluxed=True)
    isq_max = sim.config.machine.isq_max
    n = 5625
    th_ref = _trapezoid(n, math.pi)
    a_sm = math.exp(-TS / tau_sm)
    a_eq = math.exp(-TS / tau_eq)
    a_f = math.exp(-TS / 0.02)
    th_sm = th_m = integ = isq_f = 0.0
    loss = qloss = 0.0
    theta = np.empty(n)
    out = np.zeros(len(L.STATE_FIELDS))
    sim.read_into(out)
    for k in range(n):
        th_sm = a_sm * th_sm + (1 - a_sm) * th_ref[k]
        th_m_new = a_eq * th_m + (1 - a_eq) * th_sm
        w_ff = (th_sm - th_m) / tau_eq
        th_m = th_m_new
        w_ref = k_pos * (th_m - out[L.F_THETA_MEAS]) + w_ff
        e = w_ref - out[L.F_OMEGA_MEAS]
        u = k_pw * e + integ
        isq = min(max(u, -isq_max), isq_max)
        if isq == u:
            integ += k_iw * TS * e  # conditional integration (anti-windup)
        isq_f = a_f * isq_f + (1 - a_f) * isq
        if abs(isq) / isq_max < 0.99:
            loss += TS * (
                abs(th_ref[k] - out[L.F_THETA_MEAS]) + 0.01 * abs(e) + 0.1 * abs(isq_f - isq)
            )
            qloss += TS * (
                (th_ref[k] - out[L.F_THETA_MEAS]) ** 2 + 1e-4 * e * e + 0.01 * (isq_f - isq) ** 2
            )
        tl = 1.75 if k * TS >= 0.7 else 0.0
        sim.step_into(isq, tl, out)
        theta[k] = out[L.F_THETA]
    return theta, loss, qloss


def test_full_and_reduced_agree_on_position_experiment() -> None:
    th_full, loss_full, q_full = _position_experiment('full')
    th_red, loss_red, q_red = _position_experiment('reduced')
    d = th_full - th_red
    assert abs(th_full[-1] - math.pi) < 5e-3  # the move is done, load rejected
    assert np.max(np.abs(d)) < 2e-2
    assert np.sqrt(np.mean(d**2)) < 5e-3
    assert loss_red == pytest.approx(loss_full, rel=0.02)  # measured 0.14 %
    assert q_red == pytest.approx(q_full, rel=0.02)


# ------------------------------------------------------------- reduced model forms
def test_reduced_isq_lag_and_mechanics_exact() -> None:
    cfg = load_config(overrides={'model': 'reduced', 'machine.B': 0.0})
    sim = DriveSim(cfg)
    sim.reset()
    n = 200
    r = sim.run(np.full(n, 2.0), np.zeros(n))
    k = np.arange(1, n + 1)
    a = math.exp(-TS / 6e-4)
    isq_true = 2.0 * (1.0 - a**k)
    np.testing.assert_allclose(r['isq'], isq_true, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(r['torque'], cfg.machine.Kt * isq_true, rtol=1e-12)
    # omega(t) = Kt/J * 2 (t - tau_i (1 - exp(-t/tau_i))): RK4 with exact isq(t) stages is
    # Simpson's rule on the exponential, (Ts/tau_i)^4/2880 per step: 2.4e-5 relative here.
    t = k * TS
    w_exact = cfg.machine.Kt / cfg.machine.J * 2.0 * (t - 6e-4 * (1.0 - np.exp(-t / 6e-4)))
    np.testing.assert_allclose(r['omega'], w_exact, rtol=5e-5)
    # ideal lag (tau_i = 0): constant acceleration, RK4 exact for polynomials
    sim = DriveSim(
        load_config(
            overrides={'model': 'reduced', 'machine.B': 0.0, 'control.reduced_current_lag': 0.0}
        )
    )
    sim.reset(theta=0.0)  # (the default start is half an encoder count in)
    r = sim.run(np.full(n, 2.0), np.full(n, 0.5))
    acc = (cfg.machine.Kt * 2.0 - 0.5) / cfg.machine.J
    np.testing.assert_allclose(r['omega'], acc * t, rtol=1e-12)
    np.testing.assert_allclose(r['theta'], 0.5 * acc * t**2, rtol=1e-12)


def test_full_model_torque_tracks_command() -> None:
    for delay in (0, 1):
        sim = DriveSim(
            load_config(overrides={'control.computation_delay_steps': delay, 'machine.J': 1.0})
        )
        sim.reset()
        r = sim.run(np.full(100, 2.0), np.zeros(100))
        kt = sim.config.machine.Kt
        assert r['torque'][-1] == pytest.approx(kt * 2.0, rel=2e-3)
        assert r['isq'][-1] == pytest.approx(2.0, rel=1e-3)
        assert r['isd'][-1] == pytest.approx(2.45, rel=1e-3)
        # 63 % rise of isq after about 1/wc (+ delay) = 0.67 ms (+ 0.2 ms)
        k63 = int(np.argmax(r['isq'] > 0.632 * 2.0)) + 1
        assert 2 <= k63 <= 6


def test_fluxed_reset_is_a_steady_state() -> None:
    sim = DriveSim(load_config(overrides={'machine.J': 1e9, 'machine.B': 0.0}))
    for omega in (0.0, 150.0):
        sim.reset(theta=0.3, omega=omega, fluxed=True)
        psi0 = sim.psi_r
        r = sim.run(np.zeros(500), np.zeros(500))
        assert psi0 == pytest.approx(0.50225, rel=1e-12)
        # At speed the sampled current (held 2.45 A by the PI) differs from the step-average
        # current by the ZOH ripple, so the flux settles ~4e-4 lower at 150 rad/s.
        assert np.max(np.abs(r['psi_r'] - psi0)) < 1e-3 * psi0
        assert np.max(np.abs(r['isd'] - 2.45)) < 1e-3
        # encoder quantisation (1 count = 1.5 mrad) jitters the orientation at speed:
        # |isq_true| <= isd * 1.5e-3 = 3.7 mA, i.e. 2.6e-3 N m
        assert np.max(np.abs(r['torque'])) < (5e-3 if omega else 1e-9)
