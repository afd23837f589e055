"""The drive's declared command delay (docs/interfaces.md, docs/real-drive.md).

d = 1: the command given at state k acts over k -> k+1 (the simulator's default); d = 2: a
power stage that latches its command at the next period start, so it acts over
k+1 -> k+2. Every state says d (field ``command_delay``) and labels the command that
acted (``applied_step = k - d`` when it was the answer in time).
"""

from __future__ import annotations

import numpy as np
import pytest

from im_drive_sim import contract
from im_drive_sim.drive_file import load_config
from im_drive_sim.params import ConfigError, config_from_dict
from im_drive_sim.sim import STATE_FIELDS, DriveSim

F = contract.STATE_INDEX


def _states(delay: int, isq: np.ndarray, load: np.ndarray) -> np.ndarray:
    sim = DriveSim(load_config(overrides={'command_delay': delay}), seed=3)
    sim.reset(omega=0.0, fluxed=True)
    out = np.zeros((len(isq) + 1, len(STATE_FIELDS)))
    sim.read_into(out[0])
    for k in range(len(isq)):
        sim.step_into(float(isq[k]), float(load[k]), out[k + 1])
    return out


def test_delay_2_runs_each_command_one_period_later_bit_for_bit():
    rng = np.random.default_rng(5)
    n = 400
    isq = rng.uniform(-3.0, 3.0, n)
    load = np.where(np.arange(n) > 200, 0.8, 0.0)
    d2 = _states(2, isq, load)
    # delay 1 given the same commands one period later (zero first) is the same plant
    d1 = _states(1, np.r_[0.0, isq[:-1]], np.r_[0.0, load[:-1]])
    physics = [i for i, f in enumerate(STATE_FIELDS) if f not in ('applied_step', 'command_delay')]
    np.testing.assert_array_equal(d2[:, physics], d1[:, physics])
    k = d2[:, F['step_index']]
    # every state declares its delay and labels the command that acted (-1: none yet)
    assert np.all(d2[:, F['command_delay']] == 2.0) and np.all(d1[:, F['command_delay']] == 1.0)
    np.testing.assert_array_equal(d2[:, F['applied_step']], np.maximum(k - 2.0, -1.0))
    np.testing.assert_array_equal(d1[:, F['applied_step']], np.maximum(k - 1.0, -1.0))
    # ... and it is not the same plant as delay 1 with the same commands
    assert not np.array_equal(_states(1, isq, load)[:, physics], d2[:, physics])


def test_clear_command_drops_the_latched_command():
    sim = DriveSim(load_config(overrides={'command_delay': 2}), seed=0)
    sim.reset(omega=0.0, fluxed=True)
    sim.step(5.0, 0.0)  # latched: acts over the next step
    sim.clear_command()  # a safe stop: zero current at once
    sim.step(0.0, 0.0)
    assert sim.isq_ref == 0.0 and abs(sim.isq) < 0.05


def test_the_drive_file_key_is_optional_and_checked():
    base = load_config(None)
    assert base.command_delay == 1 and base.to_dict()['command_delay'] == 1
    data = base.to_dict()
    del data['command_delay']  # a file written before the key: delay 1
    assert config_from_dict(data).command_delay == 1
    assert config_from_dict({**data, 'command_delay': 2}).command_delay == 2
    assert config_from_dict(base.to_dict()) == base
    for bad in (0, 3, 1.5, True, '2'):
        with pytest.raises(ConfigError, match='command_delay must be an integer >= 1 and <= 2'):
            config_from_dict({**data, 'command_delay': bad})
    assert contract.COMMAND_DELAYS == (1, 2)
    assert contract.STATE_FIELDS[-1] == 'command_delay' and len(contract.STATE_FIELDS) == 14


def test_the_stand_in_hardware_declares_and_acts_with_its_delay():
    from im_drive_sim.example_drive import Hardware, hardware_command_delay

    class Latching(Hardware):
        command_delay = 2  # a subclass's class attribute wins over the file's

    class Three(Hardware):
        command_delay = 3

    cfg = load_config(None)
    assert hardware_command_delay(Hardware(cfg)) == 1
    assert hardware_command_delay(Latching(cfg)) == 2
    with pytest.raises(ConfigError, match=r'Three.command_delay must be 1 or 2 \(periods\), got 3'):
        hardware_command_delay(Three(cfg))
    first_isq = {}
    for d in (1, 2):
        hw = Hardware(load_config(overrides={'command_delay': d}))
        assert hw.command_delay == d
        hw.write(2.0, 0.0)
        first = hw.read().isq  # the period after the write
        hw.write(2.0, 0.0)
        second = hw.read().isq
        first_isq[d] = (first, second)
    assert first_isq[1][0] > 0.5  # delay 1: the write acts at once
    assert first_isq[2][0] == 0.0 and first_isq[2][1] == pytest.approx(first_isq[1][0])
