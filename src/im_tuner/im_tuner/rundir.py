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
What the files hold -- typed records, run config, summary, their exact text and format
versions -- is the run log's (:mod:`im_tuner.runlog`); this module reads and writes them
only through it.

One tuner per run directory: :meth:`RunDir.lock` takes an exclusive ``flock`` on the
directory itself (no lock file to create or leave behind; the kernel drops it when the
process ends, however it ends). A second tuner is refused naming the holder's PID and
command line (from ``/proc/locks``); :meth:`RunDir.holder` tells a reader (``report``)
that the run is live.
"""

from __future__ import annotations

import fcntl
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .runlog.files import FileError, RunConfig, Summary, VersionError
from .runlog.records import Record, RecordError, parse_results

RUN_FILE = 'run.yaml'
RESULTS_FILE = 'results.jsonl'
CHECKPOINT_FILE = 'checkpoint.json'
SUMMARY_FILE = 'summary.json'


def is_bag_dir(path: Path) -> bool:
    """``path`` is a directory holding a bag: its ``metadata.yaml`` or an MCAP file (a
    closed, a repaired, or a still-recording one)."""
    return path.is_dir() and ((path / 'metadata.yaml').is_file() or any(path.glob('*.mcap')))


def made_by_create(out: Path) -> tuple[Path, bool]:
    """What creating ``out`` makes: its topmost missing directory (itself or a parent) and
    True; or ``out`` itself if it exists, and False (only its contents will be new)."""
    if out.exists():
        return out, False
    made = out
    while not made.parent.exists() and made.parent != made.parent.parent:
        made = made.parent
    return made, True


def check_creatable(out: Path, error: type[Exception]) -> None:
    """Refuse (``error``) an ``--out`` that does not exist and cannot be made, before any
    work: made and removed again, so a refusal or a later failure leaves nothing (a
    writable-looking parent may still refuse, as /proc does even root)."""
    if out.exists():
        return
    made = made_by_create(out)[0]
    try:
        out.mkdir(parents=True)
    except OSError as exc:
        raise error(f'--out {out}: cannot create it ({exc.strerror or exc})') from None
    for d in (out, *out.parents):  # what mkdir made, innermost first
        d.rmdir()
        if d == made:
            break


def claim_out_dir(out: Path, error: type[Exception], what_is_there: Callable[[Path], str]) -> Path:
    """Make ``out`` (``--out``) for a new run or bag: refuse a file, a directory that holds
    anything (``what_is_there(out)`` says what), an unwritable place. An existing *empty*
    writable directory is taken. Nothing is created when this raises ``error``."""
    if out.exists():
        if not out.is_dir():
            raise error(f'--out {out}: exists and is not a directory')
        if any(out.iterdir()):
            what = what_is_there(out)
            raise error(f'--out {out}: already exists ({what}); choose a new directory')
        if not os.access(out, os.W_OK | os.X_OK):
            raise error(f'--out {out}: directory is not writable')
        return out
    parent = made_by_create(out)[0].parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise error(f'--out {out}: cannot create it ({parent} is not a writable directory)')
    try:
        out.mkdir(parents=True)
    except OSError as exc:
        raise error(f'--out {out}: cannot create it ({exc.strerror or exc})') from None
    return out


class RunDirError(Exception):
    """The directory cannot be used as (or is not) a run directory; message says why."""


def atomic_write_text(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` atomically (temp, fsync, rename, fsync dir)."""
    path = Path(path)
    tmp = path.with_name(f'.{path.name}.tmp')
    with open(tmp, 'w') as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _lock_holder(path: Path) -> str | None:
    """'pid N (command line)' of the process holding a flock on ``path`` (Linux)."""
    try:
        ino = os.stat(path).st_ino
        lines = Path('/proc/locks').read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        f = line.split()
        # "1: FLOCK  ADVISORY  WRITE 12345 08:01:1234567 0 EOF" (may carry a "->" marker)
        if '->' in f:
            continue
        if len(f) >= 6 and f[1] == 'FLOCK' and f[5].rsplit(':', 1)[-1] == str(ino):
            pid = f[4]
            try:
                cmd = Path(f'/proc/{pid}/cmdline').read_bytes().replace(b'\0', b' ')
                cmd_text = ' '.join(cmd.decode(errors='replace').split())
            except OSError:
                cmd_text = ''
            return f'pid {pid}' + (f' ({cmd_text[:160]})' if cmd_text else '')
    return None


