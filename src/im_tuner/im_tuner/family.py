"""Each drive's experiment and tuner start: the rule that carries the paper's set-up to
another motor and load (docs/drive-family.md, "The rule: each drive's experiment and
start").  Pure.  ``drive_setup`` is the seam the tuner and the study share; the paper's
750 W motor gives exactly ``ExperimentConfig()`` and the packaged ``tuner.yaml``, every
other drive is scaled from it by ratios of its constants to the paper file's.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from im_controller.config import (
    GAIN_NAMES,
    ExperimentConfig,
    Gains,
    LossConfig,
    validate_experiment_config,
    validate_loss_config,
)
from im_drive_sim.drive_file import load_config, packaged_base
from im_drive_sim.family import DRIVE_NAMES
from im_drive_sim.params import DriveConfig, MachineParams

from .space import SearchSpace, TunerParams, load_params

#: the packaged default drive (the paper's 750 W motor; ``drive_setup(None)``)
DEFAULT_DRIVE = 'paper_750w'

#: gains scaled with the drive's J/Kt (the speed loop's); the others are kept
_SPEED_LOOP_GAINS = ('k_pw', 'k_iw')


@dataclass(frozen=True)
class DriveSetup:
    """A drive (``name``: the packaged name or the path as given) and what the tuner does
    on it: its experiment (Ts, isq_max from the drive) and tuner parameters."""

    name: str
    drive: DriveConfig
    experiment: ExperimentConfig
    params: TunerParams


@dataclass(frozen=True)
class DriveScales:
    """The drive's ratios to the paper's file (each 1.0 for it; module docstring)."""

    accel: float  # [-] (T_rated/J) / paper's: a_max
    torque: float  # [-] T_rated / paper's: load step
    inertia: float  # [-] (J/Kt) / paper's: k_pw, k_iw


@lru_cache(maxsize=1)
def _paper_drive() -> DriveConfig:
    return load_config(None)


def drive_scales(m: MachineParams) -> DriveScales:
    """The ratios of machine ``m`` to the paper's (written so each is exactly 1.0 for it)."""
    p = _paper_drive().machine
    return DriveScales(
        accel=(m.rated_torque * p.J) / (m.J * p.rated_torque),
        torque=m.rated_torque / p.rated_torque,
        inertia=(m.J * p.Kt) / (p.J * m.Kt),
    )


#: the largest current step one encoder count may make through the start's k_pw, as a
#: fraction of isq_max (research/NOTES.md, "Start gains at standstill")
COUNT_STEP_MAX = 0.25


def count_step(drive: DriveConfig, k_pw: float) -> float:
    """The q-current step [A] one encoder count makes through the speed loop's P gain k_pw
    [A s/rad]: k_pw times the speed estimate's step for one count in one period,
    (1 - a) 2 pi/(N Ts), a = exp(-Ts/tau_f) the drive's speed filter (docs/drive-model.md
    section 4)."""
    s = drive.sensors
    tau = s.speed_filter_tau
    a = math.exp(-drive.Ts / tau) if tau > 0.0 else 0.0
    return k_pw * (1.0 - a) * (2.0 * math.pi / s.encoder_counts) / drive.Ts


def start_scale(drive: DriveConfig) -> float:
    """The factor of the start's (and fallback gains') k_pw and k_iw: ``inertia`` (the
    paper's speed-loop gain on this drive), at most the factor whose k_pw makes one
    encoder count a current step of ``COUNT_STEP_MAX`` isq_max; exactly 1.0 for the
    paper's drive."""
    k_pw = ExperimentConfig().fallback_gains.k_pw
    cap = COUNT_STEP_MAX * drive.machine.isq_max / count_step(drive, k_pw)
    return min(drive_scales(drive.machine).inertia, cap)


def _scaled(values: tuple[float, ...], inertia: float) -> tuple[float, ...]:
    return tuple(
        v * inertia if n in _SPEED_LOOP_GAINS else v
        for n, v in zip(GAIN_NAMES, values, strict=True)
    )


def experiment_for(drive: DriveConfig, reference: DriveConfig | None = None) -> ExperimentConfig:
    """The drive's experiment by the rule (module docstring); validated.

    reference: the same drive on the ideal bench, full model, seed 0 (the weights are
    calibrated there, whatever ``drive``'s realism); None: ``drive`` itself."""
    base = ExperimentConfig()
    m = drive.machine
    s = drive_scales(m)
    t = base.trajectory
    start = Gains(*_scaled(base.fallback_gains.as_tuple(), start_scale(drive)))
    cfg = validate_experiment_config(
        dataclasses.replace(
            base,
            control=dataclasses.replace(base.control, Ts=drive.Ts, isq_max=m.isq_max),
            trajectory=dataclasses.replace(
                t,
                a_max=t.a_max * s.accel,
                v_max=min(t.v_max, m.rated_speed),
                load_torque=t.load_torque * s.torque,
            ),
            fallback_gains=start,
        )
    )
    ref = drive if reference is None else reference
    if ref == _paper_drive():
        return cfg  # the paper's drive: its own weights, the calibration's reference
    return dataclasses.replace(cfg, loss=_calibrated_loss(ref, cfg))


