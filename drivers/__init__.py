"""Cameras and pattern outputs; :func:`open_camera` opens a camera from its URI."""

from lightflow.drivers.uri import open_camera

__all__ = ["open_camera"]
