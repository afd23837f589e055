"""run.yaml and summary.json as typed objects: :class:`RunConfig` and :class:`Summary`.

Each keeps its file's keys in order (``to_text(from_text(text)) == text`` for the files
the tuner writes), an unknown key in ``extra``; a file without ``version`` is format 1.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any

import yaml

#: The run.yaml / summary.json format this im_tuner writes (and the newest it reads).
FILE_VERSION = 1


class FileError(ValueError):
    """Not a run.yaml / summary.json of a format this im_tuner reads (message: why)."""


class VersionError(FileError):
    """A run.yaml / summary.json of a format version this im_tuner does not read (a newer
    im_tuner wrote it): never taken for a missing file."""


@dataclass(kw_only=True)
class _Keyed:
    """Fields that mirror a file's mapping; ``keys``: the file's keys in order."""

    version: int = FILE_VERSION
    extra: dict[str, Any] = field(default_factory=dict)
    keys: tuple[str, ...] = field(default=(), compare=False, repr=False)

    @classmethod
    def from_dict(cls, data: dict[str, Any]):  # -> Self
        version = data.get('version', 1)
        if (
            not isinstance(version, int)
            or isinstance(version, bool)
            or not 1 <= version <= FILE_VERSION
        ):
            raise VersionError(
                f'format version {version!r}: this im_tuner reads versions 1 to {FILE_VERSION} '
                '(a newer im_tuner wrote it?)'
            )
        names = {f.name for f in dataclasses.fields(cls)} - {'extra', 'keys'}
        known = {k: v for k, v in data.items() if k in names}
        extra = {k: v for k, v in data.items() if k not in names}
        return cls(**known, extra=extra, keys=tuple(data))

    def put(self, **fields: Any) -> None:
        """Set fields as the file will hold them: in the order put, after the keys it has,
        and written even when None (``null``), as a mapping's keys would be."""
        for k, v in fields.items():
            setattr(self, k, v)
            if k not in self.keys:
                self.keys = (*self.keys, k)

    def to_dict(self) -> dict[str, Any]:
        """The file's mapping: its keys in order, then the fields set since (not None)."""
        out: dict[str, Any] = {}
        if self.version != 1:
            out['version'] = self.version
        names = [
            f.name for f in dataclasses.fields(self) if f.name not in ('version', 'extra', 'keys')
        ]
        for k in self.keys:
            if k in self.extra:
                out[k] = self.extra[k]
            elif k in names:
                out[k] = getattr(self, k)
        for k in names:
            if k not in out and getattr(self, k) is not None:
                out[k] = getattr(self, k)
        return out


@dataclass(kw_only=True)
class RunConfig(_Keyed):
    """run.yaml: what ran (docs/tuner.md, "The run directory"); None: not in the file."""

    algo: str
    #: the algorithm's options given and the run's policies (``optim.POLICIES``: start,
    #: first; safe's model point stands for first: model)
    options: dict[str, Any] | None = None
    budget: int | None = None  #: evaluations
    seed: int | None = None  #: the run seed (optimiser and drive noise streams)
    drive_seed: int | None = None  #: the simulated drive's noise seed
    remeasure: int | None = None  #: re-measurements of the best distinct evaluations
    reference: bool | None = None  #: a reference experiment of the start gains
    retries: int | None = None  #: re-runs of a lost / off-timing attempt
    #: held + late drive periods an experiment may have and count (--timing-tolerance)
    timing_tolerance: int | None = None
    #: the host's check before the first experiment (im_drive_sim.host.check_before_run:
    #: late_pct, tolerance, share_meeting, meets, auto, ...); None: not a real-time bench
    host_check: dict[str, Any] | None = None
    #: the final choice's standstill-ripple limit (--ripple-limit): a ratio to the
    #: start's rms of isq*; None: off
    ripple_limit: float | None = None
    drive: str | None = None  #: 'sim' or the drive given with --drive
    satisfactory_loss: float | None = None
    params_file: str | None = None
    search_box: dict[str, Any] | None = None  #: name -> {lo, hi, start, unit}
    command: str | None = None  #: the tuner's command line
    bench_requested: str | None = None  #: --bench as given
    bench: str | None = None  #: the bench it ran on
    model: str | None = None
    drive_config: str | None = None
    controller_parameters: dict[str, Any] | None = None
    fault_policy: str | None = None
    #: the numeric baseline the run began on (im_drive_sim.numeric.status(): level, state,
    #: reason, numpy dispatch, OpenBLAS cores, cpu)
    numeric: dict[str, Any] | None = None

    HEADER = '# im_tuner run: what ran (see docs/tuner.md)\n'

    def to_text(self) -> str:
        """run.yaml's text."""
        return self.HEADER + yaml.safe_dump(
            self.to_dict(), sort_keys=False, default_flow_style=None, width=100
        )

    @classmethod
    def from_text(cls, text: str) -> RunConfig:
        """run.yaml's text read; :class:`FileError` if it is not a run file."""
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            # (YAML's message spans lines: the refusal is one)
            raise FileError(f'unreadable ({" ".join(str(exc).split())})') from None
        if not isinstance(data, dict) or 'algo' not in data:
            raise FileError('not a tuner run file')
        run = cls.from_dict(data)
        if 'budget' not in data:  # every tuner writes it: a hand edit lost it
            others = (
                f' (other keys: {", ".join(map(repr, run.extra))}: a typo?)' if run.extra else ''
            )
            raise FileError(f'no budget{others}')
        return run


