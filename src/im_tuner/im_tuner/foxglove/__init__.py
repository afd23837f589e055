"""Foxglove layouts shipped with im_tuner (docs/foxglove.md).

The layouts are defined once with Foxglove's SDK (``foxglove.layouts``;
:func:`.layouts.definitions` gives the SDK's objects). ``python -m im_tuner.foxglove``
prints where the installed layouts are (``share/im_tuner/foxglove/<name>.json``); ``--out
DIR`` writes them afresh from the contracts (``--namespace /bench1`` for a bench under a
namespace, ``--sdk`` for the SDK's own form). ``make foxglove-layouts`` regenerates the
committed copies in ``src/im_tuner/foxglove/``. Pure: no rclpy.
"""
