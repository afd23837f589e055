"""Foxglove layouts shipped with im_tuner (docs/foxglove.md): defined once from the contracts
with Foxglove's SDK (:mod:`.layouts`); ``python -m im_tuner.foxglove`` prints where the
installed ones are or writes them afresh (:mod:`.cli`). Pure: no rclpy."""
