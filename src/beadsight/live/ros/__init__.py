"""ROS 2 messages of live readings, shared by ROS 2 and Foxglove (``live/outputs/``) and the
MCAP recording (``live/recording/``): their contents (:mod:`~beadsight.live.ros.messages`)
and their types, generated from rosbags' type store (:mod:`~beadsight.live.ros.types`)."""
