"""The drive contract module is what every side uses: the simulator's and the
example drive's counters, layouts and QoS are the contract's, not copies of it."""

from __future__ import annotations

import dataclasses

from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

from im_drive_sim import contract, kernels, model_layout
from im_drive_sim.drive_sim_counters import Counters
from im_drive_sim.example_drive import Counters as ExampleCounters
from im_drive_sim.qos import LOCKSTEP_QOS, RECORDED_QOS, qos_profile


def test_status_counters_are_the_simulators_counters() -> None:
    assert {f.name for f in dataclasses.fields(Counters)} == set(contract.STATUS_COUNTERS)
    # the example drive (real time only) counts all but the lock-step re-sends
    example = {f.name for f in dataclasses.fields(ExampleCounters)}
    assert example <= set(contract.STATUS_COUNTERS)
    assert set(contract.STATUS_COUNTERS) - example == {'republished'}


def test_layouts() -> None:
    assert kernels.STATE_FIELDS is model_layout.STATE_FIELDS is contract.STATE_FIELDS
    assert contract.STATE_INDEX['step_index'] == 0 and contract.STATE_INDEX['omega'] == 11
    assert contract.COMMAND_FIELDS[contract.CMD_STEP] == 'answers_step'
    assert contract.COMMAND_FIELDS[contract.CMD_ISQ] == 'isq_ref'
    assert contract.COMMAND_FIELDS[contract.CMD_LOAD] == 'load_torque'
    assert set(contract.TOPIC_TYPES) == {
        contract.STATE_TOPIC,
        contract.COMMAND_TOPIC,
        contract.JOINT_STATE_TOPIC,
        contract.STATUS_TOPIC,
    }


def test_qos_profiles_from_the_contract() -> None:
    assert qos_profile(contract.LOCKSTEP) == LOCKSTEP_QOS
    assert LOCKSTEP_QOS.history == HistoryPolicy.KEEP_LAST and LOCKSTEP_QOS.depth == 64
    assert LOCKSTEP_QOS.reliability == ReliabilityPolicy.RELIABLE
    assert RECORDED_QOS.history == HistoryPolicy.KEEP_ALL
    assert RECORDED_QOS.reliability == ReliabilityPolicy.RELIABLE
    assert RECORDED_QOS.durability == DurabilityPolicy.VOLATILE


def test_a_minimal_drive_file_takes_the_rest_from_its_base(tmp_path):
    """A real drive's file (docs/real-drive.md): only what the controller reads and what is
    known; ``base`` names the file that gives the rest."""
    import pytest

    from im_drive_sim.drive_file import load_config
    from im_drive_sim.params import ConfigError

    f = tmp_path / 'my_drive.yaml'
    f.write_text('base: paper_750w\nTs: 200.0e-6\nmachine:\n  isq_max: 5.0\n')
    cfg, full = load_config(f), load_config(None)
    assert (cfg.Ts, cfg.machine.isq_max) == (2e-4, 5.0)
    assert cfg.machine.J == full.machine.J and cfg.sensors == full.sensors
    (tmp_path / 'other.yaml').write_text(f.read_text().replace('5.0', '6.0'))
    f.write_text('base: other.yaml\nmachine:\n  isq_max: 4.0\n')  # a base with a base
    with pytest.raises(ConfigError, match='has a base'):
        load_config(f)
    f.write_text('base: nowhere\nTs: 200.0e-6\n')
    with pytest.raises(ConfigError, match=r"my_drive\.yaml: base 'nowhere': cannot read"):
        load_config(f)
    f.write_text('base: paper_750w\nmachine:\n  isq_max: -1.0\n')
    with pytest.raises(ConfigError, match=r'machine\.isq_max'):
        load_config(f)


def test_the_example_drives_counts_are_published_exact() -> None:
    # %g would print 1.23457e+06 after about 250 s at 5 kHz
    c = ExampleCounters(steps=1_234_567, fresh=10**9 + 1, max_lateness_us=12.5)
    texts = c.texts()
    assert texts['steps'] == '1234567' and texts['fresh'] == '1000000001'
    assert texts['max_lateness_us'] == '12.5' and texts['overruns'] == '0'
    assert list(texts) == [f.name for f in dataclasses.fields(ExampleCounters)]
