"""Which bench, built how: the tuner's and ``sim_bench``'s bench, decided without ROS.

A :class:`BenchSpec` says what was asked: the ``--bench`` mode (``auto``, ``none``,
``inproc``, ``processes``, ``realtime``, ``realtime-processes``; :mod:`im_tuner.benches`),
the drive (``sim``, ``example``, a hardware or drive class, :mod:`.drive_spec`), the
recording, the drive's and the controller's parameters, and for a resumed run the bench
the run used before. Everything but one question is decided here: ``auto`` and ``none``
need the graph (is a controller on it?), a probe made when the bench opens
(:func:`.open.open_bench`), which then calls :meth:`BenchSpec.resolve` with the mode it
found. :meth:`BenchSpec.resolve` gives the :class:`BenchPlan` -- the mode, whether the
drive is simulated, whether a resume replays the plant, the fault policy, the children's
command lines -- or refuses a resume that would change what a run may not change (a
simulated plant for a real one, lock-step for real time).

Pure: no rclpy (unit-tested without ROS).
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from im_drive_sim import rt
from im_drive_sim.cli import UsageError

from .. import family
from ..benches import DISCOVERY_TIMEOUT, LOCKSTEP_BENCHES, SIM_BENCHES, is_simulated
from ..record.live import live_settings

if TYPE_CHECKING:
    from ..runlog import Record, RunConfig
    from ..tuner_args import TunerOptions


#: the children's console output off: they log to /rosout (recorded) and their log files
QUIET_LOGS = ('--ros-args', '--disable-stdout-logs')

Params = tuple[tuple[str, Any], ...]


def next_experiment_id(records: Sequence[Record]) -> int:
    """The first experiment id of a session that does not replay: past every id in the
    run's records (0 for none)."""
    ids = [r.experiment_id for r in records if r.experiment_id is not None]
    return max(ids) + 1 if ids else 0


def recording_options(no_record: bool, **bag_options: Any) -> str:
    """The bag's compression (default lz4) of a command line with ``--no-record`` and
    bag options (``flag_name=value``, None: not given): a bag option with no bag would
    be silently ignored, so it is refused (UsageError)."""
    for name, value in bag_options.items():
        if no_record and value is not None:
            raise UsageError(
                f'--{name.replace("_", "-")} {value} is for the bag, and --no-record records '
                'none: give one or the other'
            )
    return bag_options.get('compression') or 'lz4'


def bench_parameters(
    config: str | None, model: str | None, seed: int | None, given: Collection[str] = ()
) -> tuple[Params, Params]:
    """The drive's and the controller's parameters of a simulator's options (None: not
    given): the controller also takes the drive file and a packaged drive's experiment and
    start gains (``family.tuner_setup``), but those named in ``given`` (the user's ``-p``:
    the command line wins)."""
    given_drive = (('seed', seed), ('model', model), ('config_file', config or None))
    ctl: list[tuple[str, Any]] = []
    if config:
        ctl.append(('drive_config_file', config))
        setup = family.tuner_setup(config)
        if setup is not None:
            ctl += [(n, v) for n, v in family.controller_parameters(setup) if n not in given]
    return tuple((n, v) for n, v in given_drive if v is not None), tuple(ctl)


def parameter_args(params: Params) -> list[str]:
    """``-p name:=value`` arguments of a child node."""
    return [a for name, value in params for a in ('-p', f'{name}:={value}')]


@dataclass(frozen=True)
class BenchPlan:
    """A bench decided (:meth:`BenchSpec.resolve`): what is opened, and how a run uses it."""

    #: 'inproc', 'realtime', 'processes', 'realtime-processes' or 'external'
    mode: str
    spec: BenchSpec
    #: the drive is simulated (its experiments run on the simulation's clock)
    simulated: bool
    #: a resumed session replays the run's experiments bit for bit (lock-step simulation)
    replays: bool
    #: this session's controller starts its experiment ids here (0: its own default)
    first_experiment_id: int
    #: after a safety fault: 'reset' (the simulated bench's default) or 'stop'
    fault_policy: str

    @property
    def drive_parameters(self) -> Params:
        return self.spec.drive_parameters

    @property
    def controller_parameters(self) -> Params:
        """The controller's parameters; a session that does not replay also starts its
        experiment ids past the run's (``first_experiment_id``)."""
        first = self.first_experiment_id
        given = self.spec.controller_parameters
        return (*given, ('first_experiment_id', first)) if first else given

    @property
    def counts_experiment_ids(self) -> bool:
        """The session record names its first experiment id (a simulated bench that does
        not replay: a real or composed drive's ids go on across sessions)."""
        return self.mode in SIM_BENCHES and not self.replays

    def child_args(self, role: str) -> list[str]:
        """The command-line tail of the bench's child ``role`` ('drive_sim' or
        'controller'): the spec's own (``sim_bench``) or the parameters as ``-p``."""
        given = self.spec.child_args
        if given is not None:
            return list(given[0] if role == 'drive_sim' else given[1])
        realtime = ['--mode', 'realtime'] if self.mode == 'realtime-processes' else []
        params = self.drive_parameters if role == 'drive_sim' else self.controller_parameters
        quiet = list(QUIET_LOGS) if self.spec.quiet else []
        return [*realtime, *quiet, *parameter_args(params)]


