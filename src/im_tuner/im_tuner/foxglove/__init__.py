"""Foxglove layouts shipped with im_tuner (docs/foxglove.md).

``python -m im_tuner.foxglove`` prints where the installed layouts are
(``share/im_tuner/foxglove/<name>.json``); ``--out DIR`` writes them afresh from the
contracts (``--namespace /bench1`` for a bench under a namespace). ``make
foxglove-layouts`` regenerates the committed copies in ``src/im_tuner/foxglove/``. Pure:
no rclpy.
"""

from .layouts import LAYOUTS, array_path, build, loss_path, render
from .signals import ARRAY_TOPICS, Signal, label, loss_signals, signal

__all__ = [
    'ARRAY_TOPICS',
    'LAYOUTS',
    'Signal',
    'array_path',
    'build',
    'label',
    'loss_path',
    'loss_signals',
    'render',
    'signal',
]
