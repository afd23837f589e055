"""The offline configuration study of the paper (Tables I-III), in simulation, no ROS.

The grid (spec.py, docs/reproduction.md): SPSA over (a, c), neCGA over n; ``runs`` runs of
``budget`` loss evaluations per configuration, in-process on the nodes' numba kernels
(``im_tuner.offline``), in a process pool.

**A study run is a tuner run**, by construction: the tuner's own ``TuningRun`` on the
offline bench (``offline.OfflineBench``), its records kept in memory
(``runlog.MemoryRecord``).  Run r of every configuration uses the run seed ``run_seed(seed,
r)`` and does exactly what ``ros2 run im_tuner tuner --seed <run seed> --remeasure 1`` does
on the simulated lock-step bench.  The seeds are shared by all configurations (common
random numbers), and runs are independent, so the results are identical for any number of
workers.

The statistics (normalised loss, satisfactory runs, intervals): docs/reproduction.md.

This package imports nothing itself, so that ``python -m im_tuner.study`` with a bad
option refuses at once.
"""
