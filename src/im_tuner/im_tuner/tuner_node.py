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

Exit codes: 0 done, 1 the bench failed (best gains applied, bag closed), 2 bad input,
130 interrupted (SIGINT/SIGTERM; resumable).
"""

from __future__ import annotations

import argparse
import math
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
import yaml
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions

from im_controller.config import GAIN_NAMES, GAIN_UNITS
from im_drive_sim.cli import Parser, UsageError, check_ros_args, finite_float

from . import optim
from .link import FAULT_POLICIES, ControllerLink, DriveMonitor, controller_topics, drive_report
from .optim.base import OptimizerError
from .rundir import RunDir, RunDirError
from .space import TunerParams, TunerParamsError, load_params, parse_params
from .tuning import (
    BenchFailure,
    ResumeError,
    StopRequested,
    TuningRun,
    replay,
    replay_plan,
    run_seeds,
)

BENCHES = ('auto', 'inproc', 'processes', 'realtime', 'none')
SIM_BENCHES = ('inproc', 'processes', 'realtime')
#: simulated benches that repeat a plant history bit for bit (a resumed run replays it)
LOCKSTEP_BENCHES = ('inproc', 'processes')
RECORDER_RESTARTS = 3  # replacements of a recorder child that died, per session
EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
#: settings a resumed run takes from run.yaml (giving them with --resume is an error)
RUN_SETTINGS = (
    'algo',
    'budget',
    'seed',
    'params',
    'remeasure',
    'no_reference',
    'model',
    'drive_config',
    'retries',
)


def _build_parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog='ros2 run im_tuner tuner',
        description='Tune the cascaded position/speed controller online by SPSA or '
        'a compact GA on measured experiment losses (docs/tuner.md).',
    )
    ap.add_argument('--algo', choices=optim.ALGOS, help='optimiser (default: necga)')
    ap.add_argument(
        '--budget', type=int, metavar='N', help='loss evaluations (default 200, as in the paper)'
    )
    ap.add_argument(
        '--seed',
        type=int,
        metavar='S',
        help="seed of the optimiser and of the simulated drive's noise "
        '(default: a fresh one, printed and stored in run.yaml)',
    )
    ap.add_argument(
        '--out',
        type=Path,
        metavar='DIR',
        help='run directory to create (default: bags/tuner_<algo>_<UTC time>)',
    )
    ap.add_argument(
        '--resume',
        type=Path,
        metavar='RUN_DIR',
        help='continue the killed or interrupted run in RUN_DIR',
    )
    ap.add_argument(
        '--bench',
        choices=BENCHES,
        help='where the controller comes from '
        '(default: auto = use one on the graph, else simulate in-process; '
        'realtime = the simulated bench as processes at 5 kHz wall clock)',
    )
    ap.add_argument('--quiet', action='store_true', help='no progress bar (for scripts)')
    ap.add_argument(
        '--params',
        type=Path,
        metavar='FILE',
        help='tuner parameter file: search box, start point, satisfactory loss '
        "(default: the packaged config/tuner.yaml, the paper's motor)",
    )
    ap.add_argument(
        '--remeasure',
        type=int,
        metavar='K',
        help='re-measure the K best distinct evaluations once at the end '
        '(default 3; 0 = off); the best re-measured is left applied',
    )
    ap.add_argument(
        '--no-reference',
        action='store_true',
        help='do not measure the start gains first (the reference)',
    )
    ap.add_argument(
        '--retries',
        type=int,
        metavar='R',
        help='re-runs of an evaluation whose result is lost (default 3)',
    )
    ap.add_argument(
        '--eval-timeout',
        type=finite_float(0.0, lo_open=True, unit='s'),
        default=60.0,
        metavar='S',
        help='wall time allowed per experiment [s] (default 60)',
    )
    ap.add_argument(
        '--fault-policy',
        choices=FAULT_POLICIES,
        help='after a safety fault: reset it and go on, or stop the run '
        '(default: reset on the simulated bench, stop on an external one)',
    )
    ap.add_argument(
        '--controller',
        default='/controller',
        metavar='NODE',
        help='controller node name (default /controller)',
    )
    ap.add_argument('--no-record', action='store_true', help='do not record a bag')
    ap.add_argument(
        '--compression',
        choices=('none', 'zstd', 'lz4'),
        default='lz4',
        help='MCAP chunk compression (default lz4)',
    )
    ap.add_argument(
        '--model',
        choices=('full', 'reduced'),
        help="simulated bench: drive model fidelity (default: the drive file's)",
    )
    ap.add_argument(
        '--drive-config',
        type=Path,
        metavar='FILE',
        help="simulated bench: drive parameter file (default: the paper's motor)",
    )
    ap.add_argument(
        '--discovery-timeout',
        type=finite_float(0.0, 3600.0, unit='s'),
        default=2.0,
        metavar='S',
        help='--bench auto/none: how long to look for a controller [s] (default 2)',
    )
    g = ap.add_argument_group('algorithm options (docs/optimisers.md)')
    seen: dict[str, Any] = {}
    for specs in optim.OPTIONS.values():
        for name, spec in specs.items():
            if name in seen:
                continue
            seen[name] = spec
            algos = ', '.join(a for a, s in optim.OPTIONS.items() if name in s)
            text = f'{spec.help} (default {spec.default!r}; for {algos})'
            # argparse %-formats help texts: a literal % (e.g. "~10% of") must be doubled
            kw: dict[str, Any] = {
                'dest': f'opt_{name}',
                'default': None,
                'help': text.replace('%', '%%'),
            }
            choices = getattr(spec, 'choices', None)
            if choices:
                kw['choices'] = list(choices)
            elif spec.type in (int, float):
                kw['type'] = spec.type
            g.add_argument(f'--{name.replace("_", "-")}', **kw)
    return ap


def _algo_options(cli: argparse.Namespace, algo: str) -> dict[str, Any]:
    """The algorithm options given on the command line; an option of another algorithm
    is an error (it would be silently ignored otherwise)."""
    given = {k[4:]: v for k, v in vars(cli).items() if k.startswith('opt_') and v is not None}
    mine = optim.OPTIONS[algo]
    wrong = [n for n in given if n not in mine]
    if wrong:
        flags = ', '.join('--' + n.replace('_', '-') for n in wrong)
        valid = ', '.join('--' + n.replace('_', '-') for n in mine) or 'none'
        raise UsageError(f'{flags} does not apply to --algo {algo} (its options: {valid})')
    return given


# -- the run configuration -------------------------------------------------------------------
def _new_run_config(cli: argparse.Namespace, argv: list[str]) -> tuple[dict[str, Any], TunerParams]:
    algo = cli.algo or 'necga'
    budget = 200 if cli.budget is None else cli.budget
    if budget < 1:
        raise UsageError(f'--budget must be >= 1 loss evaluations, got {budget}')
    if cli.seed is not None and cli.seed < 0:
        raise UsageError(f'--seed must be >= 0, got {cli.seed}')
    seed = cli.seed if cli.seed is not None else int(np.random.SeedSequence().entropy % 2**31)
    remeasure = 3 if cli.remeasure is None else cli.remeasure
    if remeasure < 0:
        raise UsageError(f'--remeasure must be >= 0, got {remeasure}')
    retries = 3 if cli.retries is None else cli.retries
    if retries < 0:
        raise UsageError(f'--retries must be >= 0, got {retries}')
    if not cli.eval_timeout > 0 or not math.isfinite(cli.eval_timeout):
        raise UsageError(f'--eval-timeout must be > 0 s, got {cli.eval_timeout}')
    try:
        params = load_params(cli.params)
    except TunerParamsError as exc:
        raise UsageError(str(exc)) from None
    if cli.drive_config is not None:
        from im_drive_sim.params import ConfigError, load_config

        try:
            load_config(cli.drive_config)
        except ConfigError as exc:
            raise UsageError(str(exc)) from None
    options = _algo_options(cli, algo)
    opt_ss, drive_seed = run_seeds(seed)
    try:  # validate the options now: nothing is created on bad input
        optim.make_optimizer(algo, params.space.dim, opt_ss, _start(algo, params), **options)
    except OptimizerError as exc:
        raise UsageError(str(exc)) from None
    run = {
        'algo': algo,
        'options': options,
        'budget': budget,
        'seed': seed,
        'drive_seed': drive_seed,
        'remeasure': remeasure,
        'reference': not cli.no_reference,
        'retries': retries,
        'satisfactory_loss': params.satisfactory_loss,
        'params_file': params.source,
        'search_box': params.space.as_dict(),
        'command': ' '.join(shlex.quote(a) for a in argv),
    }
    return run, params


def _start(algo: str, params: TunerParams) -> np.ndarray | None:
    """SPSA starts from the file's start point; the compact GAs from their distribution."""
    return params.space.start_u if algo in optim.TAKES_START else None


