"""The benches the tuner runs on (docs/architecture.md names the modules).

``InProcessBench`` and ``bench_metadata`` are imported on first use, so the offline bench
(study workers) does not load rclpy.
"""

from __future__ import annotations

from typing import Any

__all__ = ['InProcessBench', 'bench_metadata']


def __getattr__(name: str) -> Any:
    if name in __all__:
        from . import inprocess

        return getattr(inprocess, name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
