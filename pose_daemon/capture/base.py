"""Frame, the one small interface every frame source implements, and the grey conversion."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Protocol, runtime_checkable

import cv2
import numpy as np

from ..attitude import Attitude


@dataclass
class Frame:
    """One grayscale image with its capture time.

    ``t_capture_s`` is the sensor time stamp where the camera gives one, on the monotonic
    clock (seconds); it is carried unchanged to every output. ``attitude``: the vehicle's at
    ``t_capture_s`` when the source knows it (a recording, the synthetic source), else None.
    """

    image: np.ndarray
    t_capture_s: float
    seq: int
    metadata: Dict[str, Any] = field(default_factory=dict)
    attitude: Optional[Attitude] = None


@runtime_checkable
class FrameSource(Protocol):
    """``read()`` returns the next Frame, raises EndOfStream when a finite source is done
    and SourceError when the source failed (it may then be closed and opened again)."""

    def open(self) -> None: ...

    def read(self) -> Frame: ...

    def close(self) -> None: ...


def as_gray(image: Any) -> np.ndarray:
    """A 2-D uint8 grey image from what a camera or a file gives: uint8 or uint16, grey,
    (H, W, 1), BGR or BGRA. ValueError naming the problem for anything else.

    The one grey conversion of the project: the sources, the detector and calibration use it.
    """
    if not isinstance(image, np.ndarray):
        raise ValueError(f"image must be a numpy array, got {type(image).__name__}")
    if image.size == 0:
        raise ValueError(f"image is empty (shape {image.shape})")
    if image.dtype == np.uint16:
        # 16-bit grey (a PNG, a camera's wide output) spans 0..65535: keep the top byte.
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ValueError(f"image must be uint8 (or uint16) grey levels, got dtype {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_BGRA2GRAY)
    if image.ndim != 2:
        raise ValueError(f"image must be grey (H, W) or BGR (H, W, 3), got shape {image.shape}")
    return np.ascontiguousarray(image)
