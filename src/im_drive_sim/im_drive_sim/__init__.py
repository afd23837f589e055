"""Induction-motor drive simulator core (pure Python + numba, no ROS imports).

Model, control, measurement and API are documented in docs/drive-model.md.
Heavy modules (numba kernels) are imported lazily on first attribute access.

Importing this package first sets the project's numeric baseline (:mod:`.numeric`: numpy's
and OpenBLAS's dispatch held at x86-64-v3, so that a run gives the same bits on every
x86-64 CPU) -- before numpy is imported, which is why every package of the project
imports this one first.
"""

from __future__ import annotations

from typing import Any

from . import numeric as _numeric

_numeric.apply()

__version__ = '0.1.0'

__all__ = [
    'STATE_FIELDS',
    'ConfigError',
    'DriveConfig',
    'DriveSim',
    '__version__',
    'default_config_path',
    'load_config',
]


def __getattr__(name: str) -> Any:
    # Lazy re-exports keep `import im_drive_sim` cheap (no numba import) for tools.
    if name in ('ConfigError', 'DriveConfig', 'load_config', 'default_config_path'):
        from . import params

        return getattr(params, name)
    if name in ('DriveSim', 'STATE_FIELDS'):
        from . import sim

        return getattr(sim, name)
    raise AttributeError(f"module 'im_drive_sim' has no attribute {name!r}")
