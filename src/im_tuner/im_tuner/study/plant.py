"""The study's simulated plant when it is not the drive the tuner is told:
``study --plant FILE|NAME`` and ``--plant-mismatch 'J=x1.5 Rr=x1.3 coulomb=2% delay=2'``.

Everything the tuner derives from *its* drive (the experiment, the search box and its
start, ``safe``'s first step) comes from the told drive; only the offline bench the runs
measure on is the plant. L_ref is the start measured on the plant (``StudyResult.l_ref_told``
keeps the told drive's beside it). The plant must match the told drive's ``Ts`` and
``machine.isq_max`` (:func:`check_plant`); the ``--plant-mismatch`` syntax, what may differ
and why: docs/optimisers.md, "When the drive file is wrong".

Light at import (dataclasses and ``im_drive_sim.params``): the command checks its options
with it before the heavy modules load.
"""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Protocol

from im_drive_sim.params import ConfigError, DriveConfig, MachineParams, config_from_dict

#: A parsed mismatch: (key, value) in the order given; a factor for a machine key, a
#: percentage of rated torque for 'coulomb', periods for 'delay'.
Mismatch = tuple[tuple[str, float], ...]


class StudySpec(Protocol):
    """What this module reads of a ``spec.StudySpec`` (``spec`` imports this module)."""

    @property
    def drives(self) -> tuple[str, ...]: ...
    @property
    def drive_config(self) -> str | None: ...
    @property
    def plant(self) -> tuple[str, ...]: ...
    @property
    def mismatch(self) -> Mismatch: ...


class PlantError(ValueError):
    """A plant or mismatch the study cannot run: one line, naming the option."""


#: The factors a machine key may take: a drive file wrong by up to 10x either way (beyond,
#: the plant is another drive, given as --plant)
FACTOR_RANGE = (0.1, 10.0)

#: Machine keys that may not take a factor, and why.
_NO_FACTOR = {
    'isq_max': "the controller's current clamp: the plant must have the told drive's",
    'rated_torque': 'a rating the simulated machine does not use (coulomb=P% is relative to it)',
    'rated_speed': 'a rating the simulated machine does not use',
    'pole_pairs': 'an integer: give a drive file with that many pole pairs with --plant',
}
#: The machine keys a factor applies to: every float key but those of ``_NO_FACTOR``.
FACTOR_KEYS: tuple[str, ...] = tuple(
    f.name
    for f in dataclasses.fields(MachineParams)
    if f.metadata['kind'] == 'float' and f.name not in _NO_FACTOR
)
_SPECIAL = ('coulomb', 'delay')
_TOKEN = re.compile(r'[\s,]+')


def _number(text: str) -> float | None:
    try:
        v = float(text)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


def parse_mismatch(text: str) -> Mismatch:
    """``'J=x1.5 Rr=x1.3 coulomb=2% delay=2'`` -> ``(('J', 1.5), ('Rr', 1.3),
    ('coulomb', 2.0), ('delay', 2))`` (module docstring); :class:`PlantError` naming the
    token otherwise."""
    tokens = [t for t in _TOKEN.split(text.strip()) if t]
    if not tokens:
        raise PlantError('--plant-mismatch: nothing given (e.g. J=x2 coulomb=2% delay=2)')
    out: list[tuple[str, float]] = []
    for tok in tokens:
        key, eq, value = tok.partition('=')
        if not eq or not key or not value:
            raise PlantError(f'--plant-mismatch {tok!r}: KEY=VALUE expected (e.g. J=x2)')
        if any(k == key for k, _ in out):
            raise PlantError(f'--plant-mismatch {tok!r}: {key} given twice')
        out.append((key, _value(tok, key, value)))
    keys = [k for k, _ in out]
    if 'coulomb' in keys and 'coulomb_torque' in keys:
        raise PlantError('--plant-mismatch: coulomb=P% and coulomb_torque=xF: give one')
    return tuple(out)


