"""The camera's response: how the grey levels a camera delivers relate to the light it saw.

Real cameras do not deliver linear intensity: they encode it with a gamma curve (sRGB,
Rec. 709), so that the 50 % grey level of a blurred edge is not where the edge is. A dark
marker's half-way crossing in encoded values lies on its dark side: the marker looks
smaller the more the edge is blurred. Edges are fitted in linear intensity when the
response is known: ``gamma`` 1.0 (linear, the renderer's default), a power law
(value = 255 * (linear / 255) ** (1 / gamma)), or "srgb" (the sRGB curve, linear toe).

One owner for both directions: the renderer encodes with ``encode``, the detector
decodes with ``decode_lut``.
"""

from __future__ import annotations

import math
from typing import Optional, Union

import numpy as np

#: A camera response: a gamma exponent (> 0; 1.0 = linear) or "srgb".
Response = Union[float, str]


def check_response(value: Response, name: str = "gamma") -> Response:
    """``value`` if it is a valid response (a number in [0.2, 5] or "srgb"), else ValueError."""
    if isinstance(value, str):
        if value.strip().lower() == "srgb":
            return "srgb"
        raise ValueError(f"{name} must be a number in [0.2, 5] or 'srgb', got {value!r}")
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not math.isfinite(value)
        or not 0.2 <= float(value) <= 5.0
    ):
        raise ValueError(f"{name} must be a number in [0.2, 5] or 'srgb', got {value!r}")
    return float(value)


def is_linear(response: Response) -> bool:
    return not isinstance(response, str) and float(response) == 1.0


def decode(values: np.ndarray, response: Response) -> np.ndarray:
    """Encoded grey levels (0..255 scale, float) -> linear intensity on the same 0..255 scale."""
    v = np.clip(np.asarray(values, dtype=np.float64) / 255.0, 0.0, None)
    if response == "srgb":
        lin = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    else:
        lin = v ** float(response)
    return lin * 255.0


def encode(values: np.ndarray, response: Response) -> np.ndarray:
    """Linear intensity (0..255 scale) -> the grey levels the camera delivers (float, unclipped
    above 255 only by the curve's extension)."""
    v = np.clip(np.asarray(values, dtype=np.float64) / 255.0, 0.0, None)
    if response == "srgb":
        enc = np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1.0 / 2.4) - 0.055)
    else:
        enc = v ** (1.0 / float(response))
    return enc * 255.0


def decode_lut(response: Response) -> Optional[np.ndarray]:
    """A 256-entry float32 table uint8 grey level -> linear intensity, or None when linear."""
    if is_linear(response):
        return None
    return decode(np.arange(256, dtype=np.float64), response).astype(np.float32)
