"""Configuration of the induction-motor drive simulator: frozen dataclasses, YAML loading
and validation (reading a drive file and its ``base``, ``load_config``: ``drive_file.py``).

Every value is validated on load and a ``ConfigError`` names the file and the dotted key
path of the first bad value (the policy: docs/drive-model.md, "Parameter file reference").

Units are SI throughout; dq quantities are amplitude-invariant peak values.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any


class ConfigError(ValueError):
    """Invalid drive configuration; the message names the source and the key path."""


def _f(
    unit: str,
    lo: float | None = 0.0,
    strict: bool = True,
    hi: float | None = None,
    doc: str = '',
    off: float | None = None,
    new: bool = False,
) -> Any:
    """Float field metadata: bounds ``lo < x`` (strict) or ``lo <= x``, optional ``x <= hi``.

    ``off``: a bench effect's key, optional in a file: when absent, the realism profile's
    value, else ``off`` (the value that switches the effect off). ``new``: a key added after
    files existed, also a keyword default of the dataclass (constructors need not name it).
    """
    meta = {'kind': 'float', 'unit': unit, 'lo': lo, 'strict': strict, 'hi': hi, 'doc': doc}
    if off is None:
        return field(metadata=meta)
    meta['off'] = off
    if new:
        return field(default=off, kw_only=True, metadata=meta)
    return field(metadata=meta)


def _i(unit: str, lo: int = 0, hi: int | None = None, doc: str = '') -> Any:
    """Integer field metadata: ``lo <= x <= hi``."""
    return field(metadata={'kind': 'int', 'unit': unit, 'lo': lo, 'hi': hi, 'doc': doc})


@dataclass(frozen=True)
class MachineParams:
    """Induction machine, shaft and inverter constants (SI, peak amplitude-invariant dq)."""

    Rs: float = _f('ohm', doc='stator resistance')
    Rr: float = _f('ohm', doc='rotor resistance referred to the stator')
    Lls: float = _f('H', doc='stator leakage inductance')
    Llr: float = _f('H', doc='rotor leakage inductance')
    Lm: float = _f('H', doc='magnetising inductance')
    pole_pairs: int = _i('-', lo=1, doc='pole pairs p')
    J: float = _f('kg m^2', doc='total inertia, motor + load machine')
    B: float = _f('N m s/rad', strict=False, doc='viscous friction')
    coulomb_torque: float = _f('N m', strict=False, doc='Coulomb friction Tc (0 = off)', off=0.0)
    coulomb_speed: float = _f('rad/s', doc='smoothing speed: Tc tanh(omega/omega_c)')
    rated_torque: float = _f('N m')
    rated_speed: float = _f('rad/s', doc='mechanical')
    rated_flux_current: float = _f('A', doc='isd* (peak, amplitude-invariant)')
    isq_max: float = _f('A', doc='clamp of the torque-current command')
    Udc: float = _f('V', doc='DC-link voltage; voltage limit Udc/sqrt(3)')
    static_torque: float = _f(
        'N m', strict=False, doc='Stribeck static torque Ts >= Tc (0 = off)', off=0.0, new=True
    )
    stribeck_speed: float = _f('rad/s', doc='Stribeck speed ws', off=1.0, new=True)
    deadtime_voltage: float = _f(
        'V',
        strict=False,
        doc='inverter dead-time voltage error per leg (0 = off)',
        off=0.0,
        new=True,
    )
    rr_temp_rise: float = _f(
        'K', strict=False, doc='rotor temperature rise over a run (0 = off)', off=0.0, new=True
    )
    rr_temp_tau: float = _f('s', doc='thermal time constant of the rise', off=1200.0, new=True)
    rr_temp_coeff: float = _f(
        '1/K', strict=False, doc='temperature coefficient of Rr (copper)', off=0.00393, new=True
    )

    # Derived constants (equations in docs/drive-model.md)
    @property
    def Ls(self) -> float:
        """Stator self inductance Ls = Lls + Lm [H]."""
        return self.Lls + self.Lm

    @property
    def Lr(self) -> float:
        """Rotor self inductance Lr = Llr + Lm [H]."""
        return self.Llr + self.Lm

    @property
    def kr(self) -> float:
        """Rotor coupling factor kr = Lm/Lr [-]."""
        return self.Lm / self.Lr

    @property
    def sigma(self) -> float:
        """Total leakage factor sigma = 1 - Lm^2/(Ls Lr) [-]."""
        return 1.0 - self.Lm * self.Lm / (self.Ls * self.Lr)

    @property
    def tau_r(self) -> float:
        """Rotor time constant tau_r = Lr/Rr [s]."""
        return self.Lr / self.Rr

    @property
    def R_sigma(self) -> float:
        """Equivalent resistance R_sigma = Rs + kr^2 Rr [ohm]."""
        return self.Rs + self.kr**2 * self.Rr

    @property
    def rated_flux(self) -> float:
        """Rated rotor flux psi_r = Lm isd_rated [Wb]."""
        return self.Lm * self.rated_flux_current

    @property
    def Kt(self) -> float:
        """Torque constant at rated flux Kt = 1.5 p (Lm/Lr) psi_r [N m/A]."""
        return 1.5 * self.pole_pairs * self.kr * self.rated_flux

    @property
    def u_max(self) -> float:
        """Circular voltage limit Udc/sqrt(3) [V, peak phase]."""
        return self.Udc / math.sqrt(3.0)

    @property
    def rated_current(self) -> float:
        """Rated stator current [A, peak]: sqrt(isd_rated^2 + isq_rated^2) at rated flux
        and torque, isq_rated = rated_torque/Kt."""
        isq = self.rated_torque / self.Kt
        return math.sqrt(self.rated_flux_current * self.rated_flux_current + isq * isq)


@dataclass(frozen=True)
class ControlParams:
    """Inner (vector) control and reduced-model constants."""

    current_bandwidth: float = _f('rad/s', doc='PI current loop bandwidth wc')
    reduced_current_lag: float = _f('s', strict=False, doc='reduced model: isq lag tau_i')
    computation_delay_steps: int = _i(
        'steps', lo=0, hi=1, doc='0: voltage applied in the same step, 1: next step'
    )
    flux_floor: float = _f('Wb', doc='floor of psi_hat in the slip calculation')


@dataclass(frozen=True)
class SensorParams:
    """Measurement as the controller sees it."""

    encoder_counts: int = _i('counts/rev', lo=1)
    speed_filter_tau: float = _f('s', strict=False, doc='0 disables the filter')
    current_noise_std: float = _f('A', strict=False, off=0.0)
    speed_noise_std: float = _f('rad/s', strict=False)
    current_offset_a: float = _f('A', lo=None, doc='offset of phase a sensor', off=0.0, new=True)
    current_offset_b: float = _f('A', lo=None, doc='offset of phase b sensor', off=0.0, new=True)
    encoder_jitter: float = _f(
        's', strict=False, doc='std of the encoder edge (latch) time', off=0.0, new=True
    )


@dataclass(frozen=True)
class DisturbanceParams:
    """Load-side dynamics and disturbances."""

    load_lag_tau: float = _f('s', strict=False, doc='load machine torque lag, 0 = ideal')
    ripple_amplitude: float = _f('N m', strict=False, off=0.0)
    ripple_harmonic: float = _f('per rev', strict=False, off=1.0)
    ripple_phase: float = _f('rad', lo=None)
    load_noise_std: float = _f('N m', strict=False, doc='stationary std of random load', off=0.0)
    load_noise_tau: float = _f('s', strict=False, doc='correlation time, 0 = white', off=0.0)
    # the load step's variation (docs/drive-model.md 7a): relative std [-], largest delay [s]
    load_step_amplitude_std: float = _f('-', strict=False, hi=0.5, off=0.0, new=True)
    load_step_delay_max: float = _f('s', strict=False, hi=1.0, off=0.0, new=True)


_SECTIONS: dict[str, type] = {
    'machine': MachineParams,
    'control': ControlParams,
    'sensors': SensorParams,
    'disturbance': DisturbanceParams,
}
_TOP_SCALARS = ('model', 'Ts', 'seed', 'command_delay', 'realism')
#: Top-level keys a file may leave out, with their defaults.
_OPTIONAL: dict[str, Any] = {'command_delay': 1, 'realism': 'ideal'}
_MODELS = ('full', 'reduced')

#: The bench effects that vary from one experiment to the next (noise-like): the calibration
#: (``research/calibrate_bench.py``, docs/calibration.md) scales them together by one
#: factor s; the others (offsets, friction, ripple, dead time, Rr drift) are systematic and
#: keep their sourced magnitude.
BENCH_NOISE_KEYS: tuple[str, ...] = (
    'sensors.current_noise_std',
    'sensors.encoder_jitter',
    'disturbance.load_noise_std',
    'disturbance.load_step_amplitude_std',
    'disturbance.load_step_delay_max',
)
#: Each bench effect at its sourced magnitude for the reference drive, the paper's 750 W
#: (``BENCH_REFERENCE``; docs/drive-model.md, "Bench effects": the source, equation and
#: magnitude of each): the ``bench`` profile at noise scale s = 1 on that drive.
BENCH_ESTIMATES: dict[str, float] = {
    'sensors.current_noise_std': 0.01,
    'sensors.current_offset_a': 0.05,
    'sensors.current_offset_b': -0.03,
    'sensors.encoder_jitter': 1.0e-6,
    'machine.coulomb_torque': 0.02,
    'machine.static_torque': 0.03,
    'machine.stribeck_speed': 2.0,
    'machine.deadtime_voltage': 3.0,
    'machine.rr_temp_rise': 40.0,
    'machine.rr_temp_tau': 1200.0,
    'disturbance.ripple_amplitude': 0.025,
    'disturbance.ripple_harmonic': 6.0,
    'disturbance.load_noise_std': 0.0125,
    'disturbance.load_noise_tau': 0.02,
    'disturbance.load_step_amplitude_std': 0.02,
    'disturbance.load_step_delay_max': 1.0e-3,
}
#: The rating the magnitudes of ``BENCH_ESTIMATES`` are sourced for: the paper's 750 W drive
#: (``paper_750w.yaml``: rated torque [N m], DC bus [V], ``MachineParams.rated_current``
#: [A peak]; a test checks they are that file's, so its scales are exactly 1.0).
BENCH_REFERENCE: dict[str, float] = {
    'torque': 2.5,
    'bus': 311.0,
    'current': 4.289303488773733,
}
#: How each bench effect follows the drive's rating (docs/drive-model.md, "Bench effects"):
#: in proportion to the rated ``torque``, the DC ``bus`` or the rated ``current``. The
#: others (times, speeds, relative values, the rotor's warming) keep their magnitude.
BENCH_SCALING: dict[str, str] = {
    'sensors.current_noise_std': 'current',
    'sensors.current_offset_a': 'current',
    'sensors.current_offset_b': 'current',
    'machine.coulomb_torque': 'torque',
    'machine.static_torque': 'torque',
    'machine.deadtime_voltage': 'bus',
    'disturbance.ripple_amplitude': 'torque',
    'disturbance.load_noise_std': 'torque',
}
#: The calibrated scale of the noise-like magnitudes (docs/calibration.md: the fit that
#: chose it, reproduced by ``make calibrate-bench``).
BENCH_NOISE_SCALE = 4.0


def rating_scales(m: MachineParams) -> dict[str, float]:
    """The machine's rating over the reference's (``BENCH_REFERENCE``), by ``BENCH_SCALING``
    rule: rated torque, DC bus, rated current; each exactly 1.0 for the paper's 750 W."""
    return {
        'torque': m.rated_torque / BENCH_REFERENCE['torque'],
        'bus': m.Udc / BENCH_REFERENCE['bus'],
        'current': m.rated_current / BENCH_REFERENCE['current'],
    }


