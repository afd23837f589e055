"""The run directory of a tuning run: what it holds and how it is written safely.

Pure (no rclpy).  Layout (docs/tuner.md)::

    RUN/
      run.yaml          what ran: algorithm and options, seeds, budget, search box, bench,
                        drive and controller configuration, command, versions
      results.jsonl     one JSON line per experiment (reference, evaluations, re-measurements):
                        parameters, loss and terms, status, timings -- appended and fsync'ed
                        as each experiment ends, so a killed run keeps every finished one
      checkpoint.json   optimiser and tuner state after the last line (atomic replace)
      summary.json      written at the end of every session (also of an interrupted one)
      bag_0/, bag_1/ .. the MCAP log (rosbag2 directory) of each session (resumes add one)

Atomic writes: temp file in the same directory, fsync, rename, fsync the directory.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import yaml

__all__ = ['RunDirError', 'RunDir', 'atomic_write_text', 'RUN_FILE', 'RESULTS_FILE',
           'CHECKPOINT_FILE', 'SUMMARY_FILE']

RUN_FILE = 'run.yaml'
RESULTS_FILE = 'results.jsonl'
CHECKPOINT_FILE = 'checkpoint.json'
SUMMARY_FILE = 'summary.json'


class RunDirError(Exception):
    """The directory cannot be used as (or is not) a run directory; message says why."""


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_text(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` atomically (temp, fsync, rename, fsync dir)."""
    path = Path(path)
    tmp = path.with_name(f'.{path.name}.tmp')
    with open(tmp, 'w') as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


class RunDir:
    """A run directory (see the module docstring)."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)

    # -- creation / opening ------------------------------------------------------------
    @classmethod
    def create(cls, path: Path | str) -> 'RunDir':
        """Create a new run directory; refuses anything that already holds files."""
        p = Path(path)
        if p.exists():
            if not p.is_dir():
                raise RunDirError(f'--out {p}: exists and is not a directory')
            if any(p.iterdir()):
                what = 'a tuning run; continue it with --resume' if (p / RUN_FILE).exists() \
                    else 'not empty'
                raise RunDirError(f'--out {p}: already exists ({what}); choose a new directory')
        parent = p.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
            raise RunDirError(f'--out {p}: cannot create it ({parent} is not a writable '
                              'directory)')
        try:
            p.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RunDirError(f'--out {p}: cannot create it ({exc.strerror or exc})') from None
        if not os.access(p, os.W_OK | os.X_OK):
            raise RunDirError(f'--out {p}: directory is not writable')
        return cls(p)

    @classmethod
    def open(cls, path: Path | str) -> 'RunDir':
        """An existing run directory (for --resume and the report)."""
        p = Path(path)
        if not p.is_dir():
            raise RunDirError(f'{p}: not a directory')
        if not (p / RUN_FILE).is_file():
            raise RunDirError(f'{p}: not a tuning run (no {RUN_FILE})')
        return cls(p)

    # -- run.yaml ------------------------------------------------------------------------
    def write_run(self, run: dict[str, Any]) -> None:
        atomic_write_text(self.path / RUN_FILE,
                          '# im_tuner run: what ran (see docs/tuner.md)\n'
                          + yaml.safe_dump(run, sort_keys=False, default_flow_style=None,
                                           width=100))

    def read_run(self) -> dict[str, Any]:
        try:
            data = yaml.safe_load((self.path / RUN_FILE).read_text())
        except (OSError, yaml.YAMLError) as exc:
            raise RunDirError(f'{self.path / RUN_FILE}: unreadable ({exc})') from None
        if not isinstance(data, dict) or 'algo' not in data:
            raise RunDirError(f'{self.path / RUN_FILE}: not a tuner run file')
        return data

    # -- results.jsonl -------------------------------------------------------------------
    def append_result(self, record: dict[str, Any]) -> None:
        """Append one record as a JSON line and fsync (floats round-trip exactly)."""
        line = json.dumps(record, allow_nan=False, separators=(',', ':')) + '\n'
        with open(self.path / RESULTS_FILE, 'a') as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())

    def read_results(self, repair: bool = False) -> list[dict[str, Any]]:
        """Every complete record.  A torn last line (a kill while writing) is ignored, and
        cut off when ``repair``; a bad line elsewhere is an error."""
        path = self.path / RESULTS_FILE
        if not path.exists():
            return []
        raw = path.read_bytes()
        # Each record is written as one line ending in a newline: bytes after the last
        # newline are a record written only in part (the process died mid-write).
        end = raw.rfind(b'\n') + 1
        out: list[dict[str, Any]] = []
        for i, line in enumerate(raw[:end].split(b'\n')[:-1]):
            try:
                rec = json.loads(line)
            except ValueError:
                rec = None
            if not isinstance(rec, dict):
                raise RunDirError(f'{path}: line {i + 1} is not a JSON record')
            out.append(rec)
        if repair and end < len(raw):
            with open(path, 'r+b') as f:
                f.truncate(end)
                os.fsync(f.fileno())
        return out

    # -- checkpoint / summary ------------------------------------------------------------
    def write_checkpoint(self, state: dict[str, Any]) -> None:
        # allow_nan: an option may be +inf (SPSA max_step=inf: no cap); Python reads it back
        atomic_write_text(self.path / CHECKPOINT_FILE,
                          json.dumps(state, separators=(',', ':')))

    def read_checkpoint(self) -> dict[str, Any] | None:
        path = self.path / CHECKPOINT_FILE
        if not path.exists():
            return None
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise RunDirError(f'{path}: unreadable ({exc})') from None

    def write_summary(self, summary: dict[str, Any]) -> None:
        atomic_write_text(self.path / SUMMARY_FILE, json.dumps(summary, indent=2,
                                                                allow_nan=False) + '\n')

    def bag_dirs(self) -> list[Path]:
        """The session bags, in order (bag_0, bag_1, ...)."""
        bags = [p for p in self.path.glob('bag_*') if p.is_dir() and p.name[4:].isdigit()]
        return sorted(bags, key=lambda p: int(p.name[4:]))

    def next_bag_dir(self) -> Path:
        bags = self.bag_dirs()
        return self.path / f'bag_{int(bags[-1].name[4:]) + 1 if bags else 0}'
