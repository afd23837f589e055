"""A study worker process's set-up: light, so that it runs before the heavy imports.

A local pool worker unpickles its initializer before its first task: with the
initializer here (not in ``runs``, which imports the optimisers and the numba kernels),
the worker watches the study process from its first fraction of a second, while the
heavy modules are still loading.
"""

from __future__ import annotations

import os
import select
import signal
import threading
import time
from typing import TYPE_CHECKING, Any

from .spec import StudySpec

if TYPE_CHECKING:
    from im_controller.config import ExperimentConfig
    from im_drive_sim.params import DriveConfig

    from ..space import TunerParams

#: This process's study: its spec and its loaded drive and tuner parameter files.
WORKER: dict[str, Any] = {}
#: A Dask worker may run several tasks at once, in threads: one loads, the others wait.
_LOCK = threading.Lock()
#: Without pidfd (not Linux): how often a worker checks that the study lives [s].
WATCH_POLL_S = 0.5


def init_worker(spec: StudySpec) -> tuple[DriveConfig, TunerParams, ExperimentConfig]:
    """(drive, tuner parameters, experiment) of ``spec``: the files are loaded once per
    process and spec (thread-safe: a Dask worker may run several tasks at once)."""
    with _LOCK:
        if WORKER.get('spec') != spec:
            drive, params, experiment = spec.loaded()
            WORKER.update(drive=drive, params=params, experiment=experiment, spec=spec)
        return WORKER['drive'], WORKER['params'], WORKER['experiment']


def init_pool_worker(spec: StudySpec, study_pid: int) -> None:
    """Initializer of a local pool worker: it ends with the study process, however that
    ends, and leaves Ctrl-C to it.

    The workers are the forkserver's children, not the study's, and each holds the
    forkserver's "alive" pipe open: a killed study goes unnoticed by both, so each worker
    watches the study process itself.  SIGINT is ignored: Ctrl-C reaches the whole
    process group, and the study ends its workers itself (``runs._end_pool``)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    watch_study(study_pid)
    init_worker(spec)


def watch_study(pid: int) -> None:
    """End this process (``os._exit(1)``) as soon as process ``pid`` ends: a thread waits
    on a pidfd (Linux >= 5.3: readable the moment the process exits, zombie or not), or
    else polls every ``WATCH_POLL_S``."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        os._exit(1)  # the study is already gone
    except (AttributeError, OSError):  # no pidfd here
        fd = -1

    def watch() -> None:
        if fd >= 0:
            select.select([fd], [], [])
        else:
            while True:
                time.sleep(WATCH_POLL_S)
                try:
                    os.kill(pid, 0)
                except ProcessLookupError:
                    break
                except PermissionError:  # alive, another user's (cannot be the study)
                    pass
        os._exit(1)  # nothing to keep: the study, gone, wanted this worker's results

    threading.Thread(target=watch, name='study-watch', daemon=True).start()
