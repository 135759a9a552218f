"""The live web viewer (``beadsight live``): :class:`~beadsight.viewer.server.ViewerServer`."""

from beadsight.viewer.server import ViewerServer

__all__ = ["ViewerServer"]
