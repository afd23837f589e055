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

**Drives**: a study's drive, experiment and tuner parameters come from
``im_tuner.family.drive_setup``; ``--drives A,B`` runs one study per drive (``drives``) at
each algorithm's recommended configuration plus Py-BOBYQA (``bobyqa``), summed up over the
drives (``summary``). ``--plant`` makes the bench another drive than the told one (``plant``).

Modules by job: ``spec`` (the grid and the spec; light: the command checks its options
with it alone), ``plant`` (the plant apart from the told drive; light), ``results``
(StudyResult, study.npz/study.json), ``runs`` (one run = a TuningRun on the offline
bench, the pool), ``bobyqa`` (Py-BOBYQA one evaluation at a time), ``drives`` (a study
per drive, family.json), ``cluster`` (the Dask scheduler checked), ``stats`` (intervals,
Tables I-III, the paper's values), ``summary`` (over drives), ``text``, ``files`` (CSV,
tuner commands), ``figures``, ``markdown`` (reproduction.md, beside.md, family.md),
``cli``.

This package imports nothing itself, so that ``python -m im_tuner.study`` with a bad
option refuses at once.
"""
