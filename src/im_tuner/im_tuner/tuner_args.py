"""The tuner's typed command line (:class:`TunerOptions`, declared by
:func:`~.typed_cli.option`): the parser, the settings ``--resume`` takes from run.yaml
(:data:`RUN_SETTINGS`) and docs/tuner.md's options table (:func:`options_table`; ``make
docs`` writes it); drive_host, sim_bench and the study declare the options they share with
it by ``option(..., like=...)``. Also what is read from ``--ros-args``
(:func:`timing_tolerance`, :func:`ros_arguments`; a resumed run's ``-p name:=value``
parameters, :func:`run_parameters`). The checks of a new run and of ``run.yaml`` on
``--resume`` are :mod:`.tuner_cli`'s. Imports no rclpy, numba, pycma, optuna or scipy at
load, so ``--help`` and a refusal are quick.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from im_drive_sim import host, rt
from im_drive_sim.cli import UsageError, finite_float, int_in

from . import optim
from .benches import BENCHES, DISCOVERY_TIMEOUT, drive_help
from .names import DEFAULT_TIMING_TOLERANCE, FAULT_POLICIES
from .record import live as _live
from .runlog import RunConfig
from .runlog.ripple import DEFAULT_RIPPLE_LIMIT, RIPPLE_TOLERANCE
from .typed_cli import RT, SHARED, Option, OptionsParser, declared, default_text, option

_RIPPLE_LIMITED = ', '.join(f'`{a}`' for a in optim.ALGOS if a in optim.RIPPLE_LIMITED)
_OPT_KEYS = '; '.join(
    f'`{" ".join(optim.option_specs(a))}` ({a})' for a in optim.ALGOS if optim.option_specs(a)
)


@dataclass
class TunerOptions:
    """The tuner's command line, typed: one field per option, its declaration (an
    :class:`Option`) in the field's metadata. A run setting not given is None (False for
    a switch): ``--resume`` refuses it given; a new run takes :func:`default`."""

    PROG = 'ros2 run im_tuner tuner'
    DESCRIPTION = (
        'Tune the cascaded position/speed controller online by SPSA, a compact GA (the '
        'paper), CMA-ES, TPE or safe (a local search for real benches) on measured '
        'experiment losses (docs/tuner.md).'
    )
    RT_WHAT = 'the composed loop (--bench realtime)'

    algo: str | None = option(
        '`spsa`, `necga`, `cga`, `pecga`, `rcga` (the paper and its variants), `cmaes` '
        '(pycma), `tpe` (optuna), `safe` (the fewest experiments and aborts from the '
        "hand-tuned start; the paper's are `spsa` and `necga`)",
        {'choices': optim.ALGOS},
        optim.DEFAULT_ALGO,
        f'`{optim.DEFAULT_ALGO}`',
        run=True,
    )
    budget: int | None = option(
        "loss evaluations (the paper's stopping criterion: 200); never iterations",
        {'type': int_in(1), 'metavar': 'N'},
        200,
        run=True,
    )
    seed: int | None = option(
        "seeds the optimiser and the simulated drive's noise (independent streams, "
        '`numpy.random.SeedSequence(S).spawn(2)`); printed and stored in `run.yaml`',
        {'type': int_in(0), 'metavar': 'S'},
        shown='fresh',
        run=True,
    )
    out: Path | None = option(
        'run directory to create (must be new or empty)',
        arg={'type': Path, 'metavar': 'DIR'},
        shown='`bags/tuner_<algo>_<UTC time>`',
    )
    resume: Path | None = option(
        'continue a killed or interrupted run (settings come from its `run.yaml`; the `-p '
        "name:=value` parameters after `--ros-args` of the run's first command apply "
        'again, before any given now)',
        arg={'type': Path, 'metavar': 'RUN_DIR'},
    )
    bench: str | None = option(
        'where the controller comes from: `auto` (one on the graph, else simulated '
        'in-process, lock-step), `inproc`, `processes`, `realtime` (drive and controller '
        'composed in this process, one 5 kHz wall-clock loop), `realtime-processes` (the '
        'same as separate processes), `none` ([Benches](#benches))',
        {'choices': BENCHES},
        shown='`auto`',
    )
    drive: str | None = option(
        f'`--bench realtime` only: {drive_help()}',
        {'metavar': 'DRIVE'},
        shown='`sim`',
        run=True,
    )
    thread_priority: int | None = option(
        '`--bench realtime` only (given with any other bench, `auto` included: refused, '
        "exit 2): the composed loop's thread runs SCHED_FIFO at priority N, 1-99, as "
        f"ros2_control_node's `thread_priority` (default {rt.DEFAULT_PRIORITY} there too); "
        '0: the normal policy. Not permitted (no CAP_SYS_NICE, rtprio limit below N): one '
        '`warning:` line on stderr says how to grant it (limits.conf, docker '
        '`--cap-add=sys_nice --ulimit rtprio=99`) and the run goes on under SCHED_OTHER '
        '([real-drive.md, "Real-time set-up"](real-drive.md#real-time-set-up))',
        RT,
        rt.DEFAULT_PRIORITY,
        parsed=None,
    )
    cpu_affinity: int = option(
        "`--bench realtime` only: pin the loop's thread to that CPU, one the process may "
        'use (else refused, exit 2); best a CPU isolated for it',
        RT,
        shown='any CPU',
        parsed=-1,
    )
    lock_memory: bool = option(
        '`--bench realtime` only: `mlockall(MCL_CURRENT \\| MCL_FUTURE)`, no page fault '
        'inside a period; not permitted (no CAP_IPC_LOCK, memlock limit too small): one '
        '`warning:` line, the run goes on. What the loop ran with (policy, priority, '
        'affinity, memory lock, kernel, PREEMPT_RT, CPU, what was asked and refused) is '
        "in summary.json, `sessions[i].drive.loop.realtime`, and in the bag's metadata "
        'record `im_tuner.realtime`',
        RT,
        parsed=False,
    )
    params: Path | None = option(
        'tuner parameter file: search box, start point, satisfactory loss',
        {'type': Path, 'metavar': 'FILE'},
        shown="packaged `config/tuner.yaml`, or a packaged `--drive-config`'s own",
        run=True,
    )
    remeasure: int | None = option(
        're-measure the K best distinct evaluations once at the end (0 = off); the best '
        're-measured is left applied',
        {'type': int_in(0), 'metavar': 'K'},
        3,
        run=True,
    )
    no_reference: bool = option(
        'do not measure the start gains first (the reference); without it nothing '
        "measures the start's loss and ripple: safe's first step defaults to `none` and "
        'the ripple limit to `off`',
        {'action': 'store_true'},
        run=True,
    )
    ripple_limit: str | None = option(
        'the largest standstill current ripple the applied gains may have: their rms of '
        'isq* in both standstill windows (after the move, 0.300-0.700 s; after the load '
        'step, 0.900-1.125 s; results.jsonl `ripple`) at most R times the hand-tuned '
        "start's (the mean of the start's experiments, the reference first). The search "
        f'is told what a louder point costs (an evaluation well above the limit, r > '
        f'{RIPPLE_TOLERANCE:g} with r its rms over the limit, is told its loss times 1 + '
        '(r - 1), and never less than the best loss measured within the limit so far; up '
        f"to {RIPPLE_TOLERANCE:g} it is told its loss, because one experiment's ripple "
        "scatters about its gains' mean), and the re-measurements and the applied gains "
        "are the best evaluations within it, the start if none is; safe's first step from "
        'the identified drive is chosen within it as predicted on the identified model '
        "with the drive file's noise (optimisers.md). On for the default "
        "algorithm, the one meant for a user's drive (the encoder-count limit cycle the "
        "loss does not see is audible and heats the motor); off for the paper's "
        "algorithms and the others, whose final controller is the paper's (the smallest "
        'loss), unless given. `off` with `--no-reference` (nothing to compare with; giving '
        'R with it is refused). A ratio >= 1 (else one line, exit 2); stored in run.yaml '
        '(`ripple_limit`, null: off), kept by `--resume`; summary.json `ripple` says what '
        'it did ([optimisers.md](optimisers.md), "The standstill ripple")',
        {'metavar': 'R|off'},
        shown=f'{DEFAULT_RIPPLE_LIMIT:g} for {_RIPPLE_LIMITED}, `off` for the others',
        run=True,
    )
    retries: int | None = option(
        're-runs of an evaluation whose result is lost, or marked timing (its experiment '
        "did not run on the paper's timing)",
        {'type': int_in(0), 'metavar': 'R'},
        default=3,
        run=True,
    )
    timing_tolerance: int | str | None = option(
        'held + late drive periods an experiment may have and still count (its held '
        'periods are recorded with its loss); past N it is marked timing and re-run '
        "([Experiments off the paper's timing](#experiments-off-the-papers-timing-timing)); "
        f'{DEFAULT_TIMING_TOLERANCE}: the change of a loss by that many held periods stays '
        'within the bench\'s noise (docs/real-drive.md, "Timing tolerance"); 0: the '
        "paper's timing exactly. `auto`: on `--bench realtime`, twice what a 2 s check of "
        'the host finds 95 % of experiments meet (a whole run holds up to 2x the wait '
        f'alone), at least {DEFAULT_TIMING_TOLERANCE}, raised when an experiment comes back '
        '`timing` and the host, checked again, needs more (docs/real-drive.md, "Check the '
        f'host first"); elsewhere {DEFAULT_TIMING_TOLERANCE}. Also `-p timing_tolerance:=N` '
        'after `--ros-args`; stored in run.yaml, kept by `--resume`',
        {'type': host.tolerance_arg, 'metavar': 'N|auto'},
        shown=f'{DEFAULT_TIMING_TOLERANCE}',
        run=True,
    )
    eval_timeout: float = option(
        'wall time allowed for one experiment [s] (set gains to loss received); a '
        'service call waits at most min(10 s, S)',
        {'type': finite_float(0.0, lo_open=True, unit='s'), 'metavar': 'S'},
        60.0,
    )
    fault_policy: str | None = option(
        'after a safety fault: reset it and go on, or end the run (its message names '
        '`ros2 run im_controller reset_fault`, which clears the fault once the drive is '
        'checked; then `--resume`)',
        {'choices': FAULT_POLICIES},
        shown='`reset` simulated, `stop` external',
    )
    controller: str = option(
        'the controller node (its namespace also places `controller/loss`)',
        {'metavar': 'NODE'},
        '/controller',
        '`/controller`',
    )
    no_record: bool = option(
        'do not record a bag ([recorder.md](recorder.md))',
        {'action': 'store_true'},
    )
    compression: str | None = option(
        'MCAP chunk compression; refused with `--no-record` (it would be ignored)',
        {'choices': ('none', 'zstd', 'lz4')},
        shown='`lz4`',
    )
    live: int | None = option(**_live.OPTIONS['--live'])
    live_host: str | None = option(**_live.OPTIONS['--live-host'])
    live_rate: float | None = option(**_live.OPTIONS['--live-rate'])
    drive_config: Path | None = option(
        'the drive parameter file of a bench the tuner starts: the controller takes `Ts` '
        'and `machine.isq_max` from it, the simulator its motor, a `--drive` class its '
        "`config` (real-drive.md's `my_drive.yaml`). An external bench's controller was "
        "started with its own (`--drive-config`). A packaged drive's name (`im3700w-j3`, ...) "
        "also gives the controller that drive's experiment and fallback gains and the "
        'optimiser its box and start (unless `--params`): '
        '[drive-family.md](drive-family.md)',
        {'type': Path, 'metavar': 'FILE|NAME'},
        shown="the paper's 750 W motor",
        run=True,
    )
    model: str | None = option(
        "the simulator's model fidelity, `full` or `reduced` (`--drive sim` only)",
        {'choices': ('full', 'reduced')},
        shown="the drive file's",
        run=True,
    )
    discovery_timeout: float | None = option(
        'how long `--bench auto`/`none` look for a controller [s]: `auto` then simulates, '
        'so it stays short; `none` waits only until the controller is found. Discovering '
        'a running controller from a new process took 0-2.3 s at load 3 on a 2-core '
        'machine: on a loaded machine give `auto` more, or use `none`',
        {'type': finite_float(0.0, 3600.0, unit='s'), 'metavar': 'S'},
        shown=f'{DISCOVERY_TIMEOUT["auto"]:g} (`auto`), {DISCOVERY_TIMEOUT["none"]:g} (`none`)',
    )
    quiet: bool = option(
        'no progress output (the summary is still printed on stdout)',
        {'action': 'store_true'},
    )
    opt: list[str] = option(
        'an option of the algorithm (repeat it for more), or a YAML file of them: '
        f"{_OPT_KEYS}. `start` (where the search starts) and `first` (safe's first step) are "
        "the run's policies for the algorithm ([Start and first step](#start-and-first-step)). "
        '`--algo ALGO --opt help` lists them with defaults and ranges '
        '([optimisers.md](optimisers.md)). An option of another algorithm is an error, '
        'not ignored; run.yaml keeps them under `options`',
        {'action': 'append', 'metavar': 'KEY=VALUE'},
        shown="the paper's",
    )

    @property
    def bench_asked(self) -> str:
        """The bench this command line asks for: ``auto`` when ``--bench`` is not given
        (``bench`` None: a resumed run takes run.yaml's)."""
        return self.bench or 'auto'


#: the declarations, in the docs' order
OPTIONS: tuple[Option, ...] = declared(TunerOptions)
#: the settings a resumed run takes from run.yaml (giving them with --resume is an error)
RUN_SETTINGS: tuple[str, ...] = tuple(o.dest for o in OPTIONS if o.run)
SHARED.update({o.dest: (o, TunerOptions.__dataclass_fields__[o.dest].default) for o in OPTIONS})


def default(dest: str) -> Any:
    """The declared value of option ``dest`` when it is not given."""
    return next(o for o in OPTIONS if o.dest == dest).default


def build_parser() -> OptionsParser:
    """The tuner's parser, from :data:`OPTIONS`: it gives a :class:`TunerOptions`."""
    return OptionsParser(TunerOptions)


def parse_options(args: list[str]) -> TunerOptions:
    """The tuner's options from its command line (without ``--ros-args``' part). An
    ``--opt`` key given apart from its value (``--opt first none``: the tuner takes no
    positional argument) is refused naming the ``KEY=VALUE`` form."""
    for flag, key, value in zip(args, args[1:], args[2:], strict=False):
        if flag == '--opt' and '=' not in key and not value.startswith('-'):
            raise UsageError(f'--opt {key} {value}: give it as --opt {key}={value}')
    return build_parser().parse_args(args)


def options_table() -> str:
    """docs/tuner.md's options table (Markdown), from :data:`OPTIONS`."""
    actions = {s: a for a in build_parser()._actions for s in a.option_strings}
    rows = ['| option | default | meaning |', '|---|---|---|']
    for o in OPTIONS:
        meta = actions[o.flag].metavar
        if isinstance(meta, str) and actions[o.flag].nargs == '?':
            meta = f'[{meta}]'
        name = (f'{o.flag} {meta}' if isinstance(meta, str) else o.flag).replace('|', '\\|')
        rows.append(f'| `{name}` | {default_text(o)} | {o.help} |')
    return '\n'.join(rows) + '\n'


#: docs/tuner.md's lines around the generated table
TABLE_BEGIN = '<!-- options: generated from im_tuner/tuner_args.py (make docs) -->'
TABLE_END = '<!-- end of options -->'


def write_table(doc: Path) -> bool:
    """Put :func:`options_table` between the markers of ``doc``; whether it changed."""
    text = doc.read_text()
    head, rest = text.split(TABLE_BEGIN + '\n', 1)
    _old, tail = rest.split(TABLE_END, 1)
    new = head + TABLE_BEGIN + '\n' + options_table() + TABLE_END + tail
    if new != text:
        doc.write_text(new)
    return new != text


def timing_tolerance(cli: TunerOptions, argv: list[str]) -> int | str | None:
    """The tolerance asked for: ``--timing-tolerance N`` or ``-p timing_tolerance:=N``
    after ``--ros-args`` (the controller's parameter, which the tuner sets); None:
    neither; ``auto``: ``host.AUTO``. Both, differing, or a value that is not an integer
    >= 0: UsageError."""
    given = cli.timing_tolerance
    from_ros = None
    for item in ros_parameters(argv):
        if item.startswith('timing_tolerance:='):
            text = item.split(':=', 1)[1]
            try:
                from_ros = int(text)
            except ValueError:
                raise UsageError(
                    f'-p timing_tolerance:={text}: an integer >= 0 [periods]'
                ) from None
    if given == host.AUTO:
        if from_ros is not None:
            raise UsageError(
                f'--timing-tolerance auto and -p timing_tolerance:={from_ros}: give one'
            )
        return host.AUTO
    if given is not None and from_ros is not None and given != from_ros:
        raise UsageError(
            f'--timing-tolerance {given} and -p timing_tolerance:={from_ros}: give one'
        )
    value = given if isinstance(given, int) else from_ros
    if value is not None and (value < 0 or value > 1_000_000):
        raise UsageError(f'--timing-tolerance must be in [0, 1000000] periods, got {value}')
    return value


def ros_arguments(argv: list[str], run: RunConfig | None = None) -> list[str]:
    """The tuner's rclpy arguments: its ``--ros-args`` (they reach an in-process bench's
    nodes too), the console logs off (the tuner prints its own progress). ``run``: a
    resumed run's run.yaml, whose command's ``-p name:=value`` parameters come first
    (its bench runs with them again: a safety limit or an experiment parameter the run
    began with is not dropped; the timing tolerance is run.yaml's own)."""
    ros_args = argv[argv.index('--ros-args') :] if '--ros-args' in argv else ['--ros-args']
    kept = run_parameters(run) if run is not None else []
    return [argv[0], '--ros-args', *kept, *ros_args[1:], '--disable-stdout-logs']


def run_parameters(run: RunConfig) -> list[str]:
    """``-p name:=value`` items of the command a run began with (run.yaml ``command``),
    but ``timing_tolerance`` (run.yaml's own key)."""
    try:
        words = shlex.split(run.command or '')
    except ValueError:
        return []
    kept = [p for p in ros_parameters(words) if not p.startswith('timing_tolerance:=')]
    return [w for p in kept for w in ('-p', p)]


def ros_parameters(argv: list[str]) -> list[str]:
    """The ``name:=value`` operands of ``-p``/``--param`` after ``--ros-args`` in ``argv``."""
    ros = argv[argv.index('--ros-args') :] if '--ros-args' in argv else []
    return [ros[i + 1] for i, w in enumerate(ros[:-1]) if w in ('-p', '--param')]


if __name__ == '__main__':  # make docs: docs/tuner.md's table from OPTIONS
    import sys

    for name in sys.argv[1:]:
        if write_table(Path(name)):
            print(f'wrote {name}')
