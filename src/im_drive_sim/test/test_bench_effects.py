"""Bench effects and the realism profile: off (``ideal``) is bit-identical
to the bench before the effects existed; each effect on gives its documented magnitude,
measured from the simulation, seeded and reproducible (docs/drive-model.md, "Bench effects")."""

from __future__ import annotations

import hashlib
import math
import sys
from pathlib import Path

import numpy as np
import pytest

try:  # source checkout without an installed package (the lead's packaging installs it)
    import im_drive_sim  # noqa: F401
except ImportError:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from im_drive_sim import model_layout as L
from im_drive_sim.drive_file import load_config
from im_drive_sim.params import REALISM_PROFILES, ConfigError
from im_drive_sim.plant import deadtime_error, friction_of
from im_drive_sim.sim import DriveSim

NOISY = {
    'sensors.current_noise_std': 0.05,
    'sensors.speed_noise_std': 0.2,
    'disturbance.load_noise_std': 0.02,
    'disturbance.load_noise_tau': 0.01,
    'machine.coulomb_torque': 0.03,
    'disturbance.ripple_amplitude': 0.1,
    'disturbance.ripple_harmonic': 2.0,
}
#: sha256 of a 1 s run (full, reduced, full with noise/friction/ripple) taken on the code
#: BEFORE the bench effects existed (commit eab17a7): the ``ideal`` bench must not move a bit.
TODAY = {
    ('full', False): '7491d8bbe4686e0fd296b4c9ee205f3b9285324666ec93e86cf429220df06c34',
    ('reduced', False): '30bac8d75bbc804910bd37ed917a7f155ef4828af4ccccd2a83d14472f855f44',
    ('full', True): 'e44da096cfc73dbfa40463df2234c1c54c689ed393e4c1daa4c60286ae2b5094',
}


def _digest(sim: DriveSim) -> str:
    n = 5000  # 1 s
    t = np.arange(n) * sim.config.Ts
    isq = np.where(t < 0.05, 0.0, 3.0) - np.where(t > 0.5, 4.0, 0.0)
    tl = np.where((t > 0.3) & (t < 0.7), 1.75, 0.0)
    res = sim.run(isq, tl)
    h = hashlib.sha256()
    for k in sorted(res):
        h.update(k.encode())
        h.update(np.ascontiguousarray(res[k]).tobytes())
    h.update(sim.state_vector()[:35].tobytes())
    return h.hexdigest()


@pytest.mark.parametrize(('model', 'noisy'), sorted(TODAY))
def test_ideal_profile_is_todays_bench_bit_for_bit(model: str, noisy: bool) -> None:
    cfg = load_config(overrides={'model': model, **(NOISY if noisy else {})})
    assert cfg.realism == 'ideal'
    assert _digest(DriveSim(cfg)) == TODAY[(model, noisy)]
    explicit = load_config(
        overrides={'model': model, 'realism': 'ideal', **(NOISY if noisy else {})}
    )
    assert explicit == cfg


def test_bench_profile_sets_each_effect_and_explicit_keys_win() -> None:
    cfg = load_config(overrides={'realism': 'bench'})
    assert cfg.realism == 'bench' and REALISM_PROFILES['bench']
    d = cfg.to_dict()
    for key, value in REALISM_PROFILES['bench'].items():
        sec, name = key.split('.')
        assert d[sec][name] == value, key
    mine = load_config(overrides={'realism': 'bench', 'machine.coulomb_torque': 0.0})
    assert mine.machine.coulomb_torque == 0.0 and mine.machine.deadtime_voltage == 3.0
    # a round trip through to_dict keeps every value
    from im_drive_sim.params import config_from_dict

    assert config_from_dict(d) == cfg


