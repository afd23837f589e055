"""The tuner's run checks (im_tuner.tuner_cli) without a bench: --no-start's algorithms,
the same rule on --resume (run.yaml ``start: false``), and what a new run's check leaves
in run.yaml."""

from __future__ import annotations

import dataclasses

import pytest
import yaml

from im_drive_sim.cli import UsageError
from im_tuner import optim
from im_tuner.runlog import RunConfig
from im_tuner.tuner_args import build_parser, parse_options
from im_tuner.tuner_cli import _check_run, _new_run_config, check_no_start


def _new(*args: str):
    argv = ['tuner', *args]
    return _new_run_config(parse_options(argv[1:]), argv)


@pytest.mark.parametrize('algo', optim.ALGOS)
def test_no_start_is_for_spsa_cmaes_tpe_only(algo: str) -> None:
    """--no-start is for spsa, cmaes and tpe only: with safe (the default) it would start
    from a random point (its first experiment at k_pw 2.02, k_iw 154, k_pos 8.2 instead of
    the hand-tuned 0.53, 20, 30), and the compact GAs would accept it and ignore it; both
    are refused."""
    if algo in ('spsa', 'cmaes', 'tpe'):
        new = _new('--algo', algo, '--no-start', '--seed', '4')
        assert new.run.start is False and new.run.algo == algo
        assert _new('--algo', algo, '--seed', '4').run.start is True
        return
    with pytest.raises(UsageError) as exc:
        _new('--algo', algo, '--no-start', '--seed', '4')
    msg = str(exc.value)
    assert msg.startswith(f'--no-start does not apply to --algo {algo}: ')
    assert msg.endswith('it is for spsa, cmaes, tpe') and '\n' not in msg
    if algo == 'safe':
        assert 'untested random controller' in msg
    else:
        assert f'{algo} takes no start point' in msg


def test_the_default_algorithm_refuses_no_start_and_starts_from_the_file() -> None:
    assert optim.DEFAULT_ALGO == 'safe'
    with pytest.raises(UsageError, match='--algo safe'):
        _new('--no-start')
    new = _new('--seed', '3')
    space = new.params.space
    opt = optim.make_optimizer('safe', 5, 3, space.start_u)
    # its first experiment is the hand-tuned start (the packaged file's), exactly
    g = space.to_gains(opt.ask())
    assert (g.k_pw, g.k_iw, g.k_pos) == (pytest.approx(0.53), pytest.approx(20.0), 30.0)


def test_the_help_names_exactly_the_algorithms_that_take_it() -> None:
    action = next(a for a in build_parser()._actions if '--no-start' in a.option_strings)
    assert action.help.startswith('spsa, cmaes, tpe only: ')
    assert {'spsa', 'cmaes', 'tpe'} == optim.NO_START_ALGOS
    refused = action.help.split('Refused', 1)[1]
    assert all(a in refused for a in optim.ALGOS if a not in optim.NO_START_ALGOS)


def test_every_option_is_declared_once_and_the_docs_table_is_generated_from_it() -> None:
    """The parser's options are tuner_args.OPTIONS (the real-time three included), each
    once; docs/tuner.md's table is options_table() (make docs writes it); the settings
    --resume takes from run.yaml are the declared run settings; a declared default is
    the parsed value of an option that is not a run setting."""
    from pathlib import Path

    from im_tuner import tuner_args

    flags = [o.flag for o in tuner_args.OPTIONS]
    assert len(flags) == len(set(flags))
    parser = build_parser()
    parsed = {s for a in parser._actions for s in a.option_strings} - {'-h', '--help'}
    assert parsed == set(flags)
    doc = Path(__file__).resolve().parents[3] / 'docs' / 'tuner.md'
    text = doc.read_text()
    table = text.split(tuner_args.TABLE_BEGIN + '\n', 1)[1].split(tuner_args.TABLE_END)[0]
    assert table == tuner_args.options_table(), 'docs/tuner.md: run make docs'
    assert '--budget' in text and '| `--budget N` | 200 |' in table
    assert set(tuner_args.RUN_SETTINGS) == {
        'algo', 'budget', 'seed', 'params', 'remeasure', 'no_reference', 'no_start', 'first',
        'model', 'drive_config', 'retries', 'drive', 'timing_tolerance', 'ripple_limit',
    }  # fmt: skip
    cli = parser.parse_args([])
    assert tuner_args.TunerOptions(**vars(cli)) == tuner_args.TunerOptions()  # one default
    defaults = {
        o.dest: o.default
        for o in tuner_args.OPTIONS
        if not o.run and o.arg != tuner_args.RT and o.default is not None
    }
    assert defaults == {'eval_timeout': 60.0, 'controller': '/controller'}
    assert all(getattr(cli, k) == v for k, v in defaults.items())
    new = _new('--seed', '2')
    assert (new.run.algo, new.run.budget, new.run.remeasure, new.run.retries) == (
        optim.DEFAULT_ALGO,
        200,
        3,
        3,
    )


@pytest.mark.parametrize(
    ('argv', 'message'),
    [
        (['--budget', '0'], 'argument --budget: must be >= 1, got 0'),
        (['--remeasure', '-1'], 'argument --remeasure: must be >= 0, got -1'),
        (['--retries', '-2'], 'argument --retries: must be >= 0, got -2'),
        (['--seed', '-1'], 'argument --seed: must be >= 0, got -1'),
        (['--eval-timeout', '0'], 'argument --eval-timeout: must be > 0 s, got 0'),
    ],
)
def test_a_declared_range_is_checked_by_the_parser(argv: list[str], message: str) -> None:
    with pytest.raises(UsageError) as exc:
        build_parser().parse_args(argv)
    assert str(exc.value) == message


