"""The tuner: ``ros2 run im_tuner tuner --algo {spsa,necga,cga,pecga,rcga}``.

Tunes the five gains of the cascaded position controller (paper eq. 8) online: for each
evaluation it sets the gains on the controller through its parameter services
(atomically), starts the paper's experiment, waits for the loss, and tells the optimiser
(:mod:`im_tuner.tuning`, :mod:`im_tuner.link`, :mod:`im_tuner.optim`).

Benches (``--bench``):

* ``auto`` (default): a controller already on the graph (a real bench, or a simulated
  one started by hand) is used as it is; otherwise the simulated bench is brought up in
  this process (``inproc``);
* ``inproc``: drive simulator + controller in this process, lock-step (the fast path),
  with the recorder polled between steps;
* ``processes``: ``drive_sim`` and ``controller`` as child processes (lock-step);
* ``realtime``: ``drive_sim`` and ``controller`` as child processes in real time (5 kHz
  on the wall clock, as on a real bench); the drive's overruns and late commands are
  reported in the summary;
* ``none``: use the controller on the graph; fail with a clear message if none answers.

Bench processes started here end with the tuner (even a SIGKILLed one: they get SIGTERM
from the kernel and stop cleanly). A recorder child that dies is replaced (its bag is
repaired, the gap logged); a drive or controller child that dies ends the run.

Everything is recorded (``bag_<session>/`` in the run directory) unless ``--no-record``:
in-process by the bench's loop, otherwise by a ``ros2 run im_tuner recorder`` child.
The run directory (``--out``, default ``bags/tuner_<algo>_<UTC time>``) holds
``run.yaml``, ``results.jsonl``, ``checkpoint.json``, ``summary.json`` and the bags;
``--resume RUN_DIR`` continues a killed run exactly (docs/tuner.md).

The pieces: ``tuner_cli`` (options, run configuration, resume checks), ``bench.forms``
(the benches behind one protocol), ``link`` (the controller link), ``tuning`` (the
ask/measure/tell loop and its record), ``progress`` (what is printed). This module parses,
opens the bench, runs and closes.

Exit codes: 0 done, 1 the bench failed (best gains applied, bag closed), 2 bad input,
130 interrupted (SIGINT/SIGTERM; resumable).
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

# Only what parsing and checking need: rclpy, the benches, numba kernels, pycma... are
# imported once every check passed (tuner_cli), so a refusal is one line at once.
from im_drive_sim import rt
from im_drive_sim.cli import UsageError, check_ros_args

from .benches import IN_PROCESS_BENCHES, LOCKSTEP_BENCHES, SIM_BENCHES, is_simulated
from .tuner_cli import (
    DISCOVERY_TIMEOUT,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    RUN_SETTINGS,
    _build_parser,
    _check_controller_name,
    _check_run,
    _make_tuning,
    _new_run_config,
    _params_of_run,
    check_session,
)

if TYPE_CHECKING:
    from .rundir import RunDir


def _repair_old_bags(rundir: RunDir, note, current: Path | None) -> None:
    """Bags of killed sessions still say state 'recording': repair them (index, summary,
    metadata.yaml) so that the whole run opens in any reader. ``current``: this session's
    bag, being recorded (it is not a killed session's)."""
    import yaml

    from .record.repair import RepairError, repair_bag

    for bag in rundir.bag_dirs():
        if current is not None and bag == current:
            continue
        try:
            meta = yaml.safe_load((bag / 'metadata.yaml').read_text())
            state = meta['rosbag2_bagfile_information']['custom_data'].get('im_tuner.state')
        except (OSError, KeyError, TypeError, yaml.YAMLError):
            state = 'recording'
        if state == 'recording':
            try:
                rep = repair_bag(bag)
                note(f'repaired the bag of the killed session: {rep.summary().splitlines()[0]}')
            except RepairError as exc:
                note(f'warning: could not repair {bag}: {exc}')


#: [s] the --discovery-timeout a discovery-timeout message suggests for a loaded machine
SLOW_DISCOVERY_HINT_S = 20.0


def failure_advice(outcome: str, records: list[dict[str, Any]], bench: str) -> list[str]:
    """What to do about a failed run, for the summary (empty: nothing to say). A run that
    failed because its experiments kept coming out ``timing`` (held or late periods
    beyond the tolerance) is told where the controller should run."""
    if not (outcome.startswith('failed') and records and records[-1]['status'] == 'timing'):
        return []
    if bench in IN_PROCESS_BENCHES:
        return [
            'the experiments kept coming out `timing` although the controller runs in the '
            "drive's process: the composed loop itself started periods late (the drive "
            "line's overruns and worst lateness; a loaded machine). Run on a less loaded "
            'machine or core, or allow a few held periods per experiment with --ros-args -p '
            'timing_tolerance:=N and say so with the results (docs/real-drive.md, "Timing")'
        ]
    where = 'a separate controller process' if bench != 'external' else 'the external controller'
    return [
        f'the experiments kept coming out `timing`: {where} did not answer every 200 us '
        'drive period (one DDS round trip between two Python processes takes about as long '
        'as the period on a 2-core machine, and any other load makes it miss). Run the '
        "controller in the drive's process: `ros2 run im_tuner tuner --bench realtime` "
        '(simulated) or `--bench realtime --drive my_pkg.my_hw:MyHardware` with your '
        "drive's hardware class (docs/real-drive.md)"
    ]


def next_experiment_id(records: list[dict[str, Any]]) -> int:
    """The first experiment id of a session that does not replay: past every id in the
    run's records (0 for none)."""
    ids = [int(r['experiment_id']) for r in records if r.get('experiment_id') is not None]
    return max(ids) + 1 if ids else 0


def session_number(sessions: list[dict[str, Any]], records: list[dict[str, Any]]) -> int:
    """This session's number (0-based): after every session the checkpoint lists and
    every session a record names (a rebuilt checkpoint lists none)."""
    named = [int(r['session']) + 1 for r in records if isinstance(r.get('session'), int)]
    return max([len(sessions), *named])


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv if args is None else args)
    try:
        cli = _build_parser().parse_args(check_ros_args(argv)[1:])
        check_session(cli)
    except UsageError as exc:
        print(f'error: tuner: {exc}', file=sys.stderr)
        return EXIT_USAGE
    try:
        return _main(cli, argv)
    except UsageError as exc:
        print(f'error: tuner: {exc}', file=sys.stderr)
        return EXIT_USAGE
    finally:
        # a hardware class built by the checks and never taken by a bench (a refusal or a
        # failure on the way): closed, whatever the way out
        spec = sys.modules.get('im_tuner.bench.drive_spec')
        if spec is not None:
            spec.close_untaken()