def writer_of(path: Path) -> str | None:
    """Who holds an exclusive ``flock`` on ``path`` now ('pid N (command line)'), or None.
    A tuner holds one on its run directory (:meth:`RunDir.holder`), the MCAP writer
    (``record.writer.McapWriter``) one on its file until it closes it; the kernel drops
    them when the process ends, however, so a bag being recorded is told from one a
    killed recorder left."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return _lock_holder(path) or 'another process'
    finally:
        os.close(fd)  # also drops the shared lock taken to test
    return None


class RunDir:
    """A run directory (see the module docstring)."""

    durable = True  #: records fsync'ed and checkpoints written (a run can be resumed)

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self._lock_fd: int | None = None

    # -- one writer at a time --------------------------------------------------------------
    def lock(self) -> None:
        """Take the run for this process; :class:`RunDirError` naming the other process
        if one has it (a live tuner)."""
        if self._lock_fd is not None:
            return
        fd = os.open(self.path, os.O_RDONLY | os.O_DIRECTORY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise RunDirError(
                f'{self.path}: in use by {self.holder() or "another process"}; '
                'wait for it to end (or stop it with Ctrl-C) first'
            ) from None
        self._lock_fd = fd

    def unlock(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # closing the descriptor drops the flock
            self._lock_fd = None

    def holder(self) -> str | None:
        """Who holds the run ('pid N (command line)'), or None if nobody does."""
        if self._lock_fd is not None:
            return f'pid {os.getpid()} (this process)'
        return writer_of(self.path)  # (a directory's flock is tested as a file's)

    # -- creation / opening ------------------------------------------------------------
    @classmethod
    def create(cls, path: Path | str) -> RunDir:
        """Create a new run directory; refuses anything that already holds files."""
        p = claim_out_dir(
            Path(path),
            RunDirError,
            lambda d: (
                'a tuning run; continue it with --resume'
                if (d / RUN_FILE).exists()
                else 'not empty'
            ),
        )
        return cls(p)

    @classmethod
    def open(cls, path: Path | str) -> RunDir:
        """An existing run directory (for --resume and the report)."""
        p = Path(path)
        if not p.is_dir():
            raise RunDirError(f'{p}: not a directory')
        if not (p / RUN_FILE).is_file():
            hint = f'; a bag: its run is {p.parent}, its statistics `report --bag-info {p}`'
            raise RunDirError(
                f'{p}: not a tuning run (no {RUN_FILE}){hint if is_bag_dir(p) else ""}'
            )
        return cls(p)

    # -- run.yaml ------------------------------------------------------------------------
    def write_run(self, run: RunConfig) -> None:
        """Write run.yaml (its keys in their order: :meth:`RunConfig.to_text`)."""
        atomic_write_text(self.path / RUN_FILE, run.to_text())

    def read_config(self) -> RunConfig:
        """run.yaml as read (:class:`RunDirError` if it is not a run file)."""
        path = self.path / RUN_FILE
        try:
            return RunConfig.from_text(path.read_text(encoding='utf-8'))
        except (OSError, UnicodeDecodeError) as exc:
            raise RunDirError(f'{path}: unreadable ({exc})') from None
        except FileError as exc:
            raise RunDirError(f'{path}: {exc}') from None

    # -- results.jsonl -------------------------------------------------------------------
    def append_result(self, record: Record) -> None:
        """Append one record as a JSON line and fsync (floats round-trip exactly)."""
        with open(self.path / RESULTS_FILE, 'a') as f:
            f.write(record.to_json() + '\n')
            f.flush()
            os.fsync(f.fileno())

    def read_results(self, repair: bool = False) -> list[Record]:
        """Every complete record, each checked (``runlog.records.check_record``).  A torn last line
        (a kill while writing) is ignored, and cut off when ``repair`` -- only once every
        record is accepted, so a refusal changes nothing; a bad line elsewhere is an
        error (:class:`RunDirError` naming the line)."""
        path = self.path / RESULTS_FILE
        if not path.exists():
            return []
        try:
            raw = path.read_bytes()
        except OSError as exc:
            raise RunDirError(f'{path}: unreadable ({exc.strerror or exc})') from None
        try:
            out = parse_results(raw)[0]
        except RecordError as exc:
            raise RunDirError(f'{path}: {exc}') from None
        if repair:
            self.cut_torn_tail()
        return out

    def cut_torn_tail(self) -> int:
        """Cut a torn last line off results.jsonl (bytes after the last newline, left by a
        kill mid-write) before anything is appended; returns the bytes cut."""
        path = self.path / RESULTS_FILE
        if not path.exists():
            return 0
        raw = path.read_bytes()
        end = raw.rfind(b'\n') + 1
        if end == len(raw):
            return 0
        with open(path, 'r+b') as f:
            f.truncate(end)
            os.fsync(f.fileno())
        return len(raw) - end

    # -- checkpoint / summary ------------------------------------------------------------
    def write_checkpoint(self, state: dict[str, Any]) -> None:
        # allow_nan: an option may be +inf (SPSA max_step=inf: no cap); Python reads it back
        atomic_write_text(self.path / CHECKPOINT_FILE, json.dumps(state, separators=(',', ':')))

    def read_checkpoint(self) -> dict[str, Any] | None:
        """The checkpoint, or None if there is none; :class:`RunDirError` if it cannot be
        read or is not a checkpoint (the caller may rebuild it from results.jsonl)."""
        path = self.path / CHECKPOINT_FILE
        if not path.exists():
            return None
        try:
            data = json.loads(path.read_bytes())
        except OSError as exc:
            raise RunDirError(f'{path}: unreadable ({exc.strerror or exc})') from None
        except ValueError:
            raise RunDirError(f'{path}: not JSON (empty, truncated or corrupt)') from None
        if (
            not isinstance(data, dict)
            or not isinstance(data.get('records'), int)
            or not isinstance(data.get('optimizer'), dict)
            or not isinstance(data.get('tuner'), dict)
        ):
            raise RunDirError(f'{path}: not a tuner checkpoint')
        return data

    def write_summary(self, summary: Summary) -> None:
        """Write summary.json (its keys in their order: :meth:`Summary.to_text`)."""
        atomic_write_text(self.path / SUMMARY_FILE, summary.to_text())

    def read_summary(self) -> Summary | None:
        """summary.json, or None if there is none or it is not one (a killed session
        leaves none; the records are the truth); :class:`RunDirError` for one of a format
        version this im_tuner does not read (a newer tuner's: not a killed session's)."""
        path = self.path / SUMMARY_FILE
        try:
            return Summary.from_text(path.read_bytes())
        except VersionError as exc:
            raise RunDirError(f'{path}: {exc}') from None
        except (OSError, FileError):
            return None

    def bag_dirs(self) -> list[Path]:
        """The session bags, in order (bag_0, bag_1, ...)."""
        bags = [p for p in self.path.glob('bag_*') if p.is_dir() and p.name[4:].isdigit()]
        return sorted(bags, key=lambda p: int(p.name[4:]))

    def next_bag_dir(self) -> Path:
        bags = self.bag_dirs()
        return self.path / f'bag_{int(bags[-1].name[4:]) + 1 if bags else 0}'
