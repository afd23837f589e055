"""Reading a drive file: the YAML, a packaged drive's name, and ``base:`` inheritance.

Pure (no rclpy). ``load_config`` reads a drive file here; the dataclasses, the validation and
the realism profiles stay in ``params``.  A drive file may start with ``base: <drive>``:

* a packaged drive's name (``paper_750w``, ``im3700w-j3``, ... ``family.PACKAGED_NAMES``;
  a packaged drive's own base, its motor's file, comes with it), or
* a path (``sub/motor.yaml``, ``../motors/m.yaml``, or absolute) resolved relative to the
  folder of the file that names it, not to the working directory.

One level: a user's base has no base of its own (a packaged drive may).  Every problem is
one ``ConfigError`` line naming the file.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

from . import family
from .params import ConfigError, DriveConfig, config_from_dict, default_config_path
from .yaml_file import YamlFileError, read_yaml


def load_config(
    path: str | Path | None = None, overrides: Mapping[str, Any] | None = None
) -> DriveConfig:
    """Load and validate a drive configuration.

    path: YAML file, or the name of a packaged drive (``family.PACKAGED_NAMES``: a motor's
    file such as ``paper_750w`` or a drive such as ``im3700w-j3``; a name is taken only
    when no such file exists); ``None`` loads the packaged default (``default_config_path()``).
    overrides: partial nested (``{"machine": {"J": 1.0}}``) or dotted (``{"machine.J": 1.0}``)
    values merged onto the file before validation.
    Raises ``ConfigError`` (a ``ValueError``) naming the file and the key path; a bare name
    that is neither a file nor a packaged drive is refused in one line naming the drives.
    """
    p = default_config_path() if path is None else _drive_path(path)
    name = p.name
    data = _read(name, p)
    if isinstance(data, Mapping) and 'base' in data:
        data = _with_base(name, p, data)
    src = name if not overrides else f'{name} (with overrides)'
    return replace(config_from_dict(data, source=src, overrides=overrides), path=str(p.resolve()))


def _read(name: str, p: Path) -> Any:
    """The YAML document of the drive file ``p`` (``name``: how errors call it)."""
    try:
        data, text = read_yaml(p)
    except YamlFileError as exc:  # a file that is not there: named by where it was looked for
        raise ConfigError(f'{name if p.is_file() else p}: {exc}') from None
    if data is None:  # an empty file, only comments, or a bare null: no settings at all
        content = [ln.strip() for ln in text.splitlines() if ln.strip()]
        if not content:
            what = 'the file is empty'
        elif all(ln.startswith('#') or ln in ('---', '...') for ln in content):
            what = 'the file holds only comments'
        else:
            what = 'the YAML document is null'
        raise ConfigError(
            f'{name}: no settings ({what}); a drive file is a mapping, e.g. '
            "'base: paper_750w' and the values you know (docs/real-drive.md)"
        )
    return data


def _drive_path(path: str | Path) -> Path:
    """The file ``path`` names: the file itself, else the packaged drive of that name."""
    p = Path(path)
    if p.exists():
        return p
    packaged = family.packaged_path(str(path))
    if packaged is not None:
        return packaged
    if p.suffix == '' and p.name == str(path):  # a bare name: a drive's, mistyped
        raise ConfigError(family.unknown_drive_message(str(path)))
    return p


def _packaged_file(base: str) -> Path | None:
    """The packaged file ``base`` names (``im7500w-j3`` or ``im7500w-j3.yaml``), else None.
    A name with a folder in it is a path, never a packaged drive."""
    if '/' in base or '\\' in base:
        return None
    p = family.packaged_path(base.removesuffix('.yaml'))
    return p if p is not None and p.is_file() else None


def _with_base(name: str, path: Path, data: Mapping[str, Any]) -> dict[str, Any]:
    """A drive file with ``base: <file>``: that file's values, with this file's on top.

    A real drive's file needs only what the controller reads (``Ts``, ``machine.isq_max``)
    and what is really known; ``base`` gives the rest (module docstring)."""
    base = data['base']
    if not isinstance(base, str) or not base.strip():
        raise ConfigError(f'{name}: base must be a file name, got {base!r}')
    # a packaged drive's file, else relative to this file's folder (an absolute path as it is)
    packaged = _packaged_file(base)
    bp = packaged if packaged is not None else path.parent / base
    if not bp.is_file():
        raise ConfigError(
            f'{name}: base {base!r}: cannot read {bp} (no such file; a packaged drive '
            f"or a path relative to {name}'s folder)"
        )
    try:
        bdata, _ = read_yaml(bp)
    except YamlFileError as exc:
        raise ConfigError(f'{name}: base {base!r}: {bp}: {exc}') from None
    if isinstance(bdata, Mapping) and 'base' in bdata and packaged is not None:
        bdata = _with_base(bp.name, bp, bdata)  # a packaged drive: its motor's file under it
    if not isinstance(bdata, Mapping) or 'base' in bdata:
        raise ConfigError(f'{name}: base {base!r}: not a complete drive file (or has a base)')
    merged = {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in bdata.items()}
    for k, v in data.items():
        if k == 'base':
            continue
        if isinstance(v, Mapping) and isinstance(merged.get(k), dict):
            merged[k].update(v)
        else:
            merged[k] = v
    return merged


def packaged_base(path: str | Path | None) -> str | None:
    """The packaged drive a drive file stands on: ``path`` itself when it is a packaged
    drive's name (None: the default ``paper_750w``), else the packaged name of its
    ``base:`` (``im7500w-j3`` for a user's ``base: im7500w-j3``); None for a file without a
    base, on a base of its own, or that cannot be read (``load_config`` says why)."""
    if path is None:
        return family.MOTOR_FILES[0]
    if str(path) in family.PACKAGED_NAMES and not Path(path).exists():
        return str(path)
    try:
        p = _drive_path(path)
        data = _read(p.name, p)
    except ConfigError:  # (not a drive file: load_config says why, to whoever loads it)
        return None
    base = data.get('base') if isinstance(data, Mapping) else None
    if not isinstance(base, str) or _packaged_file(base) is None:
        return None
    return base.removesuffix('.yaml')  # (a packaged file: a packaged name)
