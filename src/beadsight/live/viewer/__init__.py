"""The live web viewer (``beadsight live``): :class:`~beadsight.live.viewer.server.ViewerServer`."""

from beadsight.live.viewer.server import ViewerServer

__all__ = ["ViewerServer"]