def bench_profile(
    scale: float = BENCH_NOISE_SCALE, machine: MachineParams | None = None
) -> dict[str, float]:
    """The ``bench`` effect values with the noise-like ones (``BENCH_NOISE_KEYS``) scaled
    by ``scale`` from their sourced magnitudes (``BENCH_ESTIMATES``), and each effect of
    ``BENCH_SCALING`` by ``machine``'s rating over the reference's (``rating_scales``;
    None: the reference drive, the paper's 750 W). As overrides, a drive file's
    ``realism: bench`` at another noise scale."""
    r = rating_scales(machine) if machine is not None else {}
    out = {}
    for k, v in BENCH_ESTIMATES.items():
        x = v * scale if k in BENCH_NOISE_KEYS else v
        rule = BENCH_SCALING.get(k)
        out[k] = x * r[rule] if rule is not None and machine is not None else x
    return out


#: Realism profiles: the values of the bench-effect keys (those with an ``off`` value) that
#: a file leaves out, at the reference rating (``BENCH_REFERENCE``, the paper's 750 W; a
#: drive's own: ``realism_values``). ``ideal``: every effect off. ``bench``: each effect at
#: its magnitude of docs/drive-model.md ("Bench effects"), the noise-like ones scaled by
#: ``BENCH_NOISE_SCALE``, the rating-bound ones (``BENCH_SCALING``) by the drive's rating.
#: A key the file (or an override) gives explicitly wins over its profile.
REALISM_PROFILES: dict[str, dict[str, float]] = {
    'ideal': {},
    'bench': bench_profile(),
}