#: experiments of the weights' calibration (+pi and -pi: the two directions)
CALIBRATION_EXPERIMENTS = 2


@lru_cache(maxsize=64)
def _start_terms(drive: DriveConfig, cfg: ExperimentConfig) -> tuple[float, float, float]:
    """Mean terms (a_j int f_j dt) of the start (``cfg.fallback_gains``) on ``drive`` over
    ``CALIBRATION_EXPERIMENTS`` experiments, the supervisor off (thresholds 1e12)."""
    from .offline import OfflineBench  # numba: only where a drive is calibrated

    off = dataclasses.replace(cfg.loss, threshold1=1e12, threshold2=1e12, threshold3=1e12)
    bench = OfflineBench(drive, drive.seed, dataclasses.replace(cfg, loss=off))
    runs = [bench.measure(cfg.fallback_gains).terms for _ in range(CALIBRATION_EXPERIMENTS)]
    return tuple(sum(r[j] for r in runs) / len(runs) for j in range(3))  # type: ignore[return-value]


def _calibrated_loss(reference: DriveConfig, cfg: ExperimentConfig) -> LossConfig:
    """Weights a_j such that each term of the drive's start equals the paper's start's
    term on the paper's drive (the paper's rule: the start's terms about 1/3 each)."""
    want = _start_terms(_paper_drive(), experiment_for(_paper_drive()))
    have = _start_terms(reference, cfg)
    w = cfg.loss
    a = [x * t / h for x, t, h in zip((w.a1, w.a2, w.a3), want, have, strict=True)]
    return validate_loss_config(dataclasses.replace(w, a1=a[0], a2=a[1], a3=a[2]))


def params_for(drive: DriveConfig, name: str) -> TunerParams:
    """The packaged tuner parameters with k_pw, k_iw scaled to ``drive``: the box's by
    ``inertia``, the start's by ``start_scale``."""
    base = load_params(None)
    k, k0 = drive_scales(drive.machine).inertia, start_scale(drive)
    if k == 1.0 and k0 == 1.0:
        return base
    sp = base.space
    space = SearchSpace(_scaled(sp.lo, k), _scaled(sp.hi, k), _scaled(sp.start, k0))
    return TunerParams(space, base.satisfactory_loss, f'{base.source} scaled for {name}')


def drive_setup(
    drive: str | Path | None = None, realism: str | None = None, model: str | None = None
) -> DriveSetup:
    """The setup of ``drive`` (a packaged name such as ``im3700w-j3``, a drive file's path,
    or None: the packaged default ``paper_750w``), with the realism profile ``realism``
    and the model ``model`` when given (None: the file's own). Raises ``ConfigError`` (a
    ``ValueError``, one line) for an unknown name or a bad file."""
    overrides: dict[str, str] = {}
    if realism is not None:
        overrides['realism'] = realism
    if model is not None:
        overrides['model'] = model
    cfg = load_config(drive, overrides=overrides or None)
    ref = cfg
    if (cfg.model, cfg.realism, cfg.seed) != tuple(_REFERENCE.values()):
        ref = load_config(drive, overrides=_REFERENCE)
    name = DEFAULT_DRIVE if drive is None else str(drive)
    return DriveSetup(name, cfg, experiment_for(cfg, ref), params_for(cfg, name))


#: the bench the weights are calibrated on: the drive file's own, full model, ideal, seed 0
_REFERENCE: dict[str, object] = {'model': 'full', 'realism': 'ideal', 'seed': 0}


def with_start(setup: DriveSetup, start: Gains) -> ExperimentConfig:
    """``setup``'s experiment with another start (and fallback gains), its loss weights
    calibrated on that start as ``drive_setup`` calibrates them on the rule's."""
    if start == setup.experiment.fallback_gains:
        return setup.experiment
    cfg = dataclasses.replace(setup.experiment, fallback_gains=start)
    ref = load_config(setup.name, overrides=_REFERENCE)
    if ref == _paper_drive():
        raise ValueError("the paper's drive keeps the paper's weights: no other start")
    return dataclasses.replace(cfg, loss=_calibrated_loss(ref, cfg))


