"""The tuner's run checks (im_tuner.tuner_cli) without a bench: the run's policies under
``--opt`` (``start=none``'s algorithms, safe's ``first``), the same rule on --resume
(run.yaml's ``options``), and what a new run's check leaves in run.yaml."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml

from im_drive_sim.cli import UsageError
from im_tuner import optim
from im_tuner.runlog import RunConfig
from im_tuner.tuner_args import build_parser, parse_options
from im_tuner.tuner_cli import _check_run, _new_run_config, _optimizer_args


def _new(*args: str):
    argv = ['tuner', *args]
    return _new_run_config(parse_options(argv[1:]), argv)


@pytest.mark.parametrize('algo', optim.ALGOS)
def test_start_none_is_for_spsa_cmaes_tpe_only(algo: str) -> None:
    """``--opt start=none`` is for spsa, cmaes and tpe only (their ``start`` policy): with
    safe (the default) it would start from a random point (its first experiment at k_pw
    2.02, k_iw 154, k_pos 8.2 instead of the hand-tuned 0.53, 20, 30), and the compact GAs
    take no start; both are refused, one line naming the options the algorithm has."""
    if algo in ('spsa', 'cmaes', 'tpe'):
        new = _new('--algo', algo, '--opt', 'start=none', '--seed', '4')
        assert new.run.options == {'start': 'none'} and new.run.algo == algo
        assert _optimizer_args(algo, new.run.options, new.params)['start'] is None
        hand = _new('--algo', algo, '--seed', '4')
        assert hand.run.options == {'start': 'hand'}  # (the default, kept in run.yaml)
        start = _optimizer_args(algo, hand.run.options, hand.params)['start']
        assert start.tolist() == hand.params.space.start_u.tolist()
        return
    with pytest.raises(UsageError) as exc:
        _new('--algo', algo, '--opt', 'start=none', '--seed', '4')
    msg = str(exc.value)
    assert msg.startswith(f'--opt start does not apply to --algo {algo} (its options: ')
    assert '\n' not in msg and 'start' not in msg.split('its options: ')[1].split(')')[0]
    assert msg.endswith('; start is an option of spsa, cmaes, tpe')  # (where it belongs)


def test_a_policy_value_is_one_of_its_declared_choices() -> None:
    spsa_start = "spsa option start must be one of 'hand', 'none', got 'random'"
    safe_first = "safe option first must be one of 'identify', 'model', 'none', got 'always'"
    for args, message in (
        (('--algo', 'spsa', '--opt', 'start=random'), spsa_start),
        (('--opt', 'first=always'), safe_first),
        (('--algo', 'tpe', '--opt', 'first=model'), '--opt first does not apply to --algo tpe'),
        (('--opt', 'start=hand'), '--opt start does not apply to --algo safe'),
    ):
        with pytest.raises(UsageError) as exc:
            _new('--seed', '4', *args)
        assert message in str(exc.value) and '\n' not in str(exc.value), str(exc.value)


def test_the_default_algorithm_refuses_start_none_and_starts_from_the_file() -> None:
    assert optim.DEFAULT_ALGO == 'safe'
    with pytest.raises(UsageError, match='--algo safe'):
        _new('--opt', 'start=none')
    new = _new('--seed', '3')
    space = new.params.space
    opt = optim.make_optimizer('safe', 5, 3, space.start_u)
    # its first experiment is the hand-tuned start (the packaged file's), exactly
    g = space.to_gains(opt.ask())
    assert (g.k_pw, g.k_iw, g.k_pos) == (pytest.approx(0.53), pytest.approx(20.0), 30.0)


@pytest.mark.parametrize(
    ('args', 'first'),
    [
        # auto (also not given): decided with the bench (None until then): identify on
        # the simulated drive it starts, none beside a controller it finds (first_on_bench)
        ((), None),
        (('--bench', 'auto'), None),
        (('--bench', 'auto', '--drive-config', 'paper_750w'), 'identify'),
        (('--bench', 'inproc'), 'identify'),
        (('--bench', 'processes'), 'identify'),
        (('--bench', 'none'), 'none'),  # a controller on the graph: a drive not known
        (('--bench', 'none', '--drive-config', 'paper_750w'), 'identify'),
        (('--no-reference',), 'none'),  # (identify needs the reference)
    ],
)
def test_safe_takes_the_identified_first_step_where_the_tuner_knows_the_drive(
    args: tuple[str, ...], first: str | None
) -> None:
    assert _new('--seed', '3', *args).run.options == {'first': first}


def test_opt_help_lists_the_policies_of_exactly_the_algorithms_that_take_them() -> None:
    """``--algo ALGO --opt help`` lists ALGO's policies after its hyperparameters, from
    optim.POLICIES: start for spsa, cmaes, tpe; first for safe; neither for the others."""
    assert sorted(optim.NO_START_ALGOS) == ['cmaes', 'spsa', 'tpe']
    assert sorted(optim.TAKES_FIRST) == ['safe']
    for algo in optim.ALGOS:
        text = optim.describe_options(algo)
        assert ("  start='hand': 'hand': from the parameter file's start point" in text) == (
            algo in optim.NO_START_ALGOS
        ), algo
        assert ('  first: the first step after the start' in text) == (algo == 'safe')
    action = next(a for a in build_parser()._actions if '--opt' in a.option_strings)
    assert 'sigma0 grow abort_shrink sigma_max remeasure_every model_every first (safe)' in (
        action.help
    )
    assert 'n_startup_trials n_ei_candidates multivariate start (tpe)' in action.help


def test_tuner_help_has_at_most_30_options() -> None:
    """The tuner's command line stays small: an algorithm's options and policies are
    ``--opt KEY=VALUE``, not a flag each (the option strings argparse knows, -h aside)."""
    actions = [a for a in build_parser()._actions if '-h' not in a.option_strings]
    assert len(actions) <= 30, [a.option_strings for a in actions]
    assert not {'--no-start', '--first'} & {s for a in actions for s in a.option_strings}


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
        'algo', 'budget', 'seed', 'params', 'remeasure', 'no_reference', 'model',
        'drive_config', 'retries', 'drive', 'timing_tolerance', 'ripple_limit',
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
        # long options whole: an abbreviation is an unknown argument
        (['--bud', '1'], 'unrecognized arguments: --bud 1'),
    ],
)
def test_a_declared_range_is_checked_by_the_parser(argv: list[str], message: str) -> None:
    with pytest.raises(UsageError) as exc:
        build_parser().parse_args(argv)
    assert str(exc.value) == message


def _resumed(algo: str, options: dict) -> None:
    """The optimiser a resume builds from a run.yaml with ``algo`` and ``options``."""
    new = _new('--algo', 'spsa', '--seed', '1')
    text = dataclasses.replace(new.run, algo=algo, options=options).to_text()
    run = RunConfig.from_text(yaml.safe_dump(yaml.safe_load(text), sort_keys=False))
    _check_run(run, 'run.yaml')
    assert run.options is not None
    optim.make_optimizer(algo, 5, 1, **_optimizer_args(algo, run.options, new.params))


def test_resume_keeps_the_same_rule() -> None:
    """run.yaml's ``options`` hold the run's policies as ``--opt`` gave them (safe's
    model point for first: model): a resume builds the same optimiser from them, and a
    policy the algorithm does not take, or a value not declared, is refused as ``--opt``
    refuses it."""
    for algo, options in (
        ('spsa', {'start': 'none'}),
        ('spsa', {'start': 'hand', 'c': 0.02}),
        ('necga', {}),
        ('safe', {'first': 'none'}),
        ('safe', {'first': 'identify'}),
        ('safe', {'first': [0.5] * 5}),
    ):
        _resumed(algo, options)
    for algo, options, message in (
        ('safe', {'start': 'none'}, "unknown option 'start' for safe"),
        ('necga', {'start': 'none'}, "unknown option 'start' for necga"),
        ('spsa', {'start': 'no'}, "spsa option start must be one of 'hand', 'none', got 'no'"),
        ('spsa', {'first': 'identify'}, "unknown option 'first' for spsa"),
        ('safe', {'first': 'model'}, 'safe: first must be 5 finite numbers in [0, 1]'),
    ):
        with pytest.raises(optim.OptimizerError) as exc:
            _resumed(algo, options)
        assert message in str(exc.value), str(exc.value)


def test_every_algorithm_that_takes_start_none_runs_without_a_start() -> None:
    for algo in optim.NO_START_ALGOS:
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


def test_the_study_names_the_policies_as_the_tuner_declares_them() -> None:
    """The study's grid cells give 'start' and 'first' the tuner's declared values
    (optim.POLICIES; 'random' is the study's own start, a parameter file to the tuner),
    and only to the algorithms that take them; its commands say them with --opt."""
    from types import SimpleNamespace

    from im_tuner.study.files import tuner_command
    from im_tuner.study.spec import StudySpec, grid

    cells = grid(optim.ALGOS)
    spec = StudySpec(runs=1, algos=optim.ALGOS)
    res = SimpleNamespace(cells=cells, spec=spec, run_seed=[1])
    said = set()
    for c, cell in enumerate(cells):
        for key, value in cell.options:
            if key in ('start', 'first'):
                choices = optim.POLICIES[cell.algo][key].choices
                assert value in (*choices, 'random'), (cell.label, key, value)
        assert not {'start', 'first'} & set(cell.opts)
        words = tuner_command(res, c, 0, Path('out')).split()
        said |= {w.split('=')[0] for w in words if w.startswith(('start=', 'first='))}
        assert '--no-start' not in words and '--first' not in words
    assert said == {'start', 'first'}


def test_the_other_command_lines_share_the_tuners_declarations() -> None:
    """sim_bench's, drive_host's and the study's parsers give their typed options (never a
    Namespace); an option they share with the tuner has its flag, choices and metavar
    (the drive file is --drive-config everywhere)."""
    from im_tuner import tuner_args
    from im_tuner.bench.drive_host_main import DriveHostOptions
    from im_tuner.bench.sim_bench_main import SimBenchOptions
    from im_tuner.study.cli import StudyOptions

    tuner = {a.dest: a for a in build_parser()._actions}
    for cls in (SimBenchOptions, DriveHostOptions, StudyOptions):
        parser = tuner_args.OptionsParser(cls)
        assert isinstance(parser.parse_args([]), cls)
        mine = {a.dest: a for a in parser._actions}
        shared = set(mine) & set(tuner) - {'help'}
        assert {'drive_config', 'seed', 'model', 'out'} <= shared, cls
        for dest in shared:
            a, t = mine[dest], tuner[dest]
            assert (a.option_strings, a.choices, a.metavar) == (
                t.option_strings,
                t.choices,
                t.metavar,
            ), (cls, dest)
    cli = tuner_args.OptionsParser(DriveHostOptions).parse_args(['--drive-config', 'im3700w-j3'])
    assert str(cli.drive_config) == 'im3700w-j3' and cli.drive == 'sim' and cli.tuner_timeout == 1.0
