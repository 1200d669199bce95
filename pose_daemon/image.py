"""What an image is to the project: a 2-D uint8 grey array, and the one conversion to it."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

__all__ = ["as_gray"]


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