@dataclass(frozen=True)
class BenchSpec:
    """What was asked of the bench (module docstring)."""

    #: the --bench value: auto, none, inproc, processes, realtime, realtime-processes
    requested: str = 'auto'
    #: 'sim', 'example' or 'package.module:Class' (drive_spec)
    drive: str = 'sim'
    #: the checked --drive (a drive_spec.DriveChoice, its hardware built), or None
    drive_choice: Any = None
    record: bool = True
    compression: str = 'lz4'
    controller: str = '/controller'
    #: [s] how long auto/none look for a controller (None: not looked for)
    discovery_timeout: float | None = None
    #: (name, value) of the drive's parameters, in order
    drive_parameters: Params = ()
    #: (name, value) of the controller's parameters, in order
    controller_parameters: Params = ()
    #: the run's next experiment id (its records'; 0 for a new run)
    next_experiment_id: int = 0
    #: --fault-policy (None: by the drive, BenchPlan.fault_policy)
    fault_policy: str | None = None
    #: the composed loop's scheduling (im_drive_sim.rt.RtOptions; --bench realtime)
    rt_options: Any = None
    #: the host's check before the run (im_drive_sim.host.check_before_run's record):
    #: recorded with the loop's real-time settings (None: not checked)
    host_check: dict[str, Any] | None = None
    #: a resumed run, and the bench it ran on before (run.yaml's bench)
    resumed: bool = False
    previous_bench: str | None = None
    #: the children's command-line tails as given (drive, controller), or None: from the
    #: parameters (BenchPlan.child_args)
    child_args: tuple[tuple[str, ...], tuple[str, ...]] | None = None
    #: the children's console output off (their logs go to /rosout and their log files)
    quiet: bool = True
    #: the live view of the recording (record.live.LiveSettings; None: none)
    live: Any = None

    def resolve(self, mode: str) -> BenchPlan:
        """The plan of the bench ``mode`` (``auto``/``none`` already resolved to
        ``external`` or ``inproc`` by the graph probe). A resumed run may not change a
        simulated plant for a real one, nor lock-step for real time (UsageError)."""
        if mode in ('auto', 'none'):
            raise ValueError(f'bench mode {mode!r}: resolve it on the graph first')
        simulated = is_simulated(mode, self.drive)
        if self.resumed and simulated != is_simulated(self.previous_bench, self.drive):
            raise UsageError(
                f'--resume: the run used bench {self.previous_bench!r}, now '
                f'{mode!r}: the plant history cannot be restored'
            )
        if (
            self.resumed
            and simulated
            and (mode in LOCKSTEP_BENCHES) != (self.previous_bench in LOCKSTEP_BENCHES)
        ):
            raise UsageError(
                f'--resume: the run used bench {self.previous_bench!r}, now '
                f'{mode!r}: lock-step and real time do not mix in a run'
            )
        # experiment ids unique within the run: a session that does not replay (real
        # time, a real drive) starts its controller past the run's ids; lock-step replays
        # the killed sessions from id 0, bit for bit; an external controller's ids are its
        # own (the records carry their session)
        replays = simulated and mode in LOCKSTEP_BENCHES
        first = self.next_experiment_id if mode in SIM_BENCHES and not replays else 0
        return BenchPlan(
            mode=mode,
            spec=self,
            simulated=simulated,
            replays=replays,
            first_experiment_id=first,
            fault_policy=self.fault_policy or ('reset' if simulated else 'stop'),
        )

    def probe_timeout(self) -> float:
        """[s] how long ``auto``/``none`` look for a controller on the graph."""
        if self.discovery_timeout is not None:
            return self.discovery_timeout
        return DISCOVERY_TIMEOUT[self.requested]


def tuner_bench_spec(
    cli: TunerOptions,
    run: RunConfig,
    *,
    resumed: bool,
    records: Sequence[Record] = (),
    drive_choice: Any = None,
) -> BenchSpec:
    """The tuner's bench from its options and its run: ``run`` is run.yaml's settings
    (a resumed run: its model, drive file and bench come from there) or the new run's;
    ``records``: the run's results so far (a resumed session's experiment ids go on past
    them); ``drive_choice``: the checked ``--drive`` (drive_spec.resolve)."""
    if resumed:
        requested = cli.bench or run.bench_requested or 'auto'
        model, config = run.model, run.drive_config
    else:
        requested = cli.bench_asked
        model = cli.model
        config = str(cli.drive_config) if cli.drive_config else None
    assert cli.compression is not None  # (tuner_cli.check_session put the default)
    drive, ctl = bench_parameters(config, model, run.drive_seed)
    # the run's timing tolerance: every controller the tuner starts gets it
    ctl = (('timing_tolerance', int(run.timing_tolerance or 0)), *ctl)
    return BenchSpec(
        requested=requested,
        drive=run.drive or 'sim',
        drive_choice=drive_choice,
        record=not cli.no_record,
        compression=cli.compression,
        controller=cli.controller,
        discovery_timeout=cli.discovery_timeout,
        drive_parameters=drive,
        controller_parameters=ctl,
        next_experiment_id=next_experiment_id(list(records)),
        fault_policy=cli.fault_policy,
        rt_options=rt.RtOptions.from_cli(cli, rt.DEFAULT_PRIORITY),
        host_check=run.host_check,
        resumed=resumed,
        previous_bench=run.bench if resumed else None,
        live=live_settings(
            cli.live, cli.live_host, cli.live_rate, no_record=cli.no_record, check=False
        ),
    )
