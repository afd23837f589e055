"""A study over several drives (``study --drives A,B``): one study per drive, each in a
directory of its own under the output directory, and ``family.json`` naming them.

Each drive's study is an ordinary study (``StudySpec.for_drive``: its drive, experiment
and tuner parameters from ``im_tuner.family.drive_setup``; its L_ref from 100
experiments of its own hand-tuned start; the same run seeds for every drive: common
random numbers across drives too).  Light at import (json and ``results``), so that
``study --from DIR`` tells a family directory from a single study at once.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ..rundir import atomic_write_text
from .results import StudyResult, load, save
from .spec import StudySpec

FAMILY_FILE = 'family.json'


@dataclass
class FamilyResult:
    """The studies of several drives, in the order given."""

    spec: StudySpec  #: the family's spec (``drives``: every drive)
    results: list[StudyResult]  #: one per drive, ``results[i].spec.drives == (drives[i],)``
    command: str = ''

    @property
    def names(self) -> list[str]:
        return list(self.spec.drives)


def drive_dirs(drives: tuple[str, ...]) -> list[str]:
    """A directory name per drive: the packaged name, or a drive file's stem (with a
    number when two files share a stem)."""
    out: list[str] = []
    for d in drives:
        base = Path(d).stem if (d.endswith(('.yaml', '.yml')) or '/' in d) else d
        name, k = base, 2
        while name in out:
            name, k = f'{base}_{k}', k + 1
        out.append(name)
    return out


def is_family(out: Path | str) -> bool:
    return (Path(out) / FAMILY_FILE).is_file()


def save_family(fam: FamilyResult, out: Path | str) -> list[Path]:
    """Each drive's study into ``out/<drive dir>/`` (``results.save``), then
    ``family.json``; the drive directories in order."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    dirs = [out / d for d in drive_dirs(fam.spec.drives)]
    for res, d in zip(fam.results, dirs, strict=True):
        res.command = fam.command
        save(res, d)
    meta = {'drives': list(fam.spec.drives), 'dirs': [d.name for d in dirs], 'command': fam.command}
    atomic_write_text(out / FAMILY_FILE, json.dumps(meta, indent=1) + '\n')
    return dirs


def load_family(out: Path | str) -> tuple[FamilyResult, list[Path]]:
    """Read a family written by :func:`save_family` (ValueError with the reason if it is
    not one); the drive directories beside it."""
    out = Path(out)
    try:
        meta = json.loads((out / FAMILY_FILE).read_text())
        drives, names = tuple(meta['drives']), list(meta['dirs'])
        command = str(meta.get('command', ''))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f'{out}: unreadable {FAMILY_FILE} ({exc!r:.100})') from None
    dirs = [out / n for n in names]
    results = [load(d) for d in dirs]
    if len(results) != len(drives) or not results:
        raise ValueError(f'{out}: {FAMILY_FILE} names {len(drives)} drives, {len(results)} dirs')
    import dataclasses

    # each drive's study holds its own plant (StudySpec.for_drive): the family's, one per drive
    plant = tuple(r.spec.plant[0] for r in results) if results[0].spec.plant else ()
    spec = dataclasses.replace(results[0].spec, drives=drives, plant=plant)
    return FamilyResult(spec, results, command), dirs
