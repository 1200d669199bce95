"""The camera's response exponent (``[detector] gamma``) measured on the calibration's board views.

A board's inner corners are saddle points, unbiased by blur and by the camera's tone curve: the
straight line through two neighbouring corners is where a square's edge truly lies. Each dark
square between four found corners is fitted by the detector's edge fit (started from them,
reaching as a plain square's does) read at a trial exponent, and its fitted sides are held
against the corners' lines; the exponent at which the mean size bias is zero is the camera's
(scripts/real_edge_bias.py does the same on a folder of frames: on real webcam frames an
exponent fitted on half of them left -0.4 to +0.5 % on the other half, within 0.13 % on three
of four camera modes, docs/accuracy.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from ...detect.edge_profiles import signed_area
from ...detect.refine import fit_edges
from ...detect.response import Response, decode_lut
from ...detect.square import clamp, least_width
from .board import BoardView

#: The exponents searched (bisection), the bounds of ``[detector] gamma``'s useful range.
EXPONENT_RANGE = (0.5, 4.0)
#: Bisection steps: the range / 2**9 = 0.007.
BISECTION_STEPS = 9
#: Fewer dark squares than this measured: no exponent.
MIN_SQUARES = 20


@dataclass
class ResponseMeasurement:
    """The exponent that zeroes the edge fit's mean size bias on the board's dark squares (None
    when it lies outside EXPONENT_RANGE or too few squares were measured), the squares used,
    and the size bias (%) read as linear and as sRGB, for the report."""

    exponent: Optional[float]
    squares: int
    bias_linear_pct: float
    bias_srgb_pct: float


def dark_squares(gray: np.ndarray, view: BoardView, square_m: float) -> List[np.ndarray]:
    """The board's squares between four found corners whose middle is dark, (4, 2) pixels each,
    image-clockwise. Corners are placed on the board's lattice by their object points."""
    ij = np.round(np.asarray(view.object_points, dtype=np.float64)[:, :2] / square_m).astype(int)
    at: Dict[Tuple[int, int], np.ndarray] = {(int(i), int(j)): p for (i, j), p in zip(ij, view.image_points)}
    quads, means = [], []
    h, w = gray.shape
    for i, j in at:
        keys = ((i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1))
        if not all(k in at for k in keys):
            continue
        quad = np.array([at[k] for k in keys], dtype=np.float64)
        x, y = (int(round(c)) for c in quad.mean(axis=0))
        if not (1 <= x < w - 1 and 1 <= y < h - 1):
            continue
        quads.append(quad if signed_area(quad) > 0 else quad[::-1].copy())
        means.append(float(gray[y - 1 : y + 2, x - 1 : x + 2].mean()))
    if not quads:
        return []
    level = 0.5 * (min(means) + max(means))
    return [q for q, m in zip(quads, means) if m < level]


def _offsets(fitted: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Each side's signed distance (4,) of the fitted side from the reference one at the side's
    middle (the mean over its two ends), pixels, outward +."""
    a, b = reference, np.roll(reference, -1, axis=0)
    u = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    normal = np.column_stack([u[:, 1], -u[:, 0]])  # outward for an image-clockwise outline
    fa, fb = fitted, np.roll(fitted, -1, axis=0)
    return 0.5 * (np.sum((fa - a) * normal, axis=1) + np.sum((fb - b) * normal, axis=1))


def size_bias_pct(squares: List[Tuple[np.ndarray, np.ndarray]], response: Response) -> Tuple[float, int]:
    """The edge fit's mean size bias (%, fitted / true side - 1) over ``squares`` (gray, quad)
    read at ``response``, and the number of squares fitted."""
    lut = decode_lut(response)
    sizes = []
    for gray, quad in squares:
        side = least_width(quad)
        inner, outer = clamp(0.2 * side, 1.5, 3.0), clamp(0.15 * side, 1.5, 3.0)
        fit = fit_edges(gray, quad, inner_px=inner, outer_px=outer, iterations=3, lut=lut)
        if fit is None:
            continue
        lengths = np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)
        sizes.append(200.0 * float(_offsets(fit.corners, quad).mean()) / float(lengths.mean()))
    return (float(np.mean(sizes)) if sizes else 0.0), len(sizes)


def measure_response(views: List[BoardView], square_m: float) -> ResponseMeasurement:
    """The camera's response exponent from board views that carry their frames (``view.gray``)."""
    squares = [(v.gray, q) for v in views if v.gray is not None for q in dark_squares(v.gray, v, square_m)]
    linear, n = size_bias_pct(squares, 1.0)
    srgb, _ = size_bias_pct(squares, "srgb")
    if n < MIN_SQUARES:
        return ResponseMeasurement(None, n, linear, srgb)
    lo, hi = EXPONENT_RANGE
    # The bias grows with the exponent (a dark square read at a higher one comes out larger).
    if size_bias_pct(squares, lo)[0] > 0.0 or size_bias_pct(squares, hi)[0] < 0.0:
        return ResponseMeasurement(None, n, linear, srgb)
    for _ in range(BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        if size_bias_pct(squares, mid)[0] < 0.0:
            lo = mid
        else:
            hi = mid
    return ResponseMeasurement(0.5 * (lo + hi), n, linear, srgb)
