"""The benches the tuner runs on: in-process lock-step (``InProcessBench``), the same
nodes as child processes, or an external bench on the graph (``sim_bench`` is the CLI)."""

from .inprocess import InProcessBench, bench_metadata

__all__ = ['InProcessBench', 'bench_metadata']