@dataclass(kw_only=True)
class Summary(_Keyed):
    """summary.json: a run's outcome (docs/tuner.md, "Output"); None: not in the file."""

    outcome: str
    evaluations: int | None = None
    budget: int | None = None
    experiments: int | None = None
    aborted: int | None = None
    safety_faults: int | None = None
    lost: int | None = None
    timing: int | None = None  #: experiments off the paper's timing (re-run)
    #: held + late drive periods an experiment may have and count (run.yaml's)
    timing_tolerance: int | None = None
    #: of the counted experiments: {counted, with_held, total, max} held + late periods
    held_periods: dict[str, Any] | None = None
    reference: dict[str, Any] | None = None  #: {gains, loss, aborted}
    best: dict[str, Any] | None = None  #: {eval, gains, loss, terms, remeasured_loss}
    applied: dict[str, Any] | None = None  #: {eval, gains, loss, remeasured_loss, source, ..}
    remeasured: list[dict[str, Any]] | None = None  #: [{eval, loss, aborted}]
    satisfactory_loss: float | None = None
    evaluations_to_satisfactory: int | None = None
    wall_s: float | None = None  #: the session's wall time [s]
    loop_wall_s: float | None = None  #: the tuning loop's wall time [s]
    sim_s: float | None = None  #: simulated experiment time [s]
    real_time_factor: float | None = None
    optimizer_us_per_eval: float | None = None  #: median ask + tell [us]
    sessions: list[dict[str, Any]] | None = None
    #: the standstill ripple of isq* [A]: {start, applied}, each the mean over the
    #: experiments of those gains of {rms_after_move, pp_after_move, rms_after_load,
    #: pp_after_load} (records' ``ripple``); the limit (``runlog.ripple.ripple_summary``:
    #: limit, bound, applied_within, changed, excluded, fallback); rated_isq_a
    ripple: dict[str, Any] | None = None
    #: the drive identified from the start's experiments (im_tuner.identify.Identified)
    identification: dict[str, Any] | None = None
    #: candidates the abort screen kept off the drive (predicted to abort on the
    #: identified model; ``prior.AbortScreen``); None: no screen
    screened: int | None = None
    report_command: str | None = None
    what_to_do: list[str] | None = None  #: advice about a failed run, one line each

    def to_text(self) -> str:
        """summary.json's text (no NaN/inf)."""
        return json.dumps(self.to_dict(), indent=2, allow_nan=False) + '\n'

    @classmethod
    def from_text(cls, text: str | bytes) -> Summary:
        """summary.json's text read; :class:`FileError` if it is not a summary."""
        try:
            data = json.loads(text)
        except ValueError:
            raise FileError('not JSON') from None
        if not isinstance(data, dict) or not isinstance(data.get('outcome'), str):
            raise FileError('not a tuner summary')
        return cls.from_dict(data)