def test_bench_file_with_base_and_unknown_profile(tmp_path: Path) -> None:
    f = tmp_path / 'mine.yaml'
    f.write_text('base: paper_750w\nrealism: bench\nsensors:\n  current_offset_a: 0.0\n')
    cfg = load_config(f)
    assert cfg.sensors.current_offset_a == 0.0 and cfg.sensors.current_offset_b == -0.03
    with pytest.raises(
        ConfigError,
        match=r'^paper_750w\.yaml \(with overrides\): realism must be one of ideal, bench, '
        r"got 'lab'$",
    ):
        load_config(overrides={'realism': 'lab'})
    with pytest.raises(ConfigError, match=r'static_torque 0\.01 N m must be 0 \(off\) or >= '):
        load_config(overrides={'machine.coulomb_torque': 0.02, 'machine.static_torque': 0.01})


def test_bench_profile_is_seeded_and_reproducible() -> None:
    cfg = load_config(overrides={'realism': 'bench'})
    a, b, c = DriveSim(cfg, seed=3), DriveSim(cfg, seed=3), DriveSim(cfg, seed=4)
    isq = np.full(3000, 2.0)
    ra, rb, rc = a.run(isq, 0.5), b.run(isq, 0.5), c.run(isq, 0.5)
    for k in ra:
        assert np.array_equal(ra[k], rb[k]), k
    assert not np.array_equal(ra['isq'], rc['isq'])
    ideal = DriveSim(load_config(), seed=3).run(isq, 0.5)
    assert not np.array_equal(ra['omega'], ideal['omega'])


def test_current_offset_per_phase_is_in_every_sample() -> None:
    """The sampled phase currents (isd, isq rotated back by rho) minus the true ones: the
    sensors' offsets, exactly (phase a = alpha; phase b = (-alpha + sqrt(3) beta)/2)."""
    sim = DriveSim(
        load_config(overrides={'sensors.current_offset_a': 0.05, 'sensors.current_offset_b': -0.03})
    )
    da, db = [], []
    for k in range(400):
        sim.step(2.0 if k > 50 else 0.0, 0.0)
        S = sim.state_vector()
        rho = S[L.S_RHO]
        ma = math.cos(rho) * sim.isd - math.sin(rho) * sim.isq
        mb = math.sin(rho) * sim.isd + math.cos(rho) * sim.isq
        da.append(ma - S[L.S_ISA])
        db.append(
            0.5 * (-ma + math.sqrt(3.0) * mb) - 0.5 * (-S[L.S_ISA] + math.sqrt(3.0) * S[L.S_ISB])
        )
    assert np.mean(da) == pytest.approx(0.05, abs=1e-12) and np.ptp(da) < 1e-12
    assert np.mean(db) == pytest.approx(-0.03, abs=1e-12) and np.ptp(db) < 1e-12


def _stribeck(w: float, b: float, tc: float, ts: float, wc: float, ws: float) -> float:
    """Simscape's rotational friction: the Stribeck term peaks at w_brk = ws/sqrt(2) with
    Ts - Tc, the Coulomb term smoothed at most at w_brk/10 (test_bench_fidelity: the peak)."""
    wc = min(wc, ws / (10.0 * math.sqrt(2.0)))
    x = w / ws
    return b * w + tc * math.tanh(w / wc) + math.sqrt(2 * math.e) * (ts - tc) * x * math.exp(-x * x)


def test_stribeck_friction_is_the_formula_and_decelerates_the_shaft() -> None:
    ov = {
        'model': 'reduced',
        'machine.coulomb_torque': 0.02,
        'machine.static_torque': 0.03,
        'machine.stribeck_speed': 2.0,
    }
    cfg = load_config(overrides=ov)
    m = cfg.machine
    sim = DriveSim(cfg)
    for w in (-30.0, -2.0, -0.5, 0.0, 0.3, 1.0, 2.0, 5.0, 100.0):
        want = _stribeck(w, m.B, 0.02, 0.03, m.coulomb_speed, 2.0)
        assert float(friction_of(w, sim.P)) == pytest.approx(want, rel=1e-14, abs=1e-18)
        # measured: the shaft's deceleration over one step with no torque and no load
        sim.reset(omega=w)
        sim.step(0.0, 0.0)
        measured = -m.J * (sim.omega - w) / cfg.Ts
        assert measured == pytest.approx(want, rel=2e-3, abs=1e-9)
    # towards the breakaway speed the friction exceeds Coulomb's (0.02): the Stribeck rise
    assert float(friction_of(1.0, sim.P)) > 0.02 + m.B * 1.0 + 0.009