def realism_values(realism: str, machine: MachineParams) -> dict[str, float]:
    """The profile ``realism``'s values for a drive with ``machine``'s rating: ``bench``
    scaled by ``rating_scales`` (``bench_profile``), ``ideal`` none."""
    if realism == 'bench':
        return bench_profile(BENCH_NOISE_SCALE, machine)
    return dict(REALISM_PROFILES[realism])


@dataclass(frozen=True)
class DriveConfig:
    """Complete simulator configuration.

        ``model``: ``'full'`` (voltage-fed IM + vector control) or ``'reduced'`` (ideal field
        orientation, isq lag); ``Ts``: control/simulation step [s] (an integer number of ns);
        ``seed``: seed of the disturbance/noise streams; ``command_delay``: the drive's
        command delay d [periods] (1: the command answering state k acts over k -> k+1; 2: a
        power stage that latches it at the next period start, k+1 -> k+2; the one optional
        key, default 1); ``realism``: the profile (``REALISM_PROFILES``) that gave the bench-effect
    keys the file leaves out (optional, default ``ideal``); ``source``: where it was loaded from.
    """

    model: str
    Ts: float
    seed: int
    machine: MachineParams
    control: ControlParams
    sensors: SensorParams
    disturbance: DisturbanceParams
    command_delay: int = 1
    realism: str = 'ideal'
    source: str = field(default='<dict>', compare=False)
    #: the file it was loaded from, absolute ('' for a mapping): a drive library's
    #: ``im_drive_open`` gets it (hardware_abi)
    path: str = field(default='', compare=False)

    @property
    def Ts_ns(self) -> int:
        """Step length in integer nanoseconds."""
        return round(self.Ts * 1e9)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict in the YAML layout (round-trips through ``config_from_dict``)."""
        out: dict[str, Any] = {
            'model': self.model,
            'Ts': self.Ts,
            'seed': self.seed,
            'command_delay': self.command_delay,
            'realism': self.realism,
        }
        for name in _SECTIONS:
            sec = getattr(self, name)
            out[name] = {f.name: getattr(sec, f.name) for f in fields(sec)}
        return out


def default_config_path() -> Path:
    """Path of the packaged default machine file ``im_drive_sim/config/paper_750w.yaml``."""
    return Path(str(resources.files('im_drive_sim').joinpath('config', 'paper_750w.yaml')))


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check(src: str, key: str, v: Any, meta: Mapping[str, Any]) -> Any:
    """``v`` as the field's ``kind`` (float: a finite number; int: an integer, not a bool)
    with ``lo < v`` (``strict``) or ``lo <= v`` (None: no bound) and ``v <= hi``;
    ``ConfigError`` naming ``key`` and what it must be."""
    lo, hi, strict, is_int = meta['lo'], meta['hi'], meta.get('strict'), meta['kind'] == 'int'
    req = 'an integer' if is_int else 'a finite number'
    if lo is not None:
        req += f' {">" if strict else ">="} {lo:g}'
    if hi is not None:
        req += f' and <= {hi:g}'
    if is_int:
        ok = isinstance(v, int) and not isinstance(v, bool)
    else:
        ok = _is_number(v) and math.isfinite(float(v))
    if ok and lo is not None:
        ok = v > lo if strict else v >= lo
    if ok and hi is not None:
        ok = v <= hi
    if not ok:
        raise ConfigError(f'{src}: {key} must be {req}, got {v!r}')
    return int(v) if is_int else float(v)


def _apply_overrides(src: str, data: dict[str, Any], overrides: Mapping[str, Any]) -> None:
    """Merge nested or dotted overrides into ``data`` in place (keys must exist)."""
    if not isinstance(overrides, Mapping):
        raise ConfigError(f'{src}: overrides must be a mapping, got {type(overrides).__name__}')
    for k, v in overrides.items():
        if not isinstance(k, str):
            raise ConfigError(f'{src}: override key {k!r} is not a string')
        parts = k.split('.')
        if len(parts) == 1 and k in _SECTIONS and isinstance(v, Mapping):
            for sk, sv in v.items():
                _apply_overrides(src, data, {f'{k}.{sk}': sv})
            continue
        if len(parts) == 1 and k in _TOP_SCALARS:
            data[k] = v
        elif (
            len(parts) == 2
            and parts[0] in _SECTIONS
            and parts[1] in {f.name for f in fields(_SECTIONS[parts[0]])}
        ):
            sec = data.setdefault(parts[0], {})
            if not isinstance(sec, dict):
                raise ConfigError(f'{src}: {parts[0]} must be a mapping')
            sec[parts[1]] = v
        else:
            raise ConfigError(f'{src}: unknown override key {k}')


def config_from_dict(
    data: Any, source: str = '<dict>', overrides: Mapping[str, Any] | None = None
) -> DriveConfig:
    """Validate a complete nested mapping (YAML layout) and build a ``DriveConfig``.

    Raises ``ConfigError("<source>: <key path> ...")`` on the first problem.
    """
    src = source
    if not isinstance(data, Mapping):
        raise ConfigError(
            f'{src}: top level must be a mapping of sections, got {type(data).__name__}'
        )
    data = {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in data.items()}
    if overrides:
        _apply_overrides(src, data, overrides)
    allowed = set(_TOP_SCALARS) | set(_SECTIONS)
    for k in data:
        if k not in allowed:
            raise ConfigError(f'{src}: unknown key {k} (allowed: {", ".join(sorted(allowed))})')
    for k in list(_TOP_SCALARS) + list(_SECTIONS):
        if k not in data and k not in _OPTIONAL:
            raise ConfigError(f'{src}: missing key {k}')

    model = data['model']
    if model not in _MODELS:
        raise ConfigError(f'{src}: model must be one of {", ".join(_MODELS)}, got {model!r}')
    Ts = _check(src, 'Ts', data['Ts'], {'kind': 'float', 'lo': 0.0, 'strict': True, 'hi': 1e-2})
    if abs(Ts * 1e9 - round(Ts * 1e9)) > 1e-6 * max(1.0, Ts * 1e9):
        raise ConfigError(f'{src}: Ts must be an integer number of nanoseconds, got {Ts!r}')
    seed = _check(src, 'seed', data['seed'], {'kind': 'int', 'lo': 0, 'hi': None})
    command_delay = _check(
        src,
        'command_delay',
        data.get('command_delay', _OPTIONAL['command_delay']),
        {'kind': 'int', 'lo': 1, 'hi': 2},
    )
    realism = data.get('realism', _OPTIONAL['realism'])
    if not isinstance(realism, str) or realism not in REALISM_PROFILES:
        raise ConfigError(
            f'{src}: realism must be one of {", ".join(REALISM_PROFILES)}, got {realism!r}'
        )
    # the effects off first (every key checked), then the profile for the drive's rating
    built = _build_sections(src, data, {})
    if REALISM_PROFILES[realism]:
        built = _build_sections(src, data, realism_values(realism, built['machine']))

    cfg = DriveConfig(
        model=model,
        Ts=Ts,
        seed=seed,
        command_delay=command_delay,
        realism=realism,
        source=src,
        **built,
    )
    _check_consistency(src, cfg)
    return cfg


def _build_sections(
    src: str, data: Mapping[str, Any], profile: Mapping[str, float]
) -> dict[str, Any]:
    """The sections' dataclasses from ``data``, a bench effect's key the file leaves out
    taking ``profile``'s value, else its off value; each value checked."""
    built: dict[str, Any] = {}
    for sname, cls in _SECTIONS.items():
        sec = data[sname]
        if not isinstance(sec, Mapping):
            raise ConfigError(f'{src}: {sname} must be a mapping, got {sec!r}')
        names = [f.name for f in fields(cls)]
        for k in sec:
            if k not in names:
                raise ConfigError(f'{src}: unknown key {sname}.{k}')
        kwargs: dict[str, Any] = {}
        for f in fields(cls):
            key = f'{sname}.{f.name}'
            if f.name in sec:
                value = sec[f.name]
            elif 'off' in f.metadata:  # a bench effect: the profile's value, else off
                value = profile.get(key, f.metadata['off'])
            else:
                raise ConfigError(f'{src}: missing key {key}')
            kwargs[f.name] = _check(src, key, value, f.metadata)
        built[sname] = cls(**kwargs)
    return built


