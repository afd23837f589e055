"""``ros2 run im_tuner replay``: re-drive a live controller from a recorded bag (docs/replay.md).

``plan`` (pure) reads the bag and decides what to feed and compare; ``node`` (rclpy) runs
the controller and plays the drive's side; ``replay_main`` is the command.
"""
