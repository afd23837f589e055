"""Recording: every topic of the bench into an MCAP bag that rosbag2, rosbags, the mcap
library and Foxglove open.

* ``node``: ``Recorder``, which the recorder child and the in-process bench poll;
* ``child``: the recorder child (``ros2 run im_tuner recorder``) and its status topic,
  whose contract is ``status``;
* ``take``: takes serialized messages from the subscriptions' queues (numba over rcl);
* ``writer``: the MCAP writer (chunks compressed and written on a background thread);
* ``schemas``: message and service definitions for the MCAP schemas, from the installed
  packages; ``metadata``: rosbag2's metadata.yaml;
* ``records``: MCAP records read back (shared by ``reader`` and ``repair``);
* ``reader``: the fast reader of our bags (the report); ``repair``: closes a torn bag.
"""
