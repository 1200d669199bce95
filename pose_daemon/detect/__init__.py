"""Finding the marker's four corners in a frame: square and ArUco detectors, tracking.

``MarkerDetector(marker, **options)`` is the one entry point (interface.md).
"""

from __future__ import annotations

from .detector import MarkerDetector, as_gray

__all__ = ["MarkerDetector", "as_gray"]