def _check_controller_name(name: str) -> None:
    """The controller's node name must make valid ROS names for its services and topics."""
    from rclpy.exceptions import InvalidServiceNameException, InvalidTopicNameException
    from rclpy.validate_full_topic_name import validate_full_topic_name

    try:
        for topic in controller_topics(name).values():
            validate_full_topic_name(topic)
    except (InvalidTopicNameException, InvalidServiceNameException) as exc:
        raise UsageError(
            f'--controller {name!r}: not a valid node name ({str(exc).splitlines()[0]})'
        ) from None


def _check_run(run: dict[str, Any], where: str) -> None:
    """run.yaml of a run to resume: the settings the tuner reads, with their types."""

    def bad(key: str, what: str) -> UsageError:
        return UsageError(f'{where}: {key} must be {what}, got {run.get(key)!r}')

    def is_int(v: Any) -> bool:
        return isinstance(v, int) and not isinstance(v, bool)

    if run.get('algo') not in optim.ALGOS:
        raise bad('algo', 'one of ' + ', '.join(optim.ALGOS))
    if not is_int(run.get('budget')) or run['budget'] < 1:
        raise bad('budget', 'an integer >= 1')
    for key in ('seed', 'drive_seed', 'remeasure', 'retries'):
        if not is_int(run.get(key)) or run[key] < 0:
            raise bad(key, 'an integer >= 0')
    if not isinstance(run.get('options'), dict):
        raise bad('options', 'a mapping of algorithm options')
    if not isinstance(run.get('reference'), bool):
        raise bad('reference', 'true or false')
    if not isinstance(run.get('search_box'), dict):
        raise bad('search_box', 'a mapping (the search box)')


