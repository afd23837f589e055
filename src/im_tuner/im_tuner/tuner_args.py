"""The tuner's command line: its options (:func:`build_parser`) and what it reads from
``--ros-args`` (:func:`timing_tolerance`, :func:`ros_arguments`; a resumed run's
``-p name:=value`` parameters, :func:`run_parameters`).

The checks of the options, of a new run and of ``run.yaml`` on ``--resume``, are
:mod:`.tuner_cli`'s (``prepare_run``). As that module, this one imports no rclpy, numba,
pycma, optuna or scipy at load, so ``--help`` and a refusal are quick.
"""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from im_drive_sim import host, rt
from im_drive_sim.cli import Parser, UsageError, finite_float

from . import optim
from .bench.drive_spec import drive_help
from .bench.spec import DISCOVERY_TIMEOUT
from .benches import BENCHES  # (the bench modes: one copy, in benches)
from .names import DEFAULT_TIMING_TOLERANCE, FAULT_POLICIES
from .runlog import RunConfig
from .runlog.ripple import DEFAULT_RIPPLE_LIMIT, RIPPLE_TOLERANCE

#: the algorithms --no-start is for, in --algo's order
NO_START_TEXT = ', '.join(a for a in optim.ALGOS if a in optim.NO_START_ALGOS)
#: the algorithms whose runs keep the ripple limit by default, in --algo's order
RIPPLE_LIMITED_TEXT = ', '.join(a for a in optim.ALGOS if a in optim.RIPPLE_LIMITED)


DESCRIPTION = (
    'Tune the cascaded position/speed controller online by SPSA, a compact GA (the '
    'paper), CMA-ES, TPE or safe (a local search for real benches) on measured experiment '
    'losses (docs/tuner.md).'
)


