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


#: the lazy public names and the module each comes from
_LAZY = {
    'ConfigError': 'params',
    'DriveConfig': 'params',
    'default_config_path': 'params',
    'load_config': 'drive_file',
    'DriveSim': 'sim',
    'STATE_FIELDS': 'sim',
}


def __getattr__(name: str) -> Any:
    # Lazy re-exports keep `import im_drive_sim` cheap (no numba import) for tools.
    if name not in _LAZY:
        raise AttributeError(f"module 'im_drive_sim' has no attribute {name!r}")
    from importlib import import_module

    return getattr(import_module(f'.{_LAZY[name]}', __name__), name)