def _made_by_create(out: Path) -> tuple[Path, bool]:
    """What ``RunDir.create(out)`` will make: the topmost missing directory of ``out``
    (itself or a parent), or ``out`` itself if it is an existing empty directory (then
    only its contents are ours: the bool is False)."""
    if out.exists():
        return out, False
    made = out
    while not made.parent.exists() and made.parent != made.parent.parent:
        made = made.parent
    return made, True


def _undo_create(made: tuple[Path, bool] | None) -> None:
    """A new run refused once its directory exists (a ``-p`` the controller refuses, a
    drive node class whose constructor raises): leave nothing behind."""
    if made is None:
        return
    path, whole = made
    if whole:
        shutil.rmtree(path, ignore_errors=True)
    elif path.is_dir():
        for child in path.iterdir():
            shutil.rmtree(child) if child.is_dir() else child.unlink()


def _main(cli: argparse.Namespace, argv: list[str]) -> int:
    t_wall0 = time.monotonic()
    # ---- validate everything before creating anything (tuner_cli: before importing ROS) ----
    from .bench.drive_spec import DriveSpecError, resolve

    drive_choice = None
    if cli.resume is not None:
        given = [k for k in RUN_SETTINGS if getattr(cli, k) not in (None, False)]
        given += [k[4:] for k, v in vars(cli).items() if k.startswith('opt_') and v is not None]
        if cli.out is not None:
            given.append('out')
        if given:
            raise UsageError(
                "--resume takes the run's settings from RUN_DIR/run.yaml; do not "
                'also give ' + ', '.join('--' + g.replace('_', '-') for g in given)
            )
        from .rundir import RunDir, RunDirError
        from .space import TunerParamsError

        try:
            rundir = RunDir.open(cli.resume)
            rundir.lock()  # one tuner per run, from here to the end of the process
            run = rundir.read_run()
            _check_run(run, str(rundir.path / 'run.yaml'))
            params = _params_of_run(run)
        except (RunDirError, TunerParamsError) as exc:
            raise UsageError(f'--resume: {exc}') from None
        _check_controller_name(cli.controller)
        # everything of the run is checked before anything starts (a refusal changes
        # nothing; the torn tail of results.jsonl is cut only once the run goes on)
        from .optim.base import OptimizerError
        from .progress import Progress
        from .tuning import ResumeError

        progress = Progress(run['algo'], run['budget'], cli.quiet)
        try:
            tuning = _make_tuning(rundir, run, params, progress)
            n_restored = tuning.restore()
        except (OptimizerError, ValueError, TypeError) as exc:
            raise UsageError(f'--resume: {rundir.path}/run.yaml: {exc}') from None
        except ResumeError as exc:
            raise UsageError(f'--resume: {exc}') from None
        bench_mode = cli.bench or run.get('bench_requested', 'auto')
        if (run.get('drive') or 'sim') != 'sim':
            try:  # the run's drive: checked (and a hardware class built) as for a new run
                drive_choice = resolve(str(run['drive']), run.get('drive_config'))
            except DriveSpecError as exc:
                raise UsageError(f'--resume: {exc}') from None
        made = None
    else:
        new = _new_run_config(cli, argv)
        run, params, drive_choice = new.run, new.params, new.drive
        out = new.out
        if out is None:
            from .record.node import default_out_dir

            out = default_out_dir(prefix=f'tuner_{run["algo"]}')
        rundir = None
        made = _made_by_create(out)
        bench_mode = cli.bench or 'auto'
        run['bench_requested'] = bench_mode
        from .progress import Progress

        progress = Progress(run['algo'], run['budget'], cli.quiet)

    # ---- ROS ---------------------------------------------------------------------------------
    from rclpy.context import Context
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from im_controller.config import ControllerConfigError
    from im_controller.controller_node import ControllerError
    from im_drive_sim.contract import STATE_TOPIC
    from im_drive_sim.params import ConfigError
    from im_drive_sim.runtime import ParameterOverrideError, RosSession

    from .bench import forms
    from .link import ControllerLink, controller_topics, drive_delta
    from .progress import format_summary
    from .rundir import RunDir, RunDirError
    from .tuning import BenchFailure, ResumeError, StopRequested, replay, replay_plan

    #: what a node of the in-process bench refuses at start: its -p overrides (ranges,
    #: types, the controller's cross-checks such as a move longer than the experiment),
    #: the drive file, a user's drive class
    node_refusals = (
        ConfigError,
        ControllerConfigError,
        ControllerError,
        DriveSpecError,
        InvalidParameterTypeException,
        InvalidParameterValueException,
        ParameterOverrideError,
    )
    ros_args = ['--ros-args', '--disable-stdout-logs']  # the tuner prints its own progress
    if '--ros-args' in argv:
        ros_args = [*argv[argv.index('--ros-args') :], '--disable-stdout-logs']
    ctx = Context()
    ros = RosSession([argv[0], *ros_args], context=ctx)

    def should_stop() -> bool:
        return ros.stopped

    bench: forms.Bench | None = None
    node = None
    exe = None
    bag_dir: Path | None = None
    discard_bag = False
    refused = False
    code = EXIT_OK
    try:
        node = Node('tuner', context=ctx, start_parameter_services=False)
        exe = forms.Executor(ctx)
        exe.executor.add_node(node)
        spin_until = exe.spin_until
        if bench_mode in ('auto', 'none'):
            if cli.discovery_timeout is None:
                cli.discovery_timeout = DISCOVERY_TIMEOUT[bench_mode]
            found = forms.controller_on_graph(
                node, spin_until, cli.controller, cli.discovery_timeout
            )
            if bench_mode == 'none' and not found:
                raise BenchFailure(
                    f'no controller reachable ({controller_topics(cli.controller)["start"]} '
                    f'not on the graph of ROS_DOMAIN_ID {os.environ.get("ROS_DOMAIN_ID", "0")} '
                    f'after {cli.discovery_timeout:g} s): start the bench first, e.g. '
                    '`ros2 run im_tuner sim_bench` or your drive + `ros2 run '
                    'im_controller controller`, or use --bench auto; if it is running, '
                    'discovery is slow (a loaded machine): give it longer, e.g. '
                    f'--discovery-timeout '
                    f'{max(SLOW_DISCOVERY_HINT_S, 3 * cli.discovery_timeout):g}'
                )
            bench_mode = 'external' if found else 'inproc'
        elif bench_mode == 'inproc' and forms.controller_on_graph(
            node, spin_until, cli.controller, 0.5
        ):
            raise BenchFailure(
                f'a controller ({cli.controller}) is already on the graph: '
                'tune it with --bench none, or use another ROS_DOMAIN_ID'
            )
        drive = run.get('drive') or 'sim'
        simulated = is_simulated(bench_mode, drive)
        if bench_mode in SIM_BENCHES and node.count_publishers('/' + STATE_TOPIC) > 0:
            # a drive without a controller: a second (simulated) drive would fight it
            raise BenchFailure(
                'a drive is publishing /drive/state but no controller answers '
                f'({cli.controller}): start `ros2 run im_controller controller` '
                'for it and use --bench auto, or stop that drive'
            )
        if cli.resume is not None and simulated != is_simulated(run.get('bench'), drive):
            raise UsageError(
                f'--resume: the run used bench {run.get("bench")!r}, now '
                f'{bench_mode!r}: the plant history cannot be restored'
            )
        if (
            cli.resume is not None
            and simulated
            and (bench_mode in LOCKSTEP_BENCHES) != (run.get('bench') in LOCKSTEP_BENCHES)
        ):
            raise UsageError(
                f'--resume: the run used bench {run.get("bench")!r}, now '
                f'{bench_mode!r}: lock-step and real time do not mix in a run'
            )
        fault_policy = cli.fault_policy or ('reset' if simulated else 'stop')

        # ---- the run directory ----------------------------------------------------------------
        if rundir is None:
            try:
                rundir = RunDir.create(out)
                rundir.lock()
            except RunDirError as exc:
                raise UsageError(str(exc)) from None
            run['bench'] = bench_mode
            tuning = _make_tuning(rundir, run, params, progress)
        bag_dir = None if cli.no_record else rundir.next_bag_dir()

        # ---- the bench ------------------------------------------------------------------------
        drive_over = [Parameter('seed', value=run['drive_seed'])]
        ctl_over = []
        if run.get('model'):
            drive_over.append(Parameter('model', value=run['model']))
        if run.get('drive_config'):
            drive_over.append(Parameter('config_file', value=run['drive_config']))
            ctl_over.append(Parameter('drive_config_file', value=run['drive_config']))
        # experiment ids unique within the run: a resume that does not replay (real time,
        # a real drive) starts this session's controller past the run's ids; lock-step
        # replays the killed sessions from id 0, bit for bit; an external controller's ids
        # are its own (the records carry their session)
        replays = simulated and bench_mode in LOCKSTEP_BENCHES
        first_id = 0
        if bench_mode in SIM_BENCHES and not replays:
            first_id = next_experiment_id(tuning.records)
            if first_id:
                ctl_over.append(Parameter('first_experiment_id', value=first_id))
        if cli.resume is None:
            run['model'] = cli.model
            run['drive_config'] = str(cli.drive_config) if cli.drive_config else None
            if cli.model:
                drive_over.append(Parameter('model', value=cli.model))
            if cli.drive_config:
                drive_over.append(Parameter('config_file', value=str(cli.drive_config)))
                ctl_over.append(Parameter('drive_config_file', value=str(cli.drive_config)))
        if bench_mode in IN_PROCESS_BENCHES:
            try:
                bench = forms.InProcess(
                    ctx,
                    node,
                    exe,
                    realtime=bench_mode == 'realtime',
                    rt_options=rt.RtOptions.from_cli(cli, rt.DEFAULT_PRIORITY),
                    drive=drive_choice or drive,
                    drive_overrides=drive_over,
                    controller_overrides=ctl_over,
                    bag_dir=bag_dir,
                    compression=cli.compression,
                    tuner_metadata={k: v for k, v in run.items() if k != 'search_box'},
                    command=argv,
                    should_stop=should_stop,
                )
            except node_refusals as exc:  # (nothing recorded yet: the nodes come first)
                raise UsageError(str(exc).strip().splitlines()[0]) from None
        else:
            bench = forms.Children(
                bench_mode,
                node,
                exe,
                controller=cli.controller,
                drive_overrides=drive_over,
                controller_overrides=ctl_over,
                bag_dir=bag_dir,
                compression=cli.compression,
                progress=progress,
            )
        if cli.resume is not None:
            # accepted: from here on the run directory changes
            rundir.cut_torn_tail()
            if tuning.rebuilt:
                progress.warn(f'warning: {tuning.rebuilt}; rebuilt from results.jsonl')
            # (after the bench is up, so that a refusal by its nodes changes nothing: skip
            # this session's bag, which its recorder has begun)
            _repair_old_bags(rundir, progress.note, bag_dir)
            progress.note(
                f'resuming {rundir.path}: {n_restored} records, '
                f'{tuning.state.evals}/{run["budget"]} evaluations done'
            )
        tuning.session = session_number(tuning.state.sessions, tuning.records)
        session: dict[str, Any] = {}
        if isinstance(bench, forms.Children):
            bench.attach(rundir, tuning, session)

        link = ControllerLink(
            node,
            bench.spin_until,
            controller=cli.controller,
            eval_timeout=cli.eval_timeout,
            fault_policy=fault_policy,
            should_stop=should_stop,
            supervise=bench.supervise,
            call_timeout=min(10.0, cli.eval_timeout),
        )
        if not link.wait_ready(30.0):
            raise BenchFailure(
                f'the controller {cli.controller} did not become reachable '
                'within 30 s (services and loss topic)'
            )
        if not bench.recording_ready(30.0):
            raise BenchFailure('the recorder child did not subscribe within 30 s')
        if isinstance(bench, forms.Children) and bench.mode == 'external':
            # a long-lived drive's counters run on from before this session: the summary
            # gives their difference over the session (link.drive_delta)
            bench.monitor.mark(bench.spin_until, 2.0)
        if cli.resume is None:
            run['controller_parameters'] = link.list_parameters()
            run['fault_policy'] = fault_policy
            rundir.write_run(run)
            progress.note(
                f'im_tuner: {run["algo"]} on the {bench_mode} bench, budget '
                f'{run["budget"]}, seed {run["seed"]}; run directory {rundir.path}'
            )
        session.update(
            {
                'session': tuning.session,
                'bag': bag_dir.name if bag_dir else None,
                'bench': bench_mode,
                'started': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
                'replayed': 0,
                'first_record': len(tuning.records),
            }
        )
        if bench_mode in SIM_BENCHES and not replays:
            session['first_experiment_id'] = first_id
        if cli.resume is not None and tuning.records:
            ids = f'; experiment ids go on from {first_id}' if first_id else ''
            if simulated and bench_mode not in LOCKSTEP_BENCHES:
                progress.note(
                    'real-time simulated bench: the plant starts again at rest '
                    f'(no replay); the search goes on from the checkpoint{ids}'
                )
            elif simulated:
                progress.note(
                    f'restoring the simulated plant: replaying '
                    f'{len(replay_plan(tuning.records))} experiments (checked bit '
                    'for bit)'
                )
                session['replayed'] = replay(link, tuning.records)
            else:
                progress.note(
                    ('external bench' if bench_mode == 'external' else 'a real drive')
                    + ': the plant is where it is; the search goes on from the checkpoint '
                    f'(no replay){ids}'
                )
        tuning.state.sessions.append(session)
        outcome = tuning.run(link, should_stop)
        drive_now = bench.drive_report()
        if isinstance(bench, forms.Children) and bench.mode == 'external':
            drive_now = drive_delta(bench.monitor.start, drive_now)
        session['drive'] = drive_now
        if link.faults_outside:
            # faults no result reported (a watchdog between experiments, one left from
            # before): counted with the records' faults, so the summary agrees with a
            # failure they caused
            session['faults_outside'] = list(link.faults_outside)
            tuning.state.faults += len(link.faults_outside)
        # the bag is closed before the summary: a bag that was not closed is a failure
        problems = bench.close_recording()
        for text in problems:
            progress.warn(f'error: {text}')
        if problems and outcome == 'done':
            outcome = f'failed: {problems[0]}'
        if outcome == 'interrupted':
            code = EXIT_INTERRUPTED
        elif outcome != 'done':
            code = EXIT_FAILED
        progress.close()
        summary = tuning.summary(outcome=outcome, wall_s=time.monotonic() - t_wall0)
        summary['report_command'] = f'ros2 run im_tuner report {shlex.quote(str(rundir.path))}'
        advice = failure_advice(outcome, tuning.records, bench_mode)
        if advice:
            summary['what_to_do'] = advice
        tuning._checkpoint()
        rundir.write_summary(summary)
        print(format_summary(summary, run, rundir.path), flush=True)
        if code == EXIT_INTERRUPTED:
            print(
                f'  interrupted: continue with `ros2 run im_tuner tuner --resume {rundir.path}`',
                flush=True,
            )
        elif code == EXIT_FAILED:
            print(
                '  failed: once the cause is fixed, continue with `ros2 run im_tuner tuner '
                f'--resume {shlex.quote(str(rundir.path))}`',
                flush=True,
            )
    except (BenchFailure, ResumeError) as exc:
        progress.close()
        print(f'error: tuner: {exc}', file=sys.stderr)
        code = EXIT_USAGE if isinstance(exc, ResumeError) else EXIT_FAILED
        # a replay that does not match refuses the resume: its bag holds only the replay
        discard_bag = isinstance(exc, ResumeError)
    except StopRequested:
        progress.close()
        print('tuner: interrupted before the search started', file=sys.stderr)
        code = EXIT_INTERRUPTED
    except UsageError:
        refused = True
        raise
    finally:
        if bench is not None:
            bench.close()
        if discard_bag and bag_dir is not None and bag_dir.exists():
            shutil.rmtree(bag_dir, ignore_errors=True)
        if node is not None:
            node.destroy_node()
        if exe is not None:
            exe.executor.shutdown()
        ros.close()
        if refused and cli.resume is None and rundir is not None:
            # refused by a node of the bench after the run directory was made: undo it
            rundir.unlock()
            _undo_create(made)
    return code


if __name__ == '__main__':
    os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    sys.exit(main())