def plant_options(
    plant: str | None, mismatch: str | None, drives: tuple[str, ...]
) -> tuple[tuple[str, ...], Mismatch]:
    """The command's ``--plant`` and ``--plant-mismatch`` (None: not given) for the told
    ``drives`` (``--drives``; () the one drive of ``--drive-config``): (plants, mismatch)
    for ``StudySpec``; :class:`PlantError` naming the option otherwise."""
    plants: tuple[str, ...] = ()
    if plant is not None:
        plants = tuple(d.strip() for d in plant.split(',') if d.strip())
        if not plants:
            raise PlantError('--plant: no drive named')
        if len(plants) > 1 and len(plants) != len(drives):
            raise PlantError(
                f'--plant: {len(plants)} plants for {max(len(drives), 1)} told drive(s) '
                '(one per drive of --drives, or one for all)'
            )
    return plants, (() if mismatch is None else parse_mismatch(mismatch))


def _value(tok: str, key: str, value: str) -> float:
    """The value of one token, checked (``parse_mismatch``)."""
    if key == 'coulomb':
        p = _number(value[:-1]) if value.endswith('%') else None
        if p is None or not 0.0 <= p <= 100.0:
            raise PlantError(
                f'--plant-mismatch {tok!r}: coulomb takes a percentage of rated torque in '
                '[0, 100], e.g. coulomb=2%'
            )
        return p
    if key == 'delay':
        if value not in ('1', '2'):
            raise PlantError(
                f'--plant-mismatch {tok!r}: delay is the command delay in periods, 1 or 2'
            )
        return int(value)
    if key in _NO_FACTOR:
        raise PlantError(f'--plant-mismatch {tok!r}: {key} takes no factor: {_NO_FACTOR[key]}')
    if key not in FACTOR_KEYS:
        raise PlantError(
            f'--plant-mismatch {tok!r}: unknown key {key!r} (a machine key: '
            f'{", ".join(FACTOR_KEYS)}; or coulomb=P%, delay=D)'
        )
    f = _number(value[1:]) if value[:1] == 'x' else None
    lo, hi = FACTOR_RANGE
    if f is None or not lo <= f <= hi:
        raise PlantError(
            f'--plant-mismatch {tok!r}: a machine key takes a factor xF with '
            f'{lo:g} <= F <= {hi:g}, e.g. {key}=x1.5 (a drive file off by more than {hi:g}x '
            'is another drive: give it as --plant)'
        )
    return f


def check_mismatch(mm: Mismatch) -> None:
    """A mismatch as :func:`parse_mismatch` gives it (a spec read back from study.json):
    ValueError otherwise."""
    try:
        text = ' '.join(
            f'{k}={v!r}%' if k == 'coulomb' else f'{k}={v:d}' if k == 'delay' else f'{k}=x{v!r}'
            for k, v in mm
        )
        ok = bool(mm) and parse_mismatch(text) == tuple((k, v) for k, v in mm)
    except (TypeError, ValueError):  # (a delay that is not an integer, a bad pair)
        ok = False
    if not ok:
        raise ValueError(f'plant-mismatch: not a mismatch: {mm!r}')


def mismatch_text(mm: Mismatch) -> str:
    """``J x1.5, Rr x1.3, Coulomb friction 2 % of rated torque, command delay 2 periods``."""
    parts = []
    for k, v in mm:
        if k == 'coulomb':
            parts.append(f'Coulomb friction {v:g} % of rated torque')
        elif k == 'delay':
            parts.append(f'command delay {int(v)} period{"s" if v != 1 else ""}')
        else:
            parts.append(f'{k} x{v:g}')
    return ', '.join(parts)


def apply_mismatch(drive: DriveConfig, mm: Mismatch) -> DriveConfig:
    """``drive`` with the mismatch ``mm`` applied (factors first, then ``coulomb``, then
    ``delay``), validated as a drive file is; ``drive`` itself when ``mm`` is empty.
    :class:`PlantError` when the result is not a valid drive (the reason in one line)."""
    if not mm:
        return drive
    data = drive.to_dict()
    m = data['machine']
    for k, v in mm:
        if k not in _SPECIAL:
            m[k] = m[k] * v
    for k, v in mm:
        if k == 'coulomb':
            tc = v / 100.0 * m['rated_torque']
            if m['static_torque'] != 0.0:  # keep the Stribeck hump's excess over Tc
                m['static_torque'] = m['static_torque'] + (tc - m['coulomb_torque'])
            m['coulomb_torque'] = tc
        elif k == 'delay':
            data['command_delay'] = int(v)
    try:
        out = config_from_dict(data, source=f'{drive.source} with {mismatch_text(mm)}')
    except ConfigError as exc:
        raise PlantError(f'--plant-mismatch: the plant is not a valid drive: {exc}') from None
    return dataclasses.replace(out, path=drive.path)


