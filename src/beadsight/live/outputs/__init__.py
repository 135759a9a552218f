"""Where live readings go beside files: the web viewer (:mod:`~beadsight.live.outputs.viewer`),
ROS 2 (:mod:`~beadsight.live.outputs.ros2`) and Foxglove
(:mod:`~beadsight.live.outputs.foxglove`), the network outputs on one base with one
slow-client rule (:mod:`~beadsight.live.outputs.base`)."""
