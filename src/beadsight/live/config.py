"""Defaults of the live outputs (viewer, TCP stream, ROS 2, Foxglove), in one light module
(no numpy, no OpenCV) that the outputs and the command line both read, so that
``beadsight live --help`` starts fast."""

from __future__ import annotations

DEFAULT_HOST = "127.0.0.1"  # the viewer and the stream answer this machine only by default
VIEWER_PORT = 8000
VIEWER_MAX_FPS = 20.0  # viewer updates per second, independent of the sensing rate
VIEWER_MAX_KPA = 150.0  # top of the fixed colour scale (about an 18 N finger press)
STREAM_PORT = 8765  # the TCP readings stream
STREAM_MAX_AGE_S = 0.5  # a reading is never sent later than this after it was produced
FOXGLOVE_PORT = 8766  # 8765 is the TCP readings stream
ROS_NAMESPACE = "/beadsight"  # ROS 2 topics and Foxglove channels live under it