def controller_parameters(setup: DriveSetup) -> tuple[tuple[str, float], ...]:
    """The controller's parameters (``trajectory.*``, ``loss.*``, ``fallback_gains.*`` and
    the gains, which start at the drive's start) where ``setup`` differs from the
    controller's defaults: none for the paper's drive."""
    base = ExperimentConfig()
    e = setup.experiment
    out: list[tuple[str, float]] = []
    for section in ('trajectory', 'loss'):
        mine, theirs = getattr(e, section), getattr(base, section)
        for f in dataclasses.fields(mine):
            v = getattr(mine, f.name)
            if v != getattr(theirs, f.name):
                out.append((f'{section}.{f.name}', v))
    if e.fallback_gains != base.fallback_gains:
        start = e.fallback_gains.as_tuple()
        out.extend((f'fallback_gains.{n}', v) for n, v in zip(GAIN_NAMES, start, strict=True))
        out.extend(zip(GAIN_NAMES, start, strict=True))
    return tuple(out)


def tuner_setup(drive_config: str | Path | None) -> DriveSetup | None:
    """The setup the tuner takes from ``--drive-config``: a packaged drive's name gives its
    setup; a file on a packaged base (``base: im7500w-j3``) that base's with the file's
    own drive (its Ts and isq_max); none, or a file without a base, None (the paper's)."""
    if drive_config is None:
        return None
    base = packaged_base(drive_config)
    if base is None:
        return None
    setup = drive_setup(base)
    if str(drive_config) == base:
        return setup
    drive = load_config(drive_config)
    e = setup.experiment
    control = dataclasses.replace(e.control, Ts=drive.Ts, isq_max=drive.machine.isq_max)
    experiment = validate_experiment_config(dataclasses.replace(e, control=control))
    return DriveSetup(str(drive_config), drive, experiment, setup.params)


#: ``check_drive``'s default current step [A] (the paper's motor) and the largest fraction
#: of isq_max a family drive's step takes
CHECK_AMPLITUDE = 0.5
CHECK_AMPLITUDE_MAX = 0.4


def check_amplitude(drive: DriveConfig) -> float:
    """``check_drive --amplitude`` for ``drive`` [A]: the default 0.5 A times the drive's
    J/Kt ratio to the paper's (the same acceleration of the shaft), at most 40 % of
    isq_max (check_drive refuses more than 50 %)."""
    m = drive.machine
    return min(CHECK_AMPLITUDE * drive_scales(m).inertia, CHECK_AMPLITUDE_MAX * m.isq_max)


def family_table(names: tuple[str, ...] = DRIVE_NAMES, experiments: int = 3) -> str:
    """Markdown table of each drive's setup and its start measured offline (``experiments``
    experiments from rest, drive seed 0, the drive file's own model and realism): the
    table of docs/drive-family.md (``python -m im_tuner.family``)."""
    from .offline import OfflineBench

    head = (
        '| drive | J_total [kg m^2] | a_max [rad/s^2] | load [N m] | k_pw [A s/rad] | '
        'k_iw [A/rad] | a1, a2, a3 | start loss (min-max) | terms | aborted | '
        'check_drive A [A] |\n|' + '---|' * 11
    )
    rows = [head]
    for name in names:
        s = drive_setup(name)
        e, g = s.experiment, s.experiment.fallback_gains
        bench = OfflineBench(s.drive, 0, e)
        ms = [bench.measure(g) for _ in range(experiments)]
        loss = [m.loss for m in ms]
        terms = [sum(m.terms[j] for m in ms) / len(ms) for j in range(3)]
        w = e.loss
        rows.append(
            f'| {name} | {s.drive.machine.J:.4g} | {e.trajectory.a_max:.1f} | '
            f'{e.trajectory.load_torque:.3g} | {g.k_pw:.4g} | {g.k_iw:.4g} | '
            f'{w.a1:.3g}, {w.a2:.3g}, {w.a3:.3g} | {sum(loss) / len(loss):.4f} '
            f'({min(loss):.4f}-{max(loss):.4f}) | '
            f'{terms[0]:.3f}, {terms[1]:.3f}, {terms[2]:.3f} | '
            f'{sum(m.aborted for m in ms)}/{len(ms)} | {check_amplitude(s.drive):.3g} |'
        )
    return '\n'.join(rows)


if __name__ == '__main__':  # python -m im_tuner.family [EXPERIMENTS]
    import sys

    print(family_table(experiments=int(sys.argv[1]) if len(sys.argv) > 1 else 3))