def _params_of_run(run: dict[str, Any]) -> TunerParams:
    box = {n: {k: v[k] for k in ('lo', 'hi', 'start')} for n, v in run['search_box'].items()}
    return parse_params(
        {'search_box': box, 'satisfactory_loss': run['satisfactory_loss']},
        f'run.yaml ({run.get("params_file")})',
    )


def _make_tuning(rundir: RunDir, run: dict[str, Any], params: TunerParams, progress) -> TuningRun:
    opt_ss, _ = run_seeds(run['seed'])
    opt = optim.make_optimizer(
        run['algo'], params.space.dim, opt_ss, _start(run['algo'], params), **run['options']
    )
    return TuningRun(
        rundir,
        params.space,
        opt,
        budget=run['budget'],
        satisfactory_loss=params.satisfactory_loss,
        remeasure=run['remeasure'],
        retries=run['retries'],
        reference=run['reference'],
        progress=progress,
    )


# -- progress and summary ----------------------------------------------------------------------
class Progress:
    """Evaluation i/N, best and last loss, ETA: one updating line on a terminal, a line
    every 5 % otherwise; nothing with --quiet."""

    def __init__(self, algo: str, budget: int, quiet: bool, stream=sys.stderr) -> None:
        self.algo, self.budget, self.quiet, self.stream = algo, budget, quiet, stream
        self.tty = stream.isatty()
        self.t0 = time.monotonic()
        self.n0: int | None = None
        self.every = max(1, budget // 20)
        self._open = False

    def __call__(self, kind: str, rec: dict[str, Any], run: TuningRun) -> None:
        if self.quiet:
            return
        st = run.state
        if kind == 'reference':
            self._line(
                f'{self.algo}: start controller (reference) loss {self._fmt(rec)}', force=True
            )
            return
        if kind == 'remeasure':
            self._line(
                f'{self.algo}: re-measured evaluation {rec["eval"]}: {self._fmt(rec)}', force=True
            )
            return
        if self.n0 is None:
            self.n0, self.t0 = st.evals - 1, time.monotonic()
        i, n = st.evals, self.budget
        rate = (time.monotonic() - self.t0) / max(i - self.n0, 1)
        eta = int(rate * (n - i))
        width = 24
        fill = int(width * i / n)
        best = f'{st.best["loss"]:.4f}' if st.best else '-'
        text = (
            f'{self.algo} [{"#" * fill}{"." * (width - fill)}] eval {i}/{n}  best {best}  '
            f'last {self._fmt(rec)}  ETA {eta // 60}:{eta % 60:02d}'
        )
        self._line(text, force=i == n or i % self.every == 0)

    @staticmethod
    def _fmt(rec: dict[str, Any]) -> str:
        if rec['status'] == 'lost':
            return 'lost (re-run)'
        return f'{rec["loss"]:.4f}' + (f' (aborted: {rec["reason"]})' if rec['aborted'] else '')

    def _line(self, text: str, force: bool) -> None:
        if self.tty:
            self.stream.write('\r\x1b[2K' + text)
            self._open = True
            if force and not text.startswith(self.algo + ' ['):
                self.stream.write('\n')
                self._open = False
            self.stream.flush()
        elif force:
            print(text, file=self.stream, flush=True)

    def warn(self, text: str) -> None:
        """Printed even with --quiet: something went wrong that the user must know."""
        self.quiet, quiet = False, self.quiet
        try:
            self.note(text)
        finally:
            self.quiet = quiet

    def note(self, text: str) -> None:
        if self.quiet:
            return
        if self._open:
            self.stream.write('\n')
            self._open = False
        print(text, file=self.stream, flush=True)

    def close(self) -> None:
        if self._open:
            self.stream.write('\n')
            self.stream.flush()
            self._open = False


def _gains_text(g: dict[str, float]) -> str:
    return ', '.join(f'{n} {g[n]:.6g} {GAIN_UNITS[n]}' for n in GAIN_NAMES)


def format_summary(s: dict[str, Any], run: dict[str, Any], rundir: Path) -> str:
    L = [
        f'im_tuner: {run["algo"]}, {s["evaluations"]}/{s["budget"]} evaluations, seed '
        f'{run["seed"]}: {s["outcome"]}'
    ]
    ref = s['reference']
    if s['best'] is not None:
        b = s['best']
        rm = f'; re-measured {b["remeasured_loss"]:.4f}' if b['remeasured_loss'] is not None else ''
        L.append(f'  best loss:   {b["loss"]:.4f} (evaluation {b["eval"]}{rm})')
        L.append(f'  best gains:  {_gains_text(b["gains"])}')
    else:
        L.append('  best loss:   none (no evaluation completed without abort)')
    if ref is not None:
        L.append(
            f'  start (hand-tuned) loss: {ref["loss"]:.4f}'
            + (' (aborted)' if ref['aborted'] else '')
        )
    a = s['applied']
    if a is not None and a.get('on_controller') is False:
        L.append(
            '  NOT applied: the controller could not be reached at the end; its gains are '
            'whatever it had (best gains above)'
        )
    elif a is not None:
        if a['source'] == 'reference':
            L.append('  applied: the start gains (no evaluation beat them)')
        else:
            rm = (
                f', re-measured {a["remeasured_loss"]:.4f}'
                if a['remeasured_loss'] is not None
                else ''
            )
            L.append(
                f'  applied on the controller: evaluation {a["eval"]} (loss {a["loss"]:.4f}'
                f'{rm})'
                + (
                    ''
                    if s['best'] and a['eval'] == s['best']['eval']
                    else f': {_gains_text(a["gains"])}'
                )
            )
    sat = s['evaluations_to_satisfactory']
    L.append(
        f'  satisfactory (loss <= {s["satisfactory_loss"]:g}): '
        + (f'after {sat} evaluations' if sat else 'not reached')
    )
    L.append(
        f'  aborted experiments: {s["aborted"]} of {s["evaluations"]} (safety faults '
        f'{s["safety_faults"]}); lost results re-run: {s["lost"]}'
    )
    rtf = s['real_time_factor']
    # a real drive's experiments take drive time, not simulated time
    clock = (
        'simulated experiment time'
        if run.get('bench') in SIM_BENCHES
        else "experiment time (the drive's clock)"
    )
    L.append(
        f'  wall time {s["wall_s"]:.1f} s (tuning loop {s["loop_wall_s"]:.1f} s); '
        f'{clock} {s["sim_s"]:.1f} s; real-time factor ' + (f'{rtf:.2f}' if rtf else '-')
    )
    if s['optimizer_us_per_eval'] is not None:
        L.append(f'  optimiser ask+tell: {s["optimizer_us_per_eval"]:.1f} us per evaluation')
    sessions = s['sessions']
    for i, p in enumerate(sessions):
        if 'drive' in p:
            L.append(
                _drive_text(
                    p['drive'],
                    None
                    if len(sessions) == 1
                    else 'this session'
                    if i == len(sessions) - 1
                    else f'session {i + 1}' + (f', {p["bag"]}' if p.get('bag') else ''),
                )
            )
    bags = [
        b
        for p in s['sessions']
        for b in [p.get('bag'), *(m['bag'] for m in p.get('more_bags', []))]
        if b
    ]
    L.append(
        f'  run directory: {rundir}  (run.yaml, results.jsonl, summary.json'
        + ''.join(f', {b}/' for b in bags)
        + ')'
    )
    if len(s['sessions']) > 1:
        rep = sum(p.get('replayed', 0) for p in s['sessions'])
        L.append(
            f'  sessions: {len(s["sessions"])} (resumed; {rep} experiments replayed to '
            'restore the simulated plant)'
            if rep
            else f'  sessions: {len(s["sessions"])} (resumed)'
        )
    if s.get('report_command'):
        L.append(f'  report (summary, plots, CSV): {s["report_command"]}')
    return '\n'.join(L)


def _drive_text(d: dict[str, Any] | None, which: str | None) -> str:
    """One summary line of the drive's own counters (drive/status) in session ``which``
    (None: the run has one session)."""
    head = '  drive' + (f' ({which})' if which else '')
    if d is None:
        return f'{head}: no drive/status received (its counters are unknown)'

    def n(k: str) -> str:
        v = d.get(k)
        return '-' if v is None else (f'{v:.0f}' if isinstance(v, float) else str(v))

    if d.get('mode') == 'realtime':
        text = (
            f'{head} (real time): {n("steps")} periods, overruns {n("overruns")} (worst '
            f'period-start lateness {n("max_lateness_us")} us), late commands {n("late")}, '
            f'held {n("held")}, ignored {n("stale_ignored")}, watchdog trips '
            f'{n("watchdog_trips")}'
        )
    else:
        text = (
            f'{head} ({d.get("mode")}): {n("steps")} steps, commands ignored '
            f'{n("stale_ignored")}, states re-sent {n("republished")}'
        )
    if d.get('level', 0) >= 2:
        text += f'; last status ERROR: {d.get("message")}'
    return text


# -- benches -----------------------------------------------------------------------------------
class _Executor:
    """spin_until over a plain executor (external controller / child processes)."""

    def __init__(self, context: Context) -> None:
        self.executor = SingleThreadedExecutor(context=context)

    def spin_until(self, pred: Callable[[], bool], timeout: float | None = None) -> bool:
        deadline = None if timeout is None else time.monotonic() + timeout
        while not pred():
            if deadline is not None and time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.005)
        return True


