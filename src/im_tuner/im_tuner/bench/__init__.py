"""The benches the tuner runs on.

* ``offline``: the controller's kernel fused with the drive's in one numba loop (no ROS);
  the study's engine and the oracle of the ROS tests;
* ``inprocess``: the drive simulator and controller nodes in one process, lock-step, with
  the recorder polled between steps (the tuner's default);
* ``realtime``: a drive and the controller composed in one process, one wall-clock loop
  (``compiled_loop``: its periods compiled, over the numba kernels of ``loop_kernels``;
  ``loop_routes``: its publishers through an outbox);
* ``spec`` (which bench, built how; pure), ``open`` (``open_bench``: the one builder of
  every form), ``forms`` (the benches behind one protocol), ``drive_spec`` (``--drive``),
  ``drive_status`` (the drive's counters for the summary);
* ``sim_bench``: the command line (``ros2 run im_tuner sim_bench [--processes]``), opened
  by ``open_bench`` as the tuner's bench is.

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
