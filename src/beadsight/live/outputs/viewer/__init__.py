"""The live web viewer (``beadsight live``): :class:`~beadsight.live.outputs.viewer.server.ViewerServer`."""

from beadsight.live.outputs.viewer.server import ViewerServer

__all__ = ["ViewerServer"]
