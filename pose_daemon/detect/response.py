"""The camera's response: how the grey levels a camera delivers relate to the light it saw.

Real cameras do not deliver linear intensity: they encode it with a gamma curve (sRGB,
Rec. 709), so that the 50 % grey level of a blurred edge is not where the edge is. A dark
marker's half-way crossing in encoded values lies on its dark side: the marker looks
smaller the more the edge is blurred. Edges are fitted in linear intensity when the
response is known: ``gamma`` 1.0 (linear, the renderer's default), a power law
(value = 255 * (linear / 255) ** (1 / gamma)), or "srgb" (the sRGB curve, linear toe).

A power law has one exponent at every grey level. Some cameras' curves have a shoulder: the
exponent rises towards white (the LifeCam HD-3000's from about 1.3 at a white level of 100 to
2 at 230, docs/accuracy.md), so one exponent is right only at one exposure. ``shoulder`` (0 =
a power law) bends the power law so: linear = 255 * x ** (gamma - shoulder / 2) *
exp(shoulder * (x - 1)) with x = value / 255; the local exponent (d ln linear / d ln x) is
``gamma`` at mid grey and rises by ``shoulder`` from black to white.

One owner for both directions: the renderer encodes with ``encode``, the detector
decodes with ``decode_lut``.
"""

from __future__ import annotations

import math
from typing import Optional, Union

import numpy as np

#: A camera response: a gamma exponent (> 0; 1.0 = linear) or "srgb".
Response = Union[float, str]


def _number_in(value: object, lo: float, hi: float) -> bool:
    """Whether ``value`` is a finite int or float (not a bool) in [lo, hi]."""
    return (
        not isinstance(value, bool)
        and isinstance(value, (int, float))
        and math.isfinite(value)
        and lo <= float(value) <= hi
    )


def check_response(value: Response, name: str = "gamma") -> Response:
    """``value`` if it is a valid response (a number in [0.2, 5] or "srgb"), else ValueError."""
    if isinstance(value, str):
        if value.strip().lower() == "srgb":
            return "srgb"
        raise ValueError(f"{name} must be a number in [0.2, 5] or 'srgb', got {value!r}")
    if not _number_in(value, 0.2, 5.0):
        raise ValueError(f"{name} must be a number in [0.2, 5] or 'srgb', got {value!r}")
    return float(value)


#: The lowest exponent a shoulder may leave at black (``gamma - shoulder / 2``): the curve must
#: stay a rising one through 0.
MIN_BLACK_EXPONENT = 0.1


def check_shoulder(shoulder: float, response: Response, name: str = "gamma_shoulder") -> float:
    """``shoulder`` if it is valid with ``response`` (a number in [0, 4]; 0 with "srgb"; below
    twice the exponent less ``MIN_BLACK_EXPONENT``), else ValueError."""
    if not _number_in(shoulder, 0.0, 4.0):
        raise ValueError(f"{name} must be a number in [0, 4], got {shoulder!r}")
    if float(shoulder) == 0.0:
        return 0.0
    if isinstance(response, str):
        raise ValueError(f"{name} applies to a numeric gamma, not {response!r}")
    if float(response) - 0.5 * float(shoulder) < MIN_BLACK_EXPONENT:
        raise ValueError(
            f"{name} {shoulder!r} must be below 2 * (gamma - {MIN_BLACK_EXPONENT}) = "
            f"{2.0 * (float(response) - MIN_BLACK_EXPONENT):g} (gamma {response!r})"
        )
    return float(shoulder)


def is_linear(response: Response, shoulder: float = 0.0) -> bool:
    return not isinstance(response, str) and float(response) == 1.0 and float(shoulder) == 0.0


def _bent(x: np.ndarray, gamma: float, shoulder: float) -> np.ndarray:
    """The curve x (encoded, 0..1) -> linear (0..1) of a power law with a shoulder."""
    return x ** (gamma - 0.5 * shoulder) * np.exp(shoulder * (x - 1.0))


def decode(values: np.ndarray, response: Response, shoulder: float = 0.0) -> np.ndarray:
    """Encoded grey levels (0..255 scale, float) -> linear intensity on the same 0..255 scale."""
    v = np.clip(np.asarray(values, dtype=np.float64) / 255.0, 0.0, None)
    if response == "srgb":
        lin = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    elif shoulder:
        lin = _bent(v, float(response), float(shoulder))
    else:
        lin = v ** float(response)
    return lin * 255.0


def encode(values: np.ndarray, response: Response, shoulder: float = 0.0) -> np.ndarray:
    """Linear intensity (0..255 scale) -> the grey levels the camera delivers (float, unclipped
    above 255 only by the curve's extension; with a shoulder, up to twice 255)."""
    v = np.clip(np.asarray(values, dtype=np.float64) / 255.0, 0.0, None)
    if response == "srgb":
        enc = np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1.0 / 2.4) - 0.055)
    elif shoulder:
        # No closed form: the rising curve tabulated and read backwards.
        x = np.linspace(0.0, 2.0, 8193)
        enc = np.interp(v, _bent(x, float(response), float(shoulder)), x)
    else:
        enc = v ** (1.0 / float(response))
    return enc * 255.0


def decode_lut(response: Response, shoulder: float = 0.0) -> Optional[np.ndarray]:
    """A 256-entry float32 table uint8 grey level -> linear intensity, or None when linear."""
    if is_linear(response, shoulder):
        return None
    return decode(np.arange(256, dtype=np.float64), response, shoulder).astype(np.float32)
