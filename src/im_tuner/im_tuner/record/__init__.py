"""Recording: every topic of the bench into an MCAP bag that rosbag2, rosbags, the mcap
library and Foxglove open. The modules: docs/recorder.md."""