def check_plant(told: DriveConfig, plant: DriveConfig, what: str) -> None:
    """Refuse (:class:`PlantError`, one line) a plant that cannot run the told drive's
    experiment: another Ts or isq_max (docs/optimisers.md says why)."""
    if plant.Ts != told.Ts:
        raise PlantError(
            f'{what}: Ts {plant.Ts * 1e6:g} us, the told drive {told.Ts * 1e6:g} us: the '
            "controller runs the told drive's experiment at its period, in lock-step with "
            'the plant'
        )
    if plant.machine.isq_max != told.machine.isq_max:
        raise PlantError(
            f'{what}: machine.isq_max {plant.machine.isq_max:g} A, the told drive '
            f"{told.machine.isq_max:g} A: the experiment's clamp of isq* is the told drive's"
        )
    if plant.model != told.model:  # (the study's --model is applied to both)
        raise PlantError(f'{what}: model {plant.model}, the told drive {told.model}')


def make_plant(
    told: DriveConfig,
    name: str | None,
    mm: Mismatch,
    realism: str | None,
    model: str,
) -> DriveConfig:
    """The plant: the drive ``name`` (a packaged name or a drive file, loaded as the told
    drive is: the study's ``realism`` when given, its ``model``; None: ``told`` itself) with
    the mismatch ``mm`` applied, checked against ``told`` (:func:`check_plant`)."""
    from im_drive_sim.drive_file import load_config

    if name is None:
        base = told
    else:
        overrides: dict[str, str] = {'model': model}
        if realism is not None:
            overrides['realism'] = realism
        try:
            base = load_config(name, overrides=overrides)
        except ConfigError as exc:
            raise PlantError(f'--plant: {exc}') from None
    plant = apply_mismatch(base, mm)
    what = ('--plant ' + name if name is not None else 'the plant') + (
        f' with {mismatch_text(mm)}' if mm else ''
    )
    check_plant(told, plant, what)
    return plant


def told_name(spec: StudySpec) -> str:
    """The drive the tuner is told: the (one) drive of ``spec``, its drive file, or the
    packaged default."""
    from ..family import DEFAULT_DRIVE  # (light: the family module imports no numba)

    return spec.drives[0] if spec.drives else spec.drive_config or DEFAULT_DRIVE


def plant_name(spec: StudySpec) -> str:
    """The plant: ``--plant``'s drive, else the told drive's, with its mismatch."""
    name = spec.plant[0] if spec.plant else told_name(spec)
    return f'{name} with {mismatch_text(spec.mismatch)}' if spec.mismatch else name


def plants_line(drives: list[tuple[str, StudySpec]]) -> str | None:
    """The header line of a family whose plants are not the told drives (each drive's
    name and study spec), None otherwise."""
    split = [(n, sp) for n, sp in drives if sp.plant or sp.mismatch]
    if not split:
        return None
    return (
        'the plant is not the drive the tuner is told: '
        + '; '.join(f'told {n}, plant {plant_name(sp)}' for n, sp in split)
        + " (each drive's losses normalised by its hand-tuned start on the plant)"
    )


def plant_line(spec: StudySpec, l_ref: float, l_ref_told: float | None) -> str | None:
    """The header line of a study whose plant is not the told drive, None otherwise:
    ``plant: im7500w-j10 with J x1.5, ...; the tuner told im7500w-j10 (...)``."""
    if not spec.plant and not spec.mismatch:
        return None
    text = (
        f'plant: {plant_name(spec)}; the tuner told {told_name(spec)} (its experiment, '
        'search box, start and model for the first step); L_ref is the hand-tuned start on '
        'the plant'
    )
    if l_ref_told is not None and l_ref_told > 0.0:
        text += f', {l_ref / l_ref_told:.3f} x its {l_ref_told:.5f} on the told drive'
    return text
