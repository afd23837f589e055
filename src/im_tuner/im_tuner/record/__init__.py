"""Recording: every topic of the bench into an MCAP bag that rosbag2, rosbags, the mcap
library and Foxglove open.

* ``node``: the recorder node (``ros2 run im_tuner recorder``) and ``Recorder``, which the
  in-process bench polls between steps;
* ``take``: takes serialized messages from the subscriptions' queues (numba over rcl);
* ``writer``: the MCAP writer (chunks compressed and written on a background thread);
* ``schemas``: message and service definitions for the MCAP schemas, from the installed
  packages; ``metadata``: rosbag2's metadata.yaml;
* ``records``: MCAP records read back (shared by ``reader`` and ``repair``);
* ``reader``: the fast reader of our bags (the report); ``repair``: closes a torn bag.
"""