def _run_yaml(algo: str, start: object, drop: tuple[str, ...] = ()) -> RunConfig:
    """A new run's run.yaml as a resume reads it, with ``algo`` and ``start``."""
    new = _new('--algo', 'spsa', '--seed', '1')
    text = dataclasses.replace(new.run, algo=algo, options={}, start=start).to_text()
    data = yaml.safe_load(text)
    for key in drop:
        del data[key]
    return RunConfig.from_text(yaml.safe_dump(data, sort_keys=False))


def test_resume_keeps_the_same_rule() -> None:
    """A run.yaml written with --no-start when any algorithm took it (``start: false``
    whatever the algo): safe's is refused as --no-start is; a compact GA's is harmless (it
    takes no start) and goes on; spsa's is the documented case; a start that is not a bool
    is refused."""
    _check_run(_run_yaml('spsa', False), 'run.yaml')
    _check_run(_run_yaml('necga', False), 'run.yaml')
    _check_run(_run_yaml('safe', True), 'run.yaml')
    run = _run_yaml('safe', False)
    with pytest.raises(UsageError) as exc:
        _check_run(run, 'R/run.yaml')
    assert str(exc.value).startswith(
        'R/run.yaml: start: false (--no-start) does not apply to --algo safe'
    )
    with pytest.raises(UsageError, match=r"start must be true or false, got 'no'"):
        _check_run(_run_yaml('spsa', 'no'), 'R/run.yaml')
    run = _run_yaml('safe', False, drop=('start',))  # a run.yaml without the key
    assert 'start' not in run.keys and run.start is None
    with pytest.raises(UsageError, match='start must be true or false, got None'):
        _check_run(run, 'run.yaml')


def test_check_no_start_accepts_what_the_optimisers_run_without_a_start() -> None:
    for algo in optim.NO_START_ALGOS:
        check_no_start(algo)
        opt = optim.make_optimizer(algo, 5, 2, None)  # a start of their own
        assert opt.ask().shape == (5,)


def test_the_composed_loop_runs_sched_fifo_50_unless_told_otherwise() -> None:
    """As ros2_control_node, the composed loop asks for SCHED_FIFO 50 when
    --thread-priority is not given; 0 is the normal policy; given with another bench it
    is refused (test_bad_input), not given it asks for nothing there."""
    from im_drive_sim import rt

    def opts(*args: str) -> rt.RtOptions:
        cli = parse_options(list(args))
        return rt.RtOptions.from_cli(cli, rt.DEFAULT_PRIORITY)

    assert rt.DEFAULT_PRIORITY == 50
    assert opts('--bench', 'realtime').priority == 50
    assert opts('--bench', 'realtime', '--thread-priority', '0').priority == 0
    assert opts('--bench', 'realtime', '--thread-priority', '70').priority == 70
    # another bench: nothing asked for unless given (then refused, exit 2)
    cli = parse_options(['--bench', 'inproc'])
    assert not rt.RtOptions.from_cli(cli).requested
    action = next(a for a in build_parser()._actions if '--thread-priority' in a.option_strings)
    assert "SCHED_FIFO at priority N, 1-99, as ros2_control_node's thread_priority" in action.help
    assert action.help.endswith('(default: 50)')


def test_the_ros_arguments_and_the_bag_options() -> None:
    from im_tuner.bench.spec import recording_options
    from im_tuner.tuner_args import ros_arguments
    from im_tuner.tuner_cli import check_session

    quiet = ['tuner', '--ros-args', '--disable-stdout-logs']
    assert ros_arguments(['tuner', '--budget', '3']) == quiet
    assert ros_arguments(['tuner', '--ros-args', '-p', 'a:=1']) == [
        'tuner',
        '--ros-args',
        '-p',
        'a:=1',
        '--disable-stdout-logs',
    ]
    cli = parse_options(['--no-record', '--compression', 'zstd'])
    with pytest.raises(UsageError, match=r'^--compression zstd is for the bag, and --no-record'):
        check_session(cli)
    cli = parse_options([])
    check_session(cli)
    assert cli.compression == 'lz4'
    assert recording_options(False, out='x', compression='zstd') == 'zstd'
    with pytest.raises(UsageError, match=r'^--out x is for the bag'):
        recording_options(True, out='x', compression=None)
    assert recording_options(True, out=None, compression=None) == 'lz4'


def test_a_resumed_run_keeps_the_parameters_its_command_gave():
    """--resume runs the bench with the -p parameters of the run's first command (a
    safety limit, an experiment parameter), its own after them; the tolerance is
    run.yaml's key, not repeated."""
    from im_tuner.tuner_args import ros_arguments, run_parameters

    run = RunConfig.from_dict(
        {
            'algo': 'safe',
            'command': 'ros2 run im_tuner tuner --bench inproc --ros-args '
            "-p 'safety.max_speed:=5.0' --param timing_tolerance:=3 -p move.distance:=6.28 "
            '--log-level warn',
        }
    )
    assert run_parameters(run) == ['-p', 'safety.max_speed:=5.0', '-p', 'move.distance:=6.28']
    argv = ['tuner', '--resume', 'r', '--ros-args', '-p', 'safety.max_speed:=9.0']
    assert ros_arguments(argv, run) == [
        'tuner', '--ros-args', '-p', 'safety.max_speed:=5.0', '-p', 'move.distance:=6.28',
        '-p', 'safety.max_speed:=9.0', '--disable-stdout-logs',
    ]  # fmt: skip
    assert ros_arguments(['tuner']) == ['tuner', '--ros-args', '--disable-stdout-logs']
    assert run_parameters(RunConfig.from_dict({'algo': 'safe', 'command': "x 'y"})) == []
