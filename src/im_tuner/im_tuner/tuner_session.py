"""One session of a tuner run: the run's side of the bench, from its start to its summary.

A :class:`TunerSession` is the :class:`im_tuner.bench.forms.RunHost` the tuner hands to
``open_bench``: once the bench is decided it makes the run directory of a new run and
the TuningRun (:meth:`begin`), gives a replaced recorder its new bag and books it
(:meth:`next_bag`, :meth:`bag_replaced`); then it starts the session (:meth:`accepted`,
:meth:`start`: run.yaml, the resume's replay, the session record) and ends it
(:meth:`finish`: the drive's counters, the bag closed, summary.json, the summary printed).
A new run refused once its directory exists is undone (:meth:`undo`). No rclpy at import.
"""

from __future__ import annotations

import ipaddress
import shlex
import shutil
import socket
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from im_drive_sim import numeric
from im_drive_sim.cli import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, UsageError, ros2_command

from .benches import IN_PROCESS_BENCHES, LOCKSTEP_BENCHES
from .rundir import RunDir, RunDirError, made_by_create
from .runlog import Record, Timing, replay_plan
from .tuner_cli import PreparedSession, first_on_bench, make_tuning

if TYPE_CHECKING:
    from .bench.forms import Bench
    from .bench.spec import BenchPlan
    from .link import ControllerLink
    from .tuner_args import TunerOptions


#: A composed loop whose period work (p50) takes more than this share of the period is
#: itself too slow: its late periods are the drive's, not the host's.
SLOW_DRIVE_SHARE = 0.5


def failure_advice(
    outcome: str, records: list[Record], bench: str, loop: dict[str, Any] | None = None
) -> list[str]:
    """What to do about a run that failed because its experiments kept coming out
    ``timing``, for the summary (empty: nothing to say): the cause on this bench
    (``loop``: the session's composed-loop figures)."""
    if not (outcome.startswith('failed') and records and isinstance(records[-1], Timing)):
        return []
    if bench in IN_PROCESS_BENCHES:
        loop = loop or {}
        work = (loop.get('period_work_us') or {}).get('p50')
        ts_us = 200.0
        if work is not None and work > SLOW_DRIVE_SHARE * ts_us:
            return [
                f'the experiments kept coming out `timing` because the drive is too slow: '
                f"each period's own work (your read and write, the model, the controller) "
                f'takes p50 {work:.0f} us of the {ts_us:.0f} us period, so periods start '
                'late whatever the machine does. Make the read and write return within a few '
                'tens of us: a compiled form runs a period in 6-14 us (docs/real-drive.md, '
                '"What each form costs")'
            ]
        check = (loop.get('realtime') or {}).get('host_check') or {}
        seen = (
            f' (the check before the run: late {check["late_pct"]:.3f} % of periods, 95 % of '
            f'experiments meet {check["tolerance"]})'
            if 'late_pct' in check
            else ''
        )
        return [
            'the experiments kept coming out `timing` although the controller runs in the '
            "drive's process and its period work is short: the host started periods late"
            f'{seen}; the drive line has the overruns and worst lateness. Check the host '
            '(`ros2 run im_drive_sim host_check`), run on a quieter machine or core, or allow '
            'the held periods it needs with --timing-tolerance auto (or N) and say so with '
            'the results (docs/real-drive.md, "Check the host first")'
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


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address, or a name: every address it resolves to) is this
    computer only (127.0.0.0/8, ``::1``)."""
    try:
        found = {a[4][0] for a in socket.getaddrinfo(host, None)}
    except OSError:
        return False
    return bool(found) and all(ipaddress.ip_address(a).is_loopback for a in found)


def resume_command(ros2: str, run_dir: Path, cli: TunerOptions) -> str:
    """The command that continues the run, for the user's shell (every value quoted): the
    live view is a session's own, so the command gives it again."""
    words = [ros2, 'run', 'im_tuner', 'tuner', '--resume', str(run_dir)]
    for flag, v in (('--live', cli.live), ('--live-host', cli.live_host)):
        words += [] if v is None else [flag, str(v)]
    words += [] if cli.live_rate is None else ['--live-rate', f'{cli.live_rate:g}']
    return ' '.join(shlex.quote(w) for w in words)


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