def test_position_ripple_has_its_period_and_amplitude() -> None:
    cfg = load_config(
        overrides={
            'model': 'reduced',
            'realism': 'bench',
            'disturbance.ripple_phase': 0.3,
            'disturbance.load_noise_std': 0.0,  # explicit: the bench without its random load
        }
    )
    sim = DriveSim(cfg)
    sim.reset(omega=50.0)
    th, tl = [], []
    for _ in range(2000):
        th.append(sim.theta)
        sim.step(0.0, 0.0)
        tl.append(sim.load_torque)
    th_a, tl_a = np.array(th), np.array(tl)
    want = 0.025 * np.sin(6.0 * th_a + 0.3)  # 6 periods per revolution
    assert np.max(np.abs(tl_a - want)) < 1e-12 and np.ptp(tl_a) > 0.049


def test_deadtime_voltage_error_shifts_the_dc_current() -> None:
    """DC current in phase a (b and c carry -i/2): du_alpha = -4/3 Vdt; the steady
    current (U - 4/3 Vdt)/Rs; a sign-changing current vector gets its own error."""
    da, db = deadtime_error(1.0, 0.0, 3.0)
    assert (da, db) == (pytest.approx(-4.0), pytest.approx(0.0, abs=1e-15))
    da, db = deadtime_error(0.0, 1.0, 3.0)  # ia = 0, ib > 0 > ic
    assert (da, db) == (pytest.approx(0.0, abs=1e-15), pytest.approx(-6.0 / math.sqrt(3.0)))
    for vdt in (0.0, 3.0):
        sim = DriveSim(load_config(overrides={'machine.deadtime_voltage': vdt}))
        sim.reset(theta=0.0, fluxed=False)
        res = sim.run_voltage(np.full(25000, 10.0), np.zeros(25000), 0.0)  # 5 s: 30 slow tau
        want = (10.0 - 4.0 / 3.0 * vdt) / sim.config.machine.Rs
        assert res['i_alpha'][-1] == pytest.approx(want, abs=1e-9)
        assert abs(res['i_beta'][-1]) < 1e-12 and res['omega'][-1] == 0.0


def test_rotor_resistance_drifts_to_its_warm_value() -> None:
    ov = {'machine.rr_temp_rise': 40.0, 'machine.rr_temp_tau': 1200.0}
    warm = load_config(overrides=ov)
    rr0 = warm.machine.Rr
    sim = DriveSim(warm)
    assert sim.rotor_resistance == rr0
    sim.reset(step_index=round(1200.0 / warm.Ts))  # t = tau
    assert sim.rotor_resistance == pytest.approx(rr0 * (1 + 0.00393 * 40 * (1 - math.exp(-1))))
    # t = 50 tau: the plant is the machine with Rr0 (1 + alpha dT) (bare model, same volts)
    k = round(50 * 1200.0 / warm.Ts)
    rr_hot = rr0 * (1.0 + 0.00393 * 40.0)
    hot = DriveSim(load_config(overrides={'machine.Rr': rr_hot}))
    ua = 60.0 * np.cos(2 * math.pi * 20.0 * np.arange(2000) * warm.Ts)
    ub = 60.0 * np.sin(2 * math.pi * 20.0 * np.arange(2000) * warm.Ts)
    runs = []
    for s in (sim, hot):
        s.reset(step_index=k, fluxed=False)
        runs.append(s.run_voltage(ua, ub, 0.0))
    assert sim.rotor_resistance == pytest.approx(rr_hot, rel=1e-15)
    for f in ('i_alpha', 'i_beta', 'omega', 'psi_r'):
        assert np.max(np.abs(runs[0][f] - runs[1][f])) < 1e-9, f
    cold = DriveSim(load_config())
    cold.reset(step_index=k, fluxed=False)
    assert np.max(np.abs(cold.run_voltage(ua, ub, 0.0)['omega'] - runs[1]['omega'])) > 1e-3


