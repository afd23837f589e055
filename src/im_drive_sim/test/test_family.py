"""The packaged family of drives: every name resolves, the ratio variants' inertia, the
one-line refusal of an unknown name (docs/drive-family.md)."""

from __future__ import annotations

import pytest

from im_drive_sim.drive_file import load_config
from im_drive_sim.family import (
    DRIVE_NAMES,
    MOTOR_FILES,
    MOTORS,
    PACKAGED_NAMES,
    RATIOS,
    drive_name,
    motor_and_ratio,
    packaged_path,
)
from im_drive_sim.params import ConfigError, default_config_path


def test_nine_drives_three_motors():
    assert len(DRIVE_NAMES) == 9 and len(set(DRIVE_NAMES)) == 9
    assert MOTOR_FILES == ('paper_750w', 'im3700w', 'im7500w')
    assert 'im3700w-j3' in DRIVE_NAMES and RATIOS == (1, 3, 10)
    ratings = [m.rating_w for m in MOTORS]
    assert ratings == sorted(ratings) and len(set(ratings)) == 3


@pytest.mark.parametrize('name', PACKAGED_NAMES)
def test_every_name_loads_and_passes_the_checks(name):
    cfg = load_config(name)
    assert cfg.source == f'{name}.yaml'
    assert packaged_path(name).is_file()


@pytest.mark.parametrize('motor', MOTORS, ids=lambda m: m.key)
@pytest.mark.parametrize('ratio', RATIOS)
def test_ratio_variants_total_inertia(motor, ratio):
    cfg = load_config(drive_name(motor, ratio))
    assert pytest.approx(motor.J_motor * (1 + ratio), rel=1e-12) == cfg.machine.J
    assert motor_and_ratio(drive_name(motor, ratio)) == (motor, ratio)
    own = load_config(motor.file)
    # the variant is the motor's file but for J
    assert cfg.to_dict() | {'machine': None} == own.to_dict() | {'machine': None}
    assert {k: v for k, v in cfg.to_dict()['machine'].items() if k != 'J'} == {
        k: v for k, v in own.to_dict()['machine'].items() if k != 'J'
    }


def test_paper_750w_is_the_ratio_one_drive_unchanged():
    assert load_config('im750w-j1') == load_config(None) == load_config('paper_750w')
    assert load_config('paper_750w').machine.J == 2.5e-3


def test_unknown_name_refused_in_one_line_naming_the_drives():
    with pytest.raises(ConfigError) as exc:
        load_config('im2200w-j3')
    msg = str(exc.value)
    assert '\n' not in msg and msg.startswith('im2200w-j3: no such drive file')
    assert all(n in msg for n in PACKAGED_NAMES)


def test_a_file_of_that_name_wins_and_a_missing_path_is_a_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / 'im3700w-j3').write_text(default_config_path().read_text(encoding='utf-8'))
    assert load_config('im3700w-j3').machine.J == 2.5e-3  # the local file, not the drive
    with pytest.raises(ConfigError, match='cannot read'):
        load_config('nowhere/motor.yaml')


def test_motor_rated_point_is_the_circuits():
    """rated_torque and rated_speed: the equivalent circuit at rated voltage and frequency
    delivers the rated output at that speed (the derivation of docs/drive-family.md)."""
    from im_drive_sim.analytic import phase_peak_from_line_rms, steady_state

    for m in MOTORS[1:]:
        mach = load_config(m.file).machine
        w_sync = 2 * 3.141592653589793 * 50.0 / mach.pole_pairs
        slip = 1.0 - mach.rated_speed / w_sync
        ss = steady_state(mach, phase_peak_from_line_rms(400.0), 50.0, slip)
        assert ss.p_mech == pytest.approx(m.rating_w, rel=0.01)
        assert mach.rated_torque * mach.rated_speed == pytest.approx(m.rating_w, rel=1e-3)
        assert abs(ss.psi_r) / mach.Lm == pytest.approx(mach.rated_flux_current, rel=0.01)
        assert mach.isq_max == pytest.approx(2 * mach.rated_torque / mach.Kt, rel=1e-3)


def test_command_line_drive_file_takes_names_and_refuses_unknown_ones(tmp_path, monkeypatch):
    import argparse

    from im_drive_sim.cli import drive_file

    monkeypatch.chdir(tmp_path)
    assert str(drive_file('im7500w-j10')) == 'im7500w-j10'
    with pytest.raises(argparse.ArgumentTypeError, match=r'^im9-j3: no such drive file.*im750w-j1'):
        drive_file('im9-j3')
    with pytest.raises(argparse.ArgumentTypeError, match=r'missing\.yaml: no such file'):
        drive_file('missing.yaml')
    (tmp_path / 'mine.yaml').write_text('x: 1')
    assert drive_file('mine.yaml') == tmp_path.joinpath('mine.yaml').relative_to(tmp_path)


def test_a_users_file_may_take_a_packaged_drive_as_its_base(tmp_path):
    mine = tmp_path / 'mine.yaml'
    mine.write_text('base: im7500w-j3\nmachine:\n  isq_max: 30.0\n')
    cfg = load_config(mine)
    assert cfg.machine.J == load_config('im7500w-j3').machine.J == 0.1372
    assert cfg.machine.isq_max == 30.0 and cfg.machine.Rs == 0.7384
    chain = tmp_path / 'chain.yaml'
    chain.write_text('base: mine.yaml\n')  # a user's base with a base: still one level
    with pytest.raises(ConfigError, match='has a base'):
        load_config(chain)
