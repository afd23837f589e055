"""Each drive's setup (im_tuner.family.drive_setup): the paper's is today's exactly; the
rule's ratios; every drive's start is finite and not aborted offline."""

from __future__ import annotations

import dataclasses

import pytest

from im_controller.config import ExperimentConfig, Gains
from im_drive_sim.params import ConfigError, load_config
from im_tuner.family import DRIVE_NAMES, PACKAGED_NAMES, drive_scales, drive_setup
from im_tuner.space import load_params


def _today() -> ExperimentConfig:
    base = ExperimentConfig()
    drive = load_config(None)
    ctl = dataclasses.replace(base.control, Ts=drive.Ts, isq_max=drive.machine.isq_max)
    return dataclasses.replace(base, control=ctl)


@pytest.mark.parametrize('drive', [None, 'paper_750w', 'im750w-j1'])
def test_paper_setup_is_todays_exactly(drive):
    s = drive_setup(drive)
    assert s.experiment == _today()
    assert s.params == load_params(None)
    assert s.drive == load_config(None)
    assert s.name == (drive or 'paper_750w')
    assert s.experiment.fallback_gains == Gains()


def test_realism_and_model_reach_the_drive():
    s = drive_setup('im3700w-j3', realism='bench', model='reduced')
    assert (s.drive.realism, s.drive.model) == ('bench', 'reduced')
    assert s.drive.machine.J == load_config('im3700w-j3').machine.J


def test_unknown_drive_refused_in_one_line():
    with pytest.raises(ConfigError) as exc:
        drive_setup('im2200w-j3')
    assert '\n' not in str(exc.value) and 'im7500w-j10' in str(exc.value)


@pytest.mark.parametrize('name', DRIVE_NAMES)
def test_rule(name):
    s = drive_setup(name)
    m, e, sp = s.drive.machine, s.experiment, s.params.space
    k = drive_scales(m)
    p = load_config(None).machine
    # the move and the load step ask the same fractions of rated torque as the paper's
    assert e.trajectory.a_max * m.J / m.rated_torque == pytest.approx(600 * p.J / p.rated_torque)
    assert e.trajectory.load_torque == pytest.approx(0.7 * m.rated_torque)
    assert e.trajectory.v_max == 40.0
    # the speed loop's gain k_pw Kt/J and corner k_iw/k_pw are the paper's
    assert sp.start[0] * m.Kt / m.J == pytest.approx(0.53 * p.Kt / p.J)
    assert sp.start[1] / sp.start[0] == pytest.approx(20.0 / 0.53)
    assert sp.start[2:] == (30.0, 0.005, 0.007)
    assert e.fallback_gains.as_tuple() == sp.start
    assert (sp.lo[0], sp.hi[0], sp.hi[1]) == pytest.approx(
        (0.05 * k.inertia, 3.0 * k.inertia, 200.0 * k.inertia)
    )
    assert (e.control.Ts, e.control.isq_max) == (s.drive.Ts, m.isq_max)
    assert s.name in PACKAGED_NAMES
