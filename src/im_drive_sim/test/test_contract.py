"""The drive contract module is what every side uses (issue 17): the simulator's and the
example drive's counters, layouts and QoS are the contract's, not copies of it."""

from __future__ import annotations

import dataclasses

from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

from im_drive_sim import contract, kernels
from im_drive_sim.drive_sim_node import LOCKSTEP_QOS, RECORDED_QOS, Counters
from im_drive_sim.example_drive import Counters as ExampleCounters
from im_drive_sim.runtime import qos_profile


def test_status_counters_are_the_simulators_counters() -> None:
    assert {f.name for f in dataclasses.fields(Counters)} == set(contract.STATUS_COUNTERS)
    # the example drive (real time only) counts all but the lock-step re-sends
    example = {f.name for f in dataclasses.fields(ExampleCounters)}
    assert example <= set(contract.STATUS_COUNTERS)
    assert set(contract.STATUS_COUNTERS) - example == {'republished'}


def test_layouts() -> None:
    assert kernels.STATE_FIELDS is contract.STATE_FIELDS
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
