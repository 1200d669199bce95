"""Frame sources: picamera2, OpenCV cameras and videos, replay of recordings, the synthetic renderer.

``parse_source(s)`` reads a ``[camera] source`` string into (kind, arg);
``open_source(cfg.camera, cfg)`` builds the source it names (both in sources.py).
"""

from __future__ import annotations

from ..config.forms import SOURCE_FORMS, SOURCE_KINDS, parse_source
from .base import Frame, FrameSource
from .sources import open_source

__all__ = ["Frame", "FrameSource", "SOURCE_FORMS", "SOURCE_KINDS", "open_source", "parse_source"]
