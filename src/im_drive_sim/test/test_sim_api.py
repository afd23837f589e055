"""DriveSim API: step semantics, encoder, speed estimate, disturbances, determinism."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

try:  # source checkout without an installed package (the lead's packaging installs it)
    import im_drive_sim
except ImportError:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import im_drive_sim
from im_drive_sim import model_layout as L
from im_drive_sim.drive_file import load_config
from im_drive_sim.sim import NOISE_BLOCK, RUN_FIELDS, STATE_FIELDS, DriveSim

TS = 200e-6
NOISY = {
    'sensors.current_noise_std': 0.05,
    'sensors.speed_noise_std': 0.5,
    'disturbance.load_noise_std': 0.1,
    'disturbance.load_noise_tau': 0.01,
    'disturbance.ripple_amplitude': 0.05,
    'disturbance.ripple_harmonic': 2.0,
}


def _profile(n: int) -> tuple[np.ndarray, np.ndarray]:
    k = np.arange(n)
    return np.where((k // 400) % 2 == 0, 3.0, -2.0), np.where(k > n // 2, 1.75, 0.0)


def test_package_metadata_and_fields() -> None:
    assert im_drive_sim.__version__ == '0.1.0'
    assert im_drive_sim.DriveSim is DriveSim
    assert im_drive_sim.load_config is load_config  # each lazy name resolves
    for name in im_drive_sim.__all__:
        assert getattr(im_drive_sim, name) is not None
    # the published layout, pinned: a change to it is a change of the drive contract
    assert ' '.join(STATE_FIELDS) == (
        'step_index time_ns theta_meas omega_meas torque isd isq i_alpha i_beta '
        'load_torque theta omega applied_step command_delay'
    )
    assert RUN_FIELDS[: len(STATE_FIELDS)] == STATE_FIELDS and len(RUN_FIELDS) == L.N_RUN_FIELDS


@pytest.mark.parametrize('model', ['full', 'reduced'])
def test_step_semantics_read_into_step_into_time(model: str) -> None:
    sim = DriveSim(load_config(overrides={'model': model}))
    sim.reset(theta=1.0, omega=2.0, step_index=7)
    out = np.zeros(len(STATE_FIELDS))
    sim.read_into(out)
    assert out[L.F_STEP] == 7 and out[L.F_TIME_NS] == 7 * 200_000
    assert out[L.F_THETA] == 1.0 and out[L.F_OMEGA] == 2.0 and out[L.F_OMEGA_MEAS] == 2.0
    assert sim.step_index == 7 and sim.time_ns == 1_400_000 and sim.time == pytest.approx(1.4e-3)
    sim.step_into(1.0, 0.0, out)
    assert out[L.F_STEP] == 8 and out[L.F_TIME_NS] == 1_600_000 and sim.step_index == 8
    assert out[L.F_THETA] == sim.theta and out[L.F_OMEGA] == sim.omega
    assert out[L.F_THETA_MEAS] == sim.theta_meas and out[L.F_OMEGA_MEAS] == sim.omega_meas
    assert out[L.F_TORQUE] == sim.torque and out[L.F_ISQ] == sim.isq and out[L.F_ISD] == sim.isd
    assert out[L.F_I_ALPHA] == sim.i_alpha and out[L.F_I_BETA] == sim.i_beta
    # exact integer time for long runs
    sim.reset(step_index=10**9)
    assert sim.time_ns == 200_000 * 10**9
    sim.step(0.0, 0.0)
    assert sim.time_ns == 200_000 * (10**9 + 1)
    with pytest.raises(ValueError):
        sim.step(float('nan'), 0.0)
    with pytest.raises(ValueError):
        sim.step_into(0.0, float('inf'), out)
    with pytest.raises(ValueError):
        sim.reset(step_index=-1)


def test_run_equals_step_and_step_into() -> None:
    n = 1500
    isq, tl = _profile(n)
    cfg = load_config(overrides=NOISY)
    a = DriveSim(cfg, seed=3)
    r = a.run(isq, tl)
    b = DriveSim(cfg, seed=3)
    c = DriveSim(cfg, seed=3)
    out = np.zeros(len(RUN_FIELDS))
    for k in range(n):
        b.step(isq[k], tl[k])
        c.step_into(isq[k], tl[k], out)
        assert out[L.F_THETA] == r['theta'][k] and out[L.F_OMEGA_MEAS] == r['omega_meas'][k]
        assert out[L.F_ISQ] == r['isq'][k] and out[L.F_LOAD] == r['load_torque'][k]
    assert np.array_equal(b.state_vector(), a.state_vector())
    assert np.array_equal(c.state_vector(), a.state_vector())
    assert r['step_index'][-1] == n and r['time_ns'][0] == 200_000


@pytest.mark.parametrize('model', ['full', 'reduced'])
def test_determinism_seeds_and_reset(model: str) -> None:
    n = 2 * NOISE_BLOCK + 500  # crosses noise-block refills
    isq, tl = _profile(n)
    cfg = load_config(overrides={**NOISY, 'model': model})
    r1 = DriveSim(cfg, seed=11).run(isq, tl)
    r2 = DriveSim(cfg, seed=11).run(isq, tl)
    r3 = DriveSim(cfg, seed=12).run(isq, tl)
    for f in RUN_FIELDS:
        assert np.array_equal(r1[f], r2[f]), f
    assert not np.array_equal(r1['omega_meas'], r3['omega_meas'])
    assert not np.array_equal(r1['isq'], r3['isq'])
    assert not np.array_equal(r1['load_torque'], r3['load_torque'])
    # reset rewinds everything, including the noise streams
    sim = DriveSim(cfg, seed=11)
    sim.run(isq[:1234], tl[:1234])
    sim.reset()
    r4 = sim.run(isq, tl)
    for f in RUN_FIELDS:
        assert np.array_equal(r1[f], r4[f]), f
    # noise statistics as configured (current noise on the sampled, rotated currents)
    quiet = DriveSim(load_config(overrides={'model': model}), seed=11).run(isq, tl)
    d = r1['omega_meas'] - quiet['omega_meas']
    assert np.all(np.isfinite(d)) and np.std(d) > 0.1


def test_noise_free_is_seed_independent() -> None:
    n = 800
    isq, tl = _profile(n)
    a = DriveSim(seed=1).run(isq, tl)
    b = DriveSim(seed=2).run(isq, tl)
    assert all(np.array_equal(a[f], b[f]) for f in RUN_FIELDS)


@pytest.mark.parametrize('counts', [4096, 1000])
def test_encoder_quantisation_exact(counts: int) -> None:
    cfg = load_config(overrides={'model': 'reduced', 'sensors.encoder_counts': counts})
    sim = DriveSim(cfg)
    kq = counts / (2.0 * math.pi)
    res = 2.0 * math.pi / counts
    for th in (0.0, 1e-9, -1e-9, 0.5 * res, res, -res, 3.0, -3.0, 7.5 * math.pi, -25.3, 1234.5):
        sim.reset(theta=th)
        c = math.floor(th * kq)
        assert sim.encoder_count == c
        assert sim.theta_meas == c * res
        # bracket up to rounding of theta*(counts/2pi) and count*(2pi/counts)
        assert sim.theta_meas - 1e-12 * (1 + abs(th)) <= th < sim.theta_meas + res * (1 + 1e-9)
    sim.reset(theta=-1e-9)
    assert sim.encoder_count == -1  # floor, not truncation toward zero


@pytest.mark.parametrize('tau', [1e-3, 0.0])
def test_speed_estimate_is_filtered_count_difference(tau: float) -> None:
    cfg = load_config(overrides={'sensors.speed_filter_tau': tau})
    sim = DriveSim(cfg)
    n = 3000
    isq, tl = _profile(n)
    sim.reset(theta=-2.0, omega=-5.0)
    c0 = sim.encoder_count
    r = sim.run(isq, tl)
    counts = r['encoder_count']
    kq = 4096 / (2.0 * math.pi)
    assert np.array_equal(counts, np.floor(r['theta'] * kq))  # multi-turn, negative angles
    assert np.min(r['theta']) < -2.0 and np.max(np.abs(np.diff(counts))) > 10
    raw = np.diff(np.concatenate(([c0], counts))) * (2.0 * math.pi / 4096) / TS
    a = math.exp(-TS / tau) if tau > 0 else 0.0
    y = -5.0
    ref = np.empty(n)
    for k in range(n):
        y = a * y + (1.0 - a) * raw[k]
        ref[k] = y
    np.testing.assert_allclose(r['omega_meas'], ref, rtol=1e-12, atol=1e-9)
    if tau == 0.0:
        # unfiltered: an integer number of counts per step, 1 count = 7.67 rad/s
        assert np.allclose(
            r['omega_meas'] / (2.0 * math.pi / 4096 / TS),
            np.round(r['omega_meas'] / (2.0 * math.pi / 4096 / TS)),
            atol=1e-9,
        )


def _reduced_sim(
    seed: int | None = None, machine: dict[str, float] | None = None, **disturbance: float
) -> DriveSim:
    """A simulator of the reduced model with these disturbance (and machine) parameters."""
    overrides = {'model': 'reduced', 'disturbance': disturbance, 'machine': machine or {}}
    return DriveSim(load_config(overrides=overrides), seed=seed)


def test_load_lag_and_ripple() -> None:
    sim = _reduced_sim(
        load_lag_tau=0.01, ripple_amplitude=0.2, ripple_harmonic=3.0, ripple_phase=0.4
    )
    sim.reset(theta=0.2, omega=30.0)
    n = 400
    r = sim.run(np.full(n, 1.0), np.full(n, 1.5))
    a = math.exp(-TS / 0.01)
    k = np.arange(1, n + 1)
    theta_start = np.concatenate(([0.2], r['theta'][:-1]))  # load is evaluated at step start
    expect = 1.5 * (1.0 - a**k) + 0.2 * np.sin(3.0 * theta_start + 0.4)
    np.testing.assert_allclose(r['load_torque'], expect, rtol=1e-12, atol=1e-14)


def test_random_load_statistics() -> None:
    sim = _reduced_sim(seed=5, machine={'J': 1.0}, load_noise_std=0.2, load_noise_tau=0.005)
    n = 200_000
    r = sim.run(np.zeros(n), np.zeros(n))
    v = r['load_torque'][1000:]
    assert np.std(v) == pytest.approx(0.2, rel=0.1)
    lag = round(0.005 / TS)  # autocorrelation exp(-1) at one correlation time
    rho = np.corrcoef(v[:-lag], v[lag:])[0, 1]
    assert rho == pytest.approx(math.exp(-1.0), abs=0.07)


def test_voltage_limit_and_saturation_flag() -> None:
    sim = DriveSim(load_config(overrides={'machine.J': 0.01}))
    sim.reset()
    n = 6000
    r = sim.run(np.full(n, 7.0), np.zeros(n))
    u = np.hypot(r['u_alpha'], r['u_beta'])
    umax = sim.config.machine.u_max
    assert np.max(u) <= umax * (1 + 1e-12)
    # the 7 A step saturates at once (kp e = 255 V), and again at high speed
    assert r['voltage_saturated'][0] == 1.0 and np.mean(r['voltage_saturated'][3000:]) > 0.5
    assert sim.voltage_saturated is True
    assert np.all(np.isfinite(sim.state_vector()))
    # anti-windup: after reversing the command the current follows promptly
    r2 = sim.run(np.full(200, -2.0), np.zeros(200))
    assert r2['isq'][-1] == pytest.approx(-2.0, abs=0.05)


def test_step_voltage_only_full_and_state_vector_copy() -> None:
    sim = DriveSim(load_config(overrides={'model': 'reduced'}))
    with pytest.raises(RuntimeError):
        sim.step_voltage(1.0, 0.0, 0.0)
    sim = DriveSim()
    sim.reset(fluxed=False)
    v = sim.state_vector()
    v[:] = 99.0
    assert sim.i_alpha == 0.0
    sim.step_voltage(10.0, 0.0, 0.0)
    # de-energised: sigma Ls di/dt = -R_sigma i + u (the flux term is second order in Ts)
    m = sim.config.machine
    i1 = 10.0 / m.R_sigma * (1.0 - math.exp(-TS * m.R_sigma / (m.sigma * m.Ls)))
    assert sim.i_alpha == pytest.approx(i1, rel=2e-3)
    assert sim.u_alpha == 10.0 and sim.u_beta == 0.0
    with pytest.raises(ValueError):
        DriveSim(seed=-1)
