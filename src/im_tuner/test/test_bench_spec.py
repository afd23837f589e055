"""Which bench, built how (im_tuner.bench.spec), without ROS: the tuner's options and
run.yaml to a BenchSpec, the spec to a plan per mode, and what a resumed run may change."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from im_drive_sim.cli import UsageError
from im_tuner.bench.spec import BenchSpec, next_experiment_id, tuner_bench_spec
from im_tuner.benches import DISCOVERY_TIMEOUT
from im_tuner.runlog import Lost, RunConfig
from im_tuner.tuner_args import parse_options


def _cli(*args: str):
    cli = parse_options(list(args))
    cli.compression = cli.compression or 'lz4'  # (tuner_cli.check_session's default)
    return cli


def _run(**fields) -> RunConfig:
    return RunConfig.from_dict({'algo': 'safe', **fields})


NEW_RUN = {'drive_seed': 77, 'drive': 'sim', 'timing_tolerance': 10}


def test_a_new_runs_spec_takes_the_command_line():
    cli = _cli('--model', 'reduced', '--drive-config', 'motor.yaml', '--no-record')
    spec = tuner_bench_spec(cli, _run(**NEW_RUN), resumed=False)
    assert spec.requested == 'auto' and spec.drive == 'sim' and not spec.resumed
    assert spec.drive_parameters == (
        ('seed', 77),
        ('model', 'reduced'),
        ('config_file', 'motor.yaml'),
    )
    assert spec.controller_parameters == (
        ('timing_tolerance', 10),
        ('drive_config_file', 'motor.yaml'),
    )
    assert (spec.record, spec.compression, spec.controller) == (False, 'lz4', '/controller')
    assert spec.next_experiment_id == 0 and spec.previous_bench is None
    assert spec.probe_timeout() == DISCOVERY_TIMEOUT['auto'] == 2.0
    bare = tuner_bench_spec(_cli('--bench', 'none'), _run(**NEW_RUN), resumed=False)
    assert bare.drive_parameters == (('seed', 77),) and bare.controller_parameters == (
        ('timing_tolerance', 10),
    )
    assert bare.probe_timeout() == 20.0
    given = tuner_bench_spec(_cli('--discovery-timeout', '7.5'), _run(**NEW_RUN), resumed=False)
    assert given.probe_timeout() == 7.5


def test_a_resumed_runs_spec_takes_run_yaml_and_goes_on_past_its_ids():
    run = _run(
        drive_seed=5,
        drive='sim',
        model='full',
        drive_config='m.yaml',
        bench_requested='realtime',
        bench='realtime',
        timing_tolerance=14,
    )
    records = [
        Lost(kind='eval', eval=i, gains={}, experiment_id=n) for i, n in enumerate((3, None, 11))
    ]
    spec = tuner_bench_spec(_cli('--resume', 'r'), run, resumed=True, records=records)
    assert spec.requested == 'realtime' and spec.previous_bench == 'realtime'
    assert spec.drive_parameters == (('seed', 5), ('model', 'full'), ('config_file', 'm.yaml'))
    assert spec.next_experiment_id == 12
    plan = spec.resolve('realtime')
    assert plan.simulated and not plan.replays and plan.first_experiment_id == 12
    assert plan.controller_parameters == (
        ('timing_tolerance', 14),  # the run's, for every controller the tuner starts
        ('drive_config_file', 'm.yaml'),
        ('first_experiment_id', 12),
    )
    assert plan.counts_experiment_ids and plan.fault_policy == 'reset'
    # --bench given on resume wins over run.yaml's request
    assert (
        tuner_bench_spec(_cli('--resume', 'r', '--bench', 'inproc'), run, resumed=True).requested
        == 'inproc'
    )
    assert next_experiment_id([]) == 0


@pytest.mark.parametrize(
    ('mode', 'drive', 'simulated', 'replays', 'policy'),
    [
        ('inproc', 'sim', True, True, 'reset'),
        ('processes', 'sim', True, True, 'reset'),
        ('realtime', 'sim', True, False, 'reset'),
        ('realtime', 'example', True, False, 'reset'),
        ('realtime-processes', 'sim', True, False, 'reset'),
        ('realtime', 'my_pkg.hw:Hardware', False, False, 'stop'),
        ('external', 'sim', False, False, 'stop'),
    ],
)
def test_each_mode_plans_its_replay_ids_and_fault_policy(mode, drive, simulated, replays, policy):
    plan = BenchSpec(requested=mode, drive=drive, next_experiment_id=4).resolve(mode)
    assert (plan.mode, plan.simulated, plan.replays, plan.fault_policy) == (
        mode,
        simulated,
        replays,
        policy,
    )
    # ids go on past the run's only where the bench's controller is ours and no replay
    ours = mode != 'external' and not replays
    assert plan.first_experiment_id == (4 if ours else 0)
    assert plan.counts_experiment_ids == ours
    assert (
        BenchSpec(requested=mode, drive=drive, fault_policy='stop').resolve(mode).fault_policy
        == 'stop'
    )


def test_auto_and_none_are_resolved_on_the_graph_first():
    for mode in ('auto', 'none'):
        with pytest.raises(ValueError, match='resolve it on the graph first'):
            BenchSpec(requested=mode).resolve(mode)


@pytest.mark.parametrize(
    ('before', 'now', 'drive', 'why'),
    [
        ('inproc', 'external', 'sim', 'the plant history cannot be restored'),
        ('external', 'inproc', 'sim', 'the plant history cannot be restored'),
        ('inproc', 'realtime', 'sim', 'lock-step and real time do not mix'),
        ('realtime-processes', 'processes', 'sim', 'lock-step and real time do not mix'),
    ],
)
def test_a_resume_may_not_change_the_plant(before, now, drive, why):
    spec = BenchSpec(requested=now, drive=drive, resumed=True, previous_bench=before)
    with pytest.raises(UsageError, match=why) as err:
        spec.resolve(now)
    assert f'the run used bench {before!r}, now {now!r}' in str(err.value)


@pytest.mark.parametrize(
    ('before', 'now', 'drive'),
    [
        ('inproc', 'processes', 'sim'),  # both lock-step: the replay is bit for bit
        ('realtime', 'realtime-processes', 'sim'),  # both real time: no replay
        ('external', 'external', 'sim'),
        ('realtime', 'realtime', 'my_pkg.hw:Hardware'),  # a real drive: where it is
    ],
)
def test_a_resume_may_change_what_keeps_the_plant(before, now, drive):
    plan = BenchSpec(requested=now, drive=drive, resumed=True, previous_bench=before).resolve(now)
    assert plan.mode == now


def test_the_childrens_command_lines():
    spec = BenchSpec(
        requested='realtime-processes',
        drive_parameters=(('seed', 3), ('model', 'full')),
        controller_parameters=(('drive_config_file', 'm.yaml'),),
        next_experiment_id=9,
    )
    plan = spec.resolve('realtime-processes')
    quiet = ['--ros-args', '--disable-stdout-logs']
    assert plan.child_args('drive_sim') == [
        '--mode',
        'realtime',
        *quiet,
        *['-p', 'seed:=3', '-p', 'model:=full'],
    ]
    assert plan.child_args('controller') == [
        '--mode',
        'realtime',
        *quiet,
        *['-p', 'drive_config_file:=m.yaml', '-p', 'first_experiment_id:=9'],
    ]
    lockstep = BenchSpec(requested='processes', drive_parameters=(('seed', 3),), quiet=False)
    assert lockstep.resolve('processes').child_args('drive_sim') == ['-p', 'seed:=3']
    # sim_bench's children take its own flags and the user's --ros-args as given
    given = BenchSpec(
        requested='processes',
        child_args=(('--seed', '2', '--ros-args', '-p', 'a:=1'), ('--ros-args', '-p', 'a:=1')),
    ).resolve('processes')
    assert given.child_args('drive_sim') == ['--seed', '2', '--ros-args', '-p', 'a:=1']
    assert given.child_args('controller') == ['--ros-args', '-p', 'a:=1']


def test_the_spec_imports_no_ros():
    code = (
        'import sys, im_tuner.bench.spec, im_tuner.bench.drive_status, im_tuner.tuner_session\n'
        "bad = [m for m in sys.modules if m.split('.')[0] in ('rclpy', 'diagnostic_msgs')]\n"
        'assert not bad, bad\n'
    )
    proc = subprocess.run(
        [sys.executable, '-c', code], capture_output=True, text=True, cwd=Path.cwd()
    )
    assert proc.returncode == 0, proc.stderr