def build_parser() -> argparse.ArgumentParser:
    ap = Parser(prog='ros2 run im_tuner tuner', description=DESCRIPTION)
    ap.add_argument(
        '--algo',
        choices=optim.ALGOS,
        help=f'optimiser (default: {optim.DEFAULT_ALGO}, the fewest experiments and aborts '
        "from the hand-tuned start; the paper's are spsa and necga)",
    )
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
        '(default: auto = use one on the graph, else simulate in-process, lock-step; '
        'realtime = drive and controller composed in this process, one 5 kHz wall-clock '
        'loop; realtime-processes = the same as separate processes)',
    )
    ap.add_argument(
        '--drive',
        metavar='DRIVE',
        help=f'--bench realtime: {drive_help()}',
    )
    ap.add_argument('--quiet', action='store_true', help='no progress bar (for scripts)')
    ap.add_argument(
        '--params',
        type=Path,
        metavar='FILE',
        help='tuner parameter file: search box, start point, satisfactory loss '
        "(default: the packaged config/tuner.yaml, the paper's motor, or a packaged "
        "--drive-config's own)",
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
        '--no-start',
        action='store_true',
        help=f'{NO_START_TEXT} only: do not start from the parameter '
        "file's start point (spsa, cmaes: a uniform random one; tpe: random trials first); "
        'the reference experiment still measures it. Refused with safe (a local search '
        'from the start: its first experiment would be an untested random controller) '
        'and with the compact GAs (they take no start)',
    )
    ap.add_argument(
        '--first',
        choices=('identify', 'model', 'none'),
        help="safe only: its first step after the start. 'identify': the start's two "
        'experiments identify the shaft (J, Kt, B, Tc: printed, in summary.json), then the '
        "best point of an offline tuning on the drive file's model with those values, "
        "robust to J +-10 %% and Rr x0.8-1.2; 'model': the same on the drive file's "
        'model as written, before the run, robust to J x0.7-1.4 (docs/optimisers.md); '
        "'none': a local step. Default: identify when the tuner knows the drive "
        '(--drive-config, or a '
        'simulated bench: --bench inproc, processes, realtime...), none otherwise (--bench '
        'auto or none without --drive-config: the controller found may drive another motor)',
    )
    ap.add_argument(
        '--ripple-limit',
        metavar='R|off',
        help='the largest standstill current ripple the applied gains may have: the rms '
        'of isq* in both standstill windows (after the move, after the load step) at most '
        "R times the hand-tuned start's, as the reference experiment measures it; a "
        f'louder evaluation (by more than {RIPPLE_TOLERANCE:g}x the limit: one experiment '
        'scatters) is told to the optimiser as no better than the best quiet one so far, '
        'and the re-measured and applied gains are the best evaluated within it '
        "(the start if none); safe's first step from the identified drive is chosen within "
        f"it on the models. A ratio >= 1 or 'off'. Default: {DEFAULT_RIPPLE_LIMIT:g} for "
        f"{RIPPLE_LIMITED_TEXT}, off for the others (the paper's final controller is "
        'the smallest loss); off with --no-reference (nothing to compare with) '
        '(docs/optimisers.md, "The standstill ripple")',
    )
    ap.add_argument(
        '--retries',
        type=int,
        metavar='R',
        help='re-runs of an evaluation whose result is lost, or marked timing (its '
        "experiment did not run on the paper's timing) (default 3)",
    )
    ap.add_argument(
        '--timing-tolerance',
        type=host.tolerance_arg,
        metavar='N|auto',
        help='held or late drive periods an experiment may have and still count (its '
        'held periods are recorded with its loss); past N it is marked timing and re-run. '
        f'Default {DEFAULT_TIMING_TOLERANCE}: the change of a loss by that many held periods '
        'stays within the bench\'s noise (docs/real-drive.md, "Timing tolerance"); 0: '
        "the paper's timing exactly; auto: twice what a 2 s check of this host finds 95 %% of "
        f'experiments meet, at least {DEFAULT_TIMING_TOLERANCE}, raised when an experiment '
        'comes back timing and the host, checked again, needs more (--bench realtime; '
        'elsewhere the default). Also -p timing_tolerance:=N after --ros-args',
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
        help='MCAP chunk compression (default lz4; refused with --no-record)',
    )
    ap.add_argument(
        '--model',
        choices=('full', 'reduced'),
        help="the simulator's model fidelity (--drive sim only; default: the drive file's)",
    )
    ap.add_argument(
        '--drive-config',
        type=Path,
        metavar='FILE|NAME',
        help='drive parameter file of a bench the tuner starts: Ts and isq_max for the '
        "controller, and the simulator's motor or your --drive class's config "
        "(default: the paper's 750 W motor; an external bench's controller has its own). "
        "A packaged drive's name (im3700w-j3, ...; docs/drive-family.md) also gives the "
        'controller its experiment and the optimiser its box and start',
    )
    ap.add_argument(
        '--discovery-timeout',
        type=finite_float(0.0, 3600.0, unit='s'),
        metavar='S',
        help='--bench auto/none: how long to look for a controller [s] (default: '
        f'{DISCOVERY_TIMEOUT["auto"]:g} with auto, then it simulates; '
        f'{DISCOVERY_TIMEOUT["none"]:g} with none, which waits only until it is found; '
        'discovery took up to 2.3 s on a loaded 2-core machine)',
    )
    rt.add_arguments(ap, 'the composed loop (--bench realtime)', rt.DEFAULT_PRIORITY)
    keys = '; '.join(f'{a}: {", ".join(o) or "none"}' for a, o in optim.OPTIONS.items())
    ap.add_argument(
        '--opt',
        action='append',
        default=[],
        metavar='KEY=VALUE',
        help='an option of the algorithm (repeat it for more), or a YAML file of them; '
        "'--opt help' lists the algorithm's with their defaults and ranges. "
        f'The options: {keys} (docs/optimisers.md). An option of another algorithm '
        'is an error, not ignored',
    )
    return ap


def timing_tolerance(cli: argparse.Namespace, argv: list[str]) -> int | str | None:
    """The tolerance asked for: ``--timing-tolerance N`` or ``-p timing_tolerance:=N``
    after ``--ros-args`` (the controller's parameter, which the tuner sets); None:
    neither; ``auto``: ``host.AUTO``. Both, differing, or a value that is not an integer
    >= 0: UsageError."""
    given = cli.timing_tolerance
    ros = argv[argv.index('--ros-args') :] if '--ros-args' in argv else []
    from_ros = None
    for i, a in enumerate(ros[:-1]):
        if a in ('-p', '--param') and ros[i + 1].startswith('timing_tolerance:='):
            text = ros[i + 1].split(':=', 1)[1]
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
    value = given if given is not None else from_ros
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
    ros = words[words.index('--ros-args') + 1 :] if '--ros-args' in words else []
    out = []
    for i, w in enumerate(ros[:-1]):
        if w in ('-p', '--param') and not ros[i + 1].startswith('timing_tolerance:='):
            out += ['-p', ros[i + 1]]
    return out