def _controller_on_graph(node: Node, spin_until, controller: str, timeout: float) -> bool:
    start = controller_topics(controller)['start']

    def seen() -> bool:
        return any(n == start for n, _t in node.get_service_names_and_types())

    return spin_until(seen, timeout)


def _recorder_subscribed(node: Node, topics: list[str]) -> bool:
    for t in topics:
        if not any(i.node_name == 'recorder' for i in node.get_subscriptions_info_by_topic(t)):
            return False
    return True


def _die_with_parent() -> None:
    """preexec_fn of the bench children: SIGTERM when the tuner dies, however it dies
    (Linux prctl PR_SET_PDEATHSIG; it survives the exec chain of `ros2 run`), so a
    SIGKILLed tuner leaves no orphan drive, controller or recorder behind."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass  # not Linux: the children outlive a killed tuner (SIGINT still ends them)


def _repair_old_bags(rundir: RunDir, note) -> None:
    """Bags of killed sessions still say state 'recording': repair them (index, summary,
    metadata.yaml) so that the whole run opens in any reader."""
    from .mcap_repair import RepairError, repair_bag

    for bag in rundir.bag_dirs():
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


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv if args is None else args)
    try:
        cli = _build_parser().parse_args(check_ros_args(argv)[1:])
        _check_controller_name(cli.controller)
    except UsageError as exc:
        print(f'error: tuner: {exc}', file=sys.stderr)
        return EXIT_USAGE
    try:
        return _main(cli, argv)
    except UsageError as exc:
        print(f'error: tuner: {exc}', file=sys.stderr)
        return EXIT_USAGE


def _main(cli: argparse.Namespace, argv: list[str]) -> int:
    t_wall0 = time.monotonic()
    # ---- validate everything before creating anything --------------------------------------
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
        try:
            rundir = RunDir.open(cli.resume)
            rundir.lock()  # one tuner per run, from here to the end of the process
            run = rundir.read_run()
            _check_run(run, str(rundir.path / 'run.yaml'))
            params = _params_of_run(run)
        except (RunDirError, TunerParamsError) as exc:
            raise UsageError(f'--resume: {exc}') from None
        # everything of the run is checked before anything starts (a refusal changes
        # nothing; the torn tail of results.jsonl is cut only once the run goes on)
        progress = Progress(run['algo'], run['budget'], cli.quiet)
        try:
            tuning = _make_tuning(rundir, run, params, progress)
            n_restored = tuning.restore()
        except (OptimizerError, ValueError, TypeError) as exc:
            raise UsageError(f'--resume: {rundir.path}/run.yaml: {exc}') from None
        except ResumeError as exc:
            raise UsageError(f'--resume: {exc}') from None
        bench_mode = cli.bench or run.get('bench_requested', 'auto')
    else:
        run, params = _new_run_config(cli, argv)
        out = cli.out
        if out is None:
            from .recorder_node import default_out_dir

            out = default_out_dir(prefix=f'tuner_{run["algo"]}')
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise UsageError(
                f'--out {out}: already exists; choose a new directory'
                + (' (or continue that run with --resume)' if (out / 'run.yaml').exists() else '')
            )
        rundir = None
        bench_mode = cli.bench or 'auto'
        run['bench_requested'] = bench_mode
        progress = Progress(run['algo'], run['budget'], cli.quiet)

    # ---- ROS ---------------------------------------------------------------------------------
    ros_args = ['--ros-args', '--disable-stdout-logs']  # the tuner prints its own progress
    if '--ros-args' in argv:
        ros_args = [*argv[argv.index('--ros-args') :], '--disable-stdout-logs']
    ctx = Context()
    rclpy.init(
        args=[argv[0], *ros_args], context=ctx, signal_handler_options=SignalHandlerOptions.NO
    )
    stop = {'sig': None}

    def _on_signal(signum, _frame) -> None:
        stop['sig'] = signum

    old_handlers = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    should_stop = lambda: stop['sig'] is not None  # noqa: E731
    bench = None
    rec = None
    children: dict[str, subprocess.Popen] = {}  # the live bench processes, by role
    ended: list[subprocess.Popen] = []  # ... and those already gone
    node = None
    exe = None
    bag_dir: Path | None = None
    discard_bag = False
    code = EXIT_OK
    try:
        node = Node('tuner', context=ctx, start_parameter_services=False)
        exe = _Executor(ctx)
        exe.executor.add_node(node)
        spin_until = exe.spin_until
        if bench_mode in ('auto', 'none'):
            found = _controller_on_graph(node, spin_until, cli.controller, cli.discovery_timeout)
            if bench_mode == 'none' and not found:
                raise BenchFailure(
                    f'no controller reachable ({controller_topics(cli.controller)["start"]} '
                    f'not on the graph of ROS_DOMAIN_ID {os.environ.get("ROS_DOMAIN_ID", "0")} '
                    f'after {cli.discovery_timeout:g} s): start the bench first, e.g. '
                    '`ros2 run im_tuner sim_bench` or your drive + `ros2 run '
                    'im_controller controller`, or use --bench auto'
                )
            bench_mode = 'external' if found else 'inproc'
        elif bench_mode == 'inproc' and _controller_on_graph(node, spin_until, cli.controller, 0.5):
            raise BenchFailure(
                f'a controller ({cli.controller}) is already on the graph: '
                'tune it with --bench none, or use another ROS_DOMAIN_ID'
            )
        simulated = bench_mode in SIM_BENCHES
        if simulated and node.count_publishers('/drive/state') > 0:
            # a drive without a controller: a second (simulated) drive would fight it
            raise BenchFailure(
                'a drive is publishing /drive/state but no controller answers '
                f'({cli.controller}): start `ros2 run im_controller controller` '
                'for it and use --bench auto, or stop that drive'
            )
        if cli.resume is not None and simulated != (run.get('bench') in SIM_BENCHES):
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
        else:
            # accepted: from here on the run directory changes
            rundir.cut_torn_tail()
            if tuning.rebuilt:
                progress.warn(f'warning: {tuning.rebuilt}; rebuilt from results.jsonl')
            _repair_old_bags(rundir, progress.note)
            progress.note(
                f'resuming {rundir.path}: {n_restored} records, '
                f'{tuning.state.evals}/{run["budget"]} evaluations done'
            )
        bag_dir = None if cli.no_record else rundir.next_bag_dir()

        # ---- the bench ------------------------------------------------------------------------
        drive_over = [Parameter('seed', value=run['drive_seed'])]
        ctl_over = []
        if run.get('model'):
            drive_over.append(Parameter('model', value=run['model']))
        if run.get('drive_config'):
            drive_over.append(Parameter('config_file', value=run['drive_config']))
            ctl_over.append(Parameter('drive_config_file', value=run['drive_config']))
        if cli.resume is None:
            run['model'] = cli.model
            run['drive_config'] = str(cli.drive_config) if cli.drive_config else None
            if cli.model:
                drive_over.append(Parameter('model', value=cli.model))
            if cli.drive_config:
                drive_over.append(Parameter('config_file', value=str(cli.drive_config)))
                ctl_over.append(Parameter('drive_config_file', value=str(cli.drive_config)))
        if bench_mode == 'inproc':
            from .bench import InProcessBench, bench_metadata

            def _start_recorder(b) -> None:
                nonlocal rec
                if bag_dir is None:
                    return
                from .recorder_node import RECORD_POLL_STEPS, Recorder

                meta = bench_metadata(b) | {
                    'im_tuner.tuner': {k: v for k, v in run.items() if k != 'search_box'}
                }
                rec = Recorder(
                    Node('recorder', context=ctx, start_parameter_services=False),
                    bag_dir,
                    compression=cli.compression,
                    extra_metadata=meta,
                    command=argv,
                )
                rec.wait_matched(10.0)
                b.add_poller(rec.poll, RECORD_POLL_STEPS)

            exe.executor.remove_node(node)
            bench = InProcessBench(
                context=ctx,
                drive_overrides=drive_over,
                controller_overrides=ctl_over or None,
                before_start=_start_recorder,
            )
            bench.executor.add_node(node)
            spin_until = bench.spin_until
            # Discovery can be slow on a loaded machine: look again now that ours exist.
            if (
                node.count_publishers('/drive/state') > 1
                or sum(n == 'controller' for n in node.get_node_names()) > 1
            ):
                raise BenchFailure(
                    'another drive or controller appeared on the graph (ROS_DOMAIN_ID '
                    f'{os.environ.get("ROS_DOMAIN_ID", "0")}): not adding a simulated one '
                    'beside it; use --bench none, or another domain'
                )
        else:
            ros2 = str(Path(sys.prefix) / 'bin' / 'ros2')
            # the children log to /rosout (recorded) and their log files, not the console
            quiet_logs = ['--ros-args', '--disable-stdout-logs']

            def spawn(role: str, argv_: list[str]) -> None:
                children[role] = subprocess.Popen(
                    argv_,
                    stdout=subprocess.DEVNULL,
                    preexec_fn=_die_with_parent,  # noqa: PLW1509 (only prctl, async-signal-safe)
                )

            def start_recorder(out_dir: Path) -> None:
                spawn(
                    'recorder',
                    [
                        ros2,
                        'run',
                        'im_tuner',
                        'recorder',
                        '--out',
                        str(out_dir),
                        '--compression',
                        cli.compression,
                        *quiet_logs,
                    ],
                )

            if bag_dir is not None:
                start_recorder(bag_dir)
            if bench_mode in ('processes', 'realtime'):
                mode = ['--mode', 'realtime'] if bench_mode == 'realtime' else []
                d = [ros2, 'run', 'im_drive_sim', 'drive_sim', *mode, *quiet_logs]
                c = [ros2, 'run', 'im_controller', 'controller', *mode, *quiet_logs]
                d += [a for p in drive_over for a in ('-p', f'{p.name}:={p.value}')]
                c += [a for p in ctl_over for a in ('-p', f'{p.name}:={p.value}')]
                spawn('drive_sim', d)
                spawn('controller', c)
        monitor = (
            None
            if bench_mode == 'inproc'
            else DriveMonitor(node, controller_topics(cli.controller)['drive_status'])
        )
        session: dict[str, Any] = {}
        recorder_restarts = [0]

        def recorder_died(why: str) -> None:
            """Keep what the dead recorder wrote; go on recording into a new bag."""
            from .mcap_repair import RepairError, repair_bag

            dead = rundir.bag_dirs()[-1]
            progress.warn(
                f'warning: the recorder died ({why}); {dead.name} keeps what it '
                'wrote up to its last complete chunk'
            )
            node.get_logger().error(f'recorder child died ({why}); bag {dead} repaired')
            try:
                progress.warn('  ' + repair_bag(dead).summary().splitlines()[0])
            except RepairError as exc:
                progress.warn(f'  could not repair {dead}: {exc}')
            if recorder_restarts[0] >= RECORDER_RESTARTS:
                progress.warn(
                    f'  not recording any more (already replaced {RECORDER_RESTARTS} times)'
                )
                return
            recorder_restarts[0] += 1
            new = rundir.next_bag_dir()
            start_recorder(new)
            session.setdefault('more_bags', []).append(
                {'bag': new.name, 'first_record': len(tuning.records)}
            )
            tuning._checkpoint()
            deadline = time.monotonic() + 20.0
            while (
                not _recorder_subscribed(node, rec_topics)
                and time.monotonic() < deadline
                and children['recorder'].poll() is None
            ):
                time.sleep(0.05)  # graph queries need no spinning
            progress.warn(f'  recording again into {new.name} (messages in between are in no bag)')

        def supervise() -> None:
            """Between spins: a dead bench process is noticed at once (see module doc)."""
            for role, p in list(children.items()):
                rc = p.poll()
                if rc is None:
                    continue
                ended.append(children.pop(role))
                why = f'killed by signal {-rc}' if rc < 0 else f'exit code {rc}'
                if role == 'recorder':
                    recorder_died(why)
                else:
                    node.get_logger().error(f'bench process {role} died ({why})')
                    raise BenchFailure(
                        f'the bench process {role} died ({why}); the run '
                        'stops here (the simulated plant cannot be restored '
                        'under a running search)'
                    )

        names = controller_topics(cli.controller)
        rec_topics = (
            [names['loss'], '/drive/state']
            if bench_mode in ('processes', 'realtime')
            else [names['loss']]
        )
        link = ControllerLink(
            node,
            spin_until,
            controller=cli.controller,
            eval_timeout=cli.eval_timeout,
            fault_policy=fault_policy,
            should_stop=should_stop,
            supervise=supervise,
            call_timeout=min(10.0, cli.eval_timeout),
        )
        if not link.wait_ready(30.0):
            raise BenchFailure(
                f'the controller {cli.controller} did not become reachable '
                'within 30 s (services and loss topic)'
            )
        if (
            children
            and bag_dir is not None
            and not spin_until(lambda: _recorder_subscribed(node, rec_topics), 30.0)
        ):
            raise BenchFailure('the recorder child did not subscribe within 30 s')
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
                'bag': bag_dir.name if bag_dir else None,
                'bench': bench_mode,
                'started': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
                'replayed': 0,
                'first_record': len(tuning.records),
            }
        )
        if cli.resume is not None and tuning.records:
            if bench_mode == 'realtime':
                progress.note(
                    'real-time simulated bench: the plant starts again at rest '
                    '(no replay); the search goes on from the checkpoint'
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
                    'external bench: the plant is where it is; the search goes on '
                    'from the checkpoint (no replay)'
                )
        tuning.state.sessions.append(session)
        outcome = tuning.run(link, should_stop)
        if monitor is not None:
            # the drive's counters after the last experiment (it reports about once a second)
            n0 = monitor.received
            spin_until(lambda: monitor.received > n0, 1.5)
            session['drive'] = monitor.last
        else:
            session['drive'] = drive_report(
                {
                    'mode': bench.drive.mode,
                    'model': bench.drive.config.model,
                    **{k: str(v) for k, v in vars(bench.drive.counters).items()},
                }
            )
        if outcome == 'interrupted':
            code = EXIT_INTERRUPTED
        elif outcome != 'done':
            code = EXIT_FAILED
        progress.close()
        summary = tuning.summary(outcome=outcome, wall_s=time.monotonic() - t_wall0)
        summary['report_command'] = f'ros2 run im_tuner report {shlex.quote(str(rundir.path))}'
        tuning._checkpoint()
        rundir.write_summary(summary)
        print(format_summary(summary, run, rundir.path), flush=True)
        if code == EXIT_INTERRUPTED:
            print(
                f'  interrupted: continue with `ros2 run im_tuner tuner --resume {rundir.path}`',
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
    finally:
        if rec is not None:
            if bench is not None:
                bench.final_status()  # the drive's counters at exit, into the bag
            counts = rec.close(settle=0.05 if bench is not None else 0.0)
            lost = sum(c['lost'] for c in counts.values())
            if lost:
                print(
                    f'warning: the recorder counted {lost} lost messages (see '
                    f'{rec.out}/metadata.yaml)',
                    file=sys.stderr,
                )
            rec.node.destroy_node()
        if bench is not None:
            bench.destroy()
        from im_drive_sim.runtime import stop_child

        for p in [*reversed(list(children.values())), *ended]:
            stop_child(p)
        if discard_bag and bag_dir is not None and bag_dir.exists():
            shutil.rmtree(bag_dir, ignore_errors=True)
        if node is not None:
            node.destroy_node()
        if exe is not None:
            exe.executor.shutdown()
        rclpy.try_shutdown(context=ctx)
        for s, h in old_handlers.items():
            signal.signal(s, h)
    return code


if __name__ == '__main__':
    os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    sys.exit(main())