class TunerSession:
    """The run's side of one tuner session (module docstring)."""

    def __init__(self, cli: TunerOptions, argv: list[str], cfg: PreparedSession) -> None:
        self.cli = cli
        self.argv = argv
        self.run = cfg.run
        self.params = cfg.params
        self.progress = cfg.progress
        self.rundir = cfg.rundir  # (None: a new run, made by begin)
        self.tuning = cfg.tuning
        self.n_restored = cfg.n_restored
        self.out = cfg.out
        self.host_said = cfg.host_said
        self.resumed = cli.resume is not None
        #: what a new run's directory creation makes (undone if the run is refused)
        self.made = None if self.resumed else made_by_create(cfg.out)
        self.plan: BenchPlan | None = None
        self.bag_dir: Path | None = None
        #: this session's record in the checkpoint (its bags, its bench, its replay)
        self.session: dict[str, Any] = {}
        #: the live view's figures in one line, printed with the summary ('': no --live)
        self.live_said = ''

    # -- forms.RunHost -------------------------------------------------------------------
    def begin(self, plan: BenchPlan) -> Path | None:
        """The bench is decided: a new run's directory (locked) and TuningRun; this
        session's bag directory (None: --no-record)."""
        self.plan = plan
        if self.rundir is None:
            try:
                self.rundir = RunDir.create(self.out)
                self.rundir.lock()
            except RunDirError as exc:
                raise UsageError(str(exc)) from None
            self.run.put(bench=plan.mode)
        if not self.resumed:  # (before the TuningRun: its first step models this drive)
            config = str(self.cli.drive_config) if self.cli.drive_config else None
            self.run.put(model=self.cli.model, drive_config=config)
            options = self.run.options or {}
            if 'first' in options and options['first'] is None:  # (--bench auto)
                self.run.put(options={**options, 'first': first_on_bench(self.cli, plan.mode)})
        if self.tuning is None:
            self.tuning = make_tuning(self.rundir, self.run, self.params, self.progress)
        self.bag_dir = None if self.cli.no_record else self.rundir.next_bag_dir()
        return self.bag_dir

    def tuner_metadata(self) -> dict[str, Any] | None:
        return {k: v for k, v in self.run.to_dict().items() if k != 'search_box'}

    def next_bag(self) -> Path | None:
        assert self.rundir is not None
        return self.rundir.next_bag_dir()

    def bag_replaced(self, bag: Path) -> None:
        self.session.setdefault('more_bags', []).append(
            {'bag': bag.name, 'first_record': len(self.tuning.records)}
        )
        self.tuning.checkpoint()

    def warn(self, text: str) -> None:
        self.progress.warn(text)

    # -- the session ---------------------------------------------------------------------
    def accepted(self) -> None:
        """The bench is up (its nodes accepted their settings): from here on the run
        directory changes (a resume cuts results.jsonl's torn tail, repairs old bags)."""
        rundir, tuning, progress = self.rundir, self.tuning, self.progress
        assert rundir is not None
        if self.resumed:
            rundir.cut_torn_tail()
            if tuning.rebuilt:
                progress.warn(f'warning: {tuning.rebuilt}; rebuilt from results.jsonl')
            # (after the bench is up, so that a refusal by its nodes changes nothing: skip
            # this session's bag, which its recorder has begun)
            _repair_old_bags(rundir, progress.note, self.bag_dir)
            progress.note(
                f'resuming {rundir.path}: {self.n_restored} records, '
                f'{tuning.state.evals}/{self.run.budget} evaluations done'
            )
        # after every session the checkpoint lists and every session a record names (a
        # rebuilt checkpoint lists none)
        named = [r.session + 1 for r in tuning.records if isinstance(r.session, int)]
        tuning.session = max([len(tuning.state.sessions), *named])

    def start(self, link: ControllerLink) -> None:
        """The controller answers: a new run's run.yaml; the session's record; a resumed
        lock-step run replays its experiments (checked bit for bit)."""
        from .tuning import BenchFailure, LostEvaluation, replay

        run, rundir, tuning, progress, plan = (
            self.run,
            self.rundir,
            self.tuning,
            self.progress,
            self.plan,
        )
        assert rundir is not None and plan is not None
        try:
            parameters = link.list_parameters()
        except LostEvaluation as exc:  # a controller that does not answer: one line
            raise BenchFailure(f'the controller did not list its parameters: {exc}') from None
        first = (run.options or {}).get('first', 'none')
        if not self.resumed and plan.mode == 'external' and first != 'none':
            # a controller the tuner did not start: the first step must be its drive's model
            from .prior import model_drive_mismatch

            why = model_drive_mismatch(
                run.drive_config,
                parameters.get('drive_config_file'),
                'identify' if first == 'identify' else 'model',
            )
            if why is not None:
                raise UsageError(why)  # (the run directory is undone: nothing is left)
        numeric_now = numeric.status()  # (after the controller's answer: it loads scipy)
        enforced = parameters.get('timing_tolerance')
        if enforced is not None and enforced != run.timing_tolerance:
            # a controller the tuner did not start (--bench auto/none): its read-only
            # parameter is what counts; the run records what was enforced
            progress.warn(
                f'warning: the controller enforces timing_tolerance {enforced}, not the '
                f"run's {run.timing_tolerance} (it was started with it); the run records {enforced}"
            )
            tuning.timing_tolerance = enforced
            if not self.resumed:
                run.put(timing_tolerance=enforced)
        if self.host_said is not None:  # the host's check before the run, now the bench is up
            line, warning = self.host_said
            if warning:
                print(f'warning: {line}', file=sys.stderr, flush=True)
            else:
                print(line, flush=True)
        if not self.resumed:
            run.put(
                controller_parameters=parameters,
                fault_policy=plan.fault_policy,
                numeric=numeric_now,
            )
            rundir.write_run(run)
            progress.note(
                f'im_tuner: {run.algo} on the {plan.mode} bench, budget '
                f'{run.budget}, seed {run.seed}; run directory {rundir.path}'
            )
        else:
            differs = numeric.differs(run.numeric, numeric_now)
            if differs:
                progress.warn(
                    f'warning: {differs}: its results are not bit-identical to an '
                    'uninterrupted run on the baseline (docs/tuner.md)'
                )
        if numeric_now['state'] != 'held':
            progress.warn(f'warning: numeric baseline {numeric.describe(numeric_now)}')
        live = plan.spec.live
        if live is not None:
            progress.note(f'live: {live.describe()}')
            if not is_loopback(live.host):  # (said even with --quiet)
                progress.warn(
                    f"warning: --live-host {live.host}: the run's every topic is open to "
                    'whoever reaches this computer on the network (no authentication)'
                )
        session = self.session
        session.update(
            {
                'session': tuning.session,
                'numeric': numeric_now,
                'bag': self.bag_dir.name if self.bag_dir else None,
                'bench': plan.mode,
                'started': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
                'replayed': 0,
                'first_record': len(tuning.records),
            }
        )
        first_id = plan.first_experiment_id
        if plan.counts_experiment_ids:
            session['first_experiment_id'] = first_id
        if self.resumed and tuning.records:
            ids = f'; experiment ids go on from {first_id}' if first_id else ''
            if plan.simulated and plan.mode not in LOCKSTEP_BENCHES:
                progress.note(
                    'real-time simulated bench: the plant starts again at rest '
                    f'(no replay); the search goes on from the checkpoint{ids}'
                )
            elif plan.simulated:
                progress.note(
                    f'restoring the simulated plant: replaying '
                    f'{len(replay_plan(tuning.records))} experiments (checked bit '
                    'for bit)'
                )
                session['replayed'] = replay(
                    link, tuning.records, progress.steps('restoring the simulated plant')
                )
            else:
                progress.note(
                    ('external bench' if plan.mode == 'external' else 'a real drive')
                    + ': the plant is where it is; the search goes on from the checkpoint '
                    f'(no replay){ids}'
                )
        tuning.state.sessions.append(session)
        if (run.host_check or {}).get('auto'):
            tuning.off_timing = lambda: self.recheck_host(link)

    def recheck_host(self, link: ControllerLink) -> int | None:
        """``--timing-tolerance auto``, after an experiment off the paper's timing: the host
        checked again as before the run (``host.check_before_run``). A louder host raises
        the tolerance (on the controller, in run.yaml), never lowers it; each check goes
        into the session's ``host_rechecks``. Returns the new tolerance (None: unchanged)."""
        from im_drive_sim import host, rt

        tuning, rundir = self.tuning, self.rundir
        assert tuning is not None and rundir is not None
        before = int(tuning.timing_tolerance or 0)
        opts = rt.RtOptions.from_cli(self.cli, rt.DEFAULT_PRIORITY)
        chosen, record, line = host.check_before_run(host.AUTO, before, opts)
        self.session.setdefault('host_rechecks', []).append(
            {
                'after_records': len(tuning.records),
                'late_pct': record['late_pct'],
                'max_lateness_us': record['max_lateness_us'],
                'held_per_experiment': record['held_per_experiment'],
                'timing_tolerance_before': before,
                'timing_tolerance': chosen,
            }
        )
        tuning.checkpoint()
        if chosen <= before:
            self.progress.note(
                f'host checked again after an experiment off the timing: tolerance {before} '
                f'kept (late {record["late_pct"]:.3f} % of periods)'
            )
            return None
        link.set_timing_tolerance(chosen, time.monotonic() + link.call_timeout)
        self.run.put(timing_tolerance=chosen)
        rundir.write_run(self.run)
        assert line is not None
        self.progress.note(f'{line}; the host got louder: from the next experiment on')
        return chosen

    def finish(self, outcome: str, bench: Bench, link: ControllerLink, t_wall0: float) -> int:
        """The search ended with ``outcome``: the drive's counters, the bag closed (a bag
        not closed fails the run), summary.json and the summary printed; the exit code."""
        from .progress import format_summary

        tuning, progress, rundir, plan = self.tuning, self.progress, self.rundir, self.plan
        assert rundir is not None and plan is not None
        session = self.session
        session['drive'] = bench.drive_report()
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
        if self.cli.live is not None and self.bag_dir is not None:
            from .record.live import live_line, read_live_stats

            bags = [self.bag_dir] + [rundir.path / b['bag'] for b in session.get('more_bags', [])]
            live = read_live_stats(bags)
            if live is not None:  # (said with the summary: one line)
                session['live'] = live
                self.live_said = live_line(live)
        if problems and outcome == 'done':
            outcome = f'failed: {problems[0]}'
        code = {'done': EXIT_OK, 'interrupted': EXIT_INTERRUPTED}.get(outcome, EXIT_FAILED)
        progress.close()
        summary = tuning.summary(outcome=outcome, wall_s=time.monotonic() - t_wall0)
        ros2 = ros2_command()  # (as the user's shell finds it: commands that run as printed)
        summary.report_command = f'{ros2} run im_tuner report {shlex.quote(str(rundir.path))}'
        loop = ((summary.sessions or [{}])[-1].get('drive') or {}).get('loop')
        advice = failure_advice(outcome, tuning.records, plan.mode, loop)
        if advice:
            summary.what_to_do = advice
        tuning.checkpoint()
        rundir.write_summary(summary)
        print(format_summary(summary, self.run, rundir.path), flush=True)
        if self.live_said:
            print(f'  {self.live_said}', flush=True)
        if code != EXIT_OK:
            what = 'failed: once the cause is fixed,' if code == EXIT_FAILED else 'interrupted:'
            resume = resume_command(ros2, rundir.path, self.cli)
            print(f'  {what} continue with `{resume}`', flush=True)
        return code

    def discard_bag(self) -> None:
        """A replay that did not match refused the resume: its bag holds only the replay."""
        if self.bag_dir is not None and self.bag_dir.exists():
            shutil.rmtree(self.bag_dir, ignore_errors=True)

    def undo(self) -> None:
        """A new run refused once its directory exists (a ``-p`` the controller refuses, a
        drive node class whose constructor raises): leave nothing behind."""
        if self.resumed or self.rundir is None or self.made is None:
            return
        self.rundir.unlock()
        path, whole = self.made
        if whole:
            shutil.rmtree(path, ignore_errors=True)
        elif path.is_dir():
            for child in path.iterdir():
                shutil.rmtree(child) if child.is_dir() else child.unlink()