def _counts(jitter: float, seed: int, noisy: bool) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    ov = {'model': 'reduced', 'sensors.encoder_jitter': jitter, 'machine.B': 0.0}
    if noisy:
        ov['sensors.current_noise_std'] = 0.05
    sim = DriveSim(load_config(overrides=ov), seed=seed)
    sim.reset(omega=100.0)
    res = sim.run(np.zeros(6000), 0.0)
    return res['encoder_count'], res


def test_encoder_edge_jitter_has_its_std_and_its_own_stream() -> None:
    """Reduced model (the true motion does not depend on the measurement): the count with
    jitter minus without is omega * dt * counts/(2 pi), dt of std ``encoder_jitter``."""
    c0, r0 = _counts(0.0, 5, True)
    c1, r1 = _counts(1e-4, 5, True)
    assert np.array_equal(r0['omega'], r1['omega'])
    k = 4096 / (2 * math.pi)
    dt = (c1 - c0) / (r1['omega'] * k)  # the latch time error [s]
    assert np.std(dt) == pytest.approx(1e-4, rel=0.05) and abs(np.mean(dt)) < 5e-6
    # its own stream: the current noise draws as without it; a seed reproduces it
    assert np.array_equal(r0['isd'], r1['isd'])
    assert np.array_equal(_counts(1e-4, 5, True)[0], c1)
    assert not np.array_equal(_counts(1e-4, 6, True)[0], c1)


def test_bench_random_load_has_its_std_and_correlation_time() -> None:
    cfg = load_config(
        overrides={'model': 'reduced', 'realism': 'bench', 'disturbance.ripple_amplitude': 0.0}
    )
    tl = DriveSim(cfg, seed=11).run(np.zeros(100_000), 0.0)['load_torque'][1000:]
    assert np.std(tl) == pytest.approx(cfg.disturbance.load_noise_std, rel=0.1)
    assert cfg.disturbance.load_noise_std == REALISM_PROFILES['bench']['disturbance.load_noise_std']
    lag = 100  # one correlation time (20 ms): autocorrelation exp(-1)
    rho = np.corrcoef(tl[:-lag], tl[lag:])[0, 1]
    assert rho == pytest.approx(math.exp(-1.0), abs=0.08)


# ---------------------------------------------------------------- the load step's variation
STEP_STD, STEP_DELAY = 0.05, 1.0e-3  # 5 %, up to 5 periods of 200 us


def _step_run(
    seed: int, std: float, delay: float, edges: int, hold: int = 40, realism: str = 'ideal'
) -> dict:
    """Reduced model, the load command a square wave 0 / 1 N m (``edges`` edges, ``hold``
    periods apart), every other load effect off: the load acting is the load machine's step."""
    ov = {
        'model': 'reduced',
        'realism': realism,
        'disturbance.load_step_amplitude_std': std,
        'disturbance.load_step_delay_max': delay,
        'disturbance.ripple_amplitude': 0.0,
        'disturbance.load_noise_std': 0.0,
    }
    sim = DriveSim(load_config(overrides=ov), seed=seed)
    cmd = np.repeat(np.arange(edges + 1) % 2, hold).astype(float)
    res = sim.run(np.zeros(cmd.size), cmd)
    res['cmd'] = cmd
    return res