#: machine.isq_max above this multiple of the rated torque current is refused as a typo
#: (drives clamp at 1.5-3x rated; the paper's file clamps at 2x).
ISQ_MAX_PER_RATED = 4.0


def _check_consistency(src: str, cfg: DriveConfig) -> None:
    """Cross-field checks: physically consistent and numerically safe combinations."""
    m, c = cfg.machine, cfg.control
    # Holding rated flux at standstill needs u = Rs isd_rated inside the voltage limit.
    if m.Rs * m.rated_flux_current >= m.u_max:
        raise ConfigError(
            f'{src}: machine.Udc too low: voltage limit Udc/sqrt(3) = {m.u_max:.4g} V cannot '
            f'hold rated flux at standstill (Rs*rated_flux_current = '
            f'{m.Rs * m.rated_flux_current:.4g} V)'
        )
    # RK4 with one sub-step: keep |lambda| Ts well inside the stability region (notes: 0.06).
    lam = m.R_sigma / (m.sigma * m.Ls)
    if lam * cfg.Ts > 1.0:
        raise ConfigError(
            f'{src}: Ts = {cfg.Ts:g} s too large for the electrical dynamics '
            f'(R_sigma/(sigma Ls) * Ts = {lam * cfg.Ts:.3g} > 1)'
        )
    if c.current_bandwidth * cfg.Ts > 1.0:
        raise ConfigError(
            f'{src}: control.current_bandwidth too high for Ts: wc*Ts = '
            f'{c.current_bandwidth * cfg.Ts:.3g} > 1'
        )
    # The clamp is the drive's hard current limit: a typo (700 A for this 3.1 A motor)
    # would let the controller ask for 100x rated torque. Rated torque current Tn/Kt.
    isq_rated = m.rated_torque / m.Kt
    if m.isq_max > ISQ_MAX_PER_RATED * isq_rated:
        raise ConfigError(
            f'{src}: machine.isq_max {m.isq_max:g} A is implausible: {m.isq_max / isq_rated:.3g}'
            f'x the rated torque current {isq_rated:.3g} A (rated_torque/Kt); at most '
            f'{ISQ_MAX_PER_RATED:g}x ({ISQ_MAX_PER_RATED * isq_rated:.3g} A) is accepted'
        )
    if m.static_torque != 0.0 and m.static_torque < m.coulomb_torque:
        raise ConfigError(
            f'{src}: machine.static_torque {m.static_torque:g} N m must be 0 (off) or >= '
            f'machine.coulomb_torque {m.coulomb_torque:g} N m'
        )
    if c.flux_floor >= m.rated_flux:
        raise ConfigError(
            f'{src}: control.flux_floor {c.flux_floor:g} Wb must be below the '
            f'rated flux {m.rated_flux:.4g} Wb'
        )
