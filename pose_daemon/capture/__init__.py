"""Frame sources: picamera2, OpenCV cameras and videos, replay of recordings, the synthetic renderer."""

from .base import Frame, FrameSource

__all__ = ["Frame", "FrameSource"]