def _edges(res: dict, hold: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Per rising edge of the command: the factor (level acting / commanded) and the delay
    [periods] before the new level acted (row k of a run is the load of step k)."""
    tl, cmd = res['load_torque'], res['cmd']
    factors, delays = [], []
    for k in range(hold, cmd.size, hold):
        seg = tl[k : k + hold]
        moved = np.flatnonzero(seg != tl[k - 1])
        delays.append(int(moved[0]))
        if cmd[k] == 1.0:
            factors.append(seg[-1])
    return np.array(factors), np.array(delays)


def test_load_step_off_or_without_edges_is_the_bench_without_it() -> None:
    """Off: the drive file without the keys (the ``ideal`` digests pin that). On, with a
    command that never changes: bit-identical to off (its stream is its own)."""
    cfg_off = load_config(overrides={**NOISY, 'model': 'reduced'})
    cfg_on = load_config(
        overrides={
            **NOISY,
            'model': 'reduced',
            'disturbance.load_step_amplitude_std': STEP_STD,
            'disturbance.load_step_delay_max': STEP_DELAY,
        }
    )
    assert cfg_off.disturbance.load_step_amplitude_std == 0.0
    assert DriveSim(cfg_off).P[L.P_LS_ON] == 0.0 and DriveSim(cfg_on).P[L.P_LS_DELAY_N] == 5
    isq = np.full(9000, 1.0)  # over two noise blocks
    a, b = DriveSim(cfg_off, seed=2).run(isq, 0.0), DriveSim(cfg_on, seed=2).run(isq, 0.0)
    for k in a:
        assert np.array_equal(a[k], b[k]), k


def test_load_step_amplitude_and_delay_have_their_documented_distribution() -> None:
    """2000 seeded edges: the factor 1 + N(0, std) (mean 1, std 5 %), the delay uniform
    on {0, ..., 5} periods (1 ms / 200 us), the falling edges delayed the same way."""
    res = _step_run(7, STEP_STD, STEP_DELAY, 2000)
    factors, delays = _edges(res)
    assert factors.size == 1000 and delays.size == 2000
    assert np.mean(factors) == pytest.approx(1.0, abs=3 * STEP_STD / math.sqrt(1000))
    assert np.std(factors, ddof=1) == pytest.approx(STEP_STD, rel=0.08)
    counts = np.bincount(delays, minlength=6)
    assert counts.size == 6 and np.all(np.abs(counts - 2000 / 6) < 4 * math.sqrt(2000 / 6))
    # a falling edge ends at exactly 0: the factor scales the command
    assert np.all(res['load_torque'][res['cmd'] == 0.0][-20:] == 0.0)
    # the amplitude without a delay, the delay without an amplitude error
    f0, d0 = _edges(_step_run(7, STEP_STD, 0.0, 200))
    assert np.all(d0 == 0) and np.std(f0) > 0.02
    f1, d1 = _edges(_step_run(7, 0.0, STEP_DELAY, 200))
    assert np.all(f1 == 1.0) and set(d1) == set(range(6))


def test_bench_profile_load_step_has_its_magnitude() -> None:
    """The ``bench`` profile's own magnitudes (calibrated, docs/calibration.md), measured."""
    prof = REALISM_PROFILES['bench']
    std, delay = (
        prof['disturbance.load_step_amplitude_std'],
        prof['disturbance.load_step_delay_max'],
    )
    n = round(delay / 2e-4)
    assert std > 0.0 and n >= 1
    hold = n + 20
    res = _step_run(9, std, delay, 2000, hold, 'bench')
    factors, delays = _edges(res, hold)
    assert np.std(factors, ddof=1) == pytest.approx(std, rel=0.08)
    assert abs(np.mean(factors) - 1.0) < 3 * std / math.sqrt(factors.size)
    counts = np.bincount(delays, minlength=n + 1)
    want = delays.size / (n + 1)
    assert counts.size == n + 1 and np.all(np.abs(counts - want) < 4.5 * math.sqrt(want))


def test_load_step_variation_is_seeded_and_reproducible() -> None:
    a = _edges(_step_run(3, STEP_STD, STEP_DELAY, 100))
    b = _edges(_step_run(3, STEP_STD, STEP_DELAY, 100))
    c = _edges(_step_run(4, STEP_STD, STEP_DELAY, 100))
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0]) and not np.array_equal(a[1], c[1])


def test_load_step_keys_refused_in_one_line() -> None:
    with pytest.raises(
        ConfigError,
        match=r'^paper_750w\.yaml \(with overrides\): disturbance\.load_step_amplitude_std '
        r'must be a finite number >= 0 and <= 0\.5, got -0\.1$',
    ):
        load_config(overrides={'disturbance.load_step_amplitude_std': -0.1})
    with pytest.raises(ConfigError, match=r'load_step_delay_max must be .* <= 1, got 2\.0$'):
        load_config(overrides={'disturbance.load_step_delay_max': 2.0})
