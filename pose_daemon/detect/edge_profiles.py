"""The profiles across a quadrilateral's edges, shared by the edge fits (refine.py,
refine_many.py): where they are sampled, where each crosses a level, the line through the
crossings, and the result, ``EdgeFit``."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import cv2
import numpy as np

#: Step between profile samples along an edge normal, pixels.
PROFILE_STEP_PX = 0.5
#: The next and the previous corner (or side) of each, going round an outline.
NEXT = np.array([1, 2, 3, 0])
PREV = np.array([3, 0, 1, 2])
#: Grey levels 0..255, the x of a response table's interpolation.
LEVELS = np.arange(256, dtype=np.float64)


@dataclass
class EdgeFit:
    """Refined corners (4, 2) pixels in the input order, and how well the sides fitted."""

    corners: np.ndarray
    residual_px: float  # RMS distance of the edge points to their side's line
    contrast: float  # mean light - dark grey levels across the edges
    valid_fraction: float  # share of profiles that crossed the edge cleanly
    blur_px: float = 0.0  # the edges' blur, Gaussian sigma, the most blurred side
    side_blur_px: Optional[np.ndarray] = None  # each side's (4,), from SIDE_BLUR_REPORT_PX on (fit_edges)
    # The last pass met the fit's own stopping rule (it moved the corners less than its
    # converged_px, its profiles centred on the edges): a fit from its corners would stay there.
    settled: bool = False


def signed_area(corners: np.ndarray) -> float:
    """Shoelace area in pixels^2; positive for TL,TR,BR,BL order in an image (y down)."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = np.asarray(corners, dtype=np.float64).tolist()
    return 0.5 * (x0 * y1 - x1 * y0 + x1 * y2 - x2 * y1 + x2 * y3 - x3 * y2 + x3 * y0 - x0 * y3)


def undistort_px(points: np.ndarray, camera) -> np.ndarray:
    norm = camera.undistort_normalized(points)
    return norm * np.array([camera.fx, camera.fy]) + np.array([camera.cx, camera.cy])


def distort_px(points: np.ndarray, camera) -> np.ndarray:
    norm = (points - np.array([camera.cx, camera.cy])) / np.array([camera.fx, camera.fy])
    return camera.project(np.column_stack([norm, np.ones(len(norm))]))


def crossing(prof: np.ndarray, rows: np.ndarray, level: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Fractional sample index where each profile first rises through ``level``, and the
    rise per sample there."""
    j0 = np.minimum(np.maximum((prof >= level[:, None]).argmax(axis=1), 1), prof.shape[1] - 1) - 1
    lo, hi = prof[rows, j0], prof[rows, j0 + 1]
    rise = hi - lo
    frac = np.minimum(np.maximum((level - lo) / np.maximum(rise, 1e-9), 0.0), 1.0)
    return j0 + frac, rise


def sample_profiles(gray: np.ndarray, gx: np.ndarray, gy: np.ndarray, lut: Optional[np.ndarray]) -> np.ndarray:
    """Grey levels (float64) at the sample points, bilinear; in linear intensity with ``lut``.

    Linearised before interpolating (a pixel's light mixes linearly), over just the box
    the samples touch."""
    if lut is None:
        return cv2.remap(gray, gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    h, w = gray.shape
    x0 = int(min(max(math.floor(float(gx.min())) - 1, 0), w - 1))
    y0 = int(min(max(math.floor(float(gy.min())) - 1, 0), h - 1))
    x1 = int(min(max(math.ceil(float(gx.max())) + 2, x0 + 1), w))
    y1 = int(min(max(math.ceil(float(gy.max())) + 2, y0 + 1), h))
    box = cv2.LUT(gray[y0:y1, x0:x1], lut)
    # Outside the image a sample repeats the nearest pixel, as BORDER_REPLICATE does: clamp
    # to the box (which reaches the image's edge wherever samples leave it).
    mx = np.clip(gx - x0, 0.0, x1 - x0 - 1).astype(np.float32)
    my = np.clip(gy - y0, 0.0, y1 - y0 - 1).astype(np.float32)
    return cv2.remap(box, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)


def corner_clearance(u: np.ndarray, length: np.ndarray, blur_px: float) -> np.ndarray:
    """How far from its ends (pixels) each side's profiles must start: a blurred corner
    rounds the sides near it, the further the sharper its angle (the neighbouring side is
    2.5 sigma away only that far along this one). At most 0.3 of the side."""
    if blur_px <= 0.0:
        return np.zeros(4)
    sin_corner = np.abs(u[:, 0] * u[PREV, 1] - u[:, 1] * u[PREV, 0])  # at each side's start
    sin_end = np.minimum(sin_corner, sin_corner[NEXT])
    return np.minimum(2.5 * blur_px / np.maximum(sin_end, 0.3), 0.3 * length)


def clear_of_corners(u: np.ndarray, length: np.ndarray, end: np.ndarray, blur_px: float) -> bool:
    """Do the profiles start at least ``corner_clearance`` (+ 0.5 px) from the corners?
    Plain floats: four sides, where numpy's per-call overhead would dominate."""
    (ax, ay), (bx, by), (cx, cy), (dx, dy) = u.tolist()
    # |sin| of the corner at the start of each side (between the previous side and it).
    s = [abs(ax * dy - ay * dx), abs(bx * ay - by * ax), abs(cx * by - cy * bx), abs(dx * cy - dy * cx)]
    lengths, ends = length.tolist(), end.tolist()
    for i in range(4):
        need = min(2.5 * blur_px / max(min(s[i], s[(i + 1) % 4]), 0.3), 0.3 * lengths[i])
        if need > ends[i] + 0.5:
            return False
    return True


def fit_line(points: np.ndarray) -> Tuple[float, float, float]:
    """Least-squares line through points (k, 2): unit normal (nx, ny) and offset c, n.x = c."""
    vx, vy, x0, y0 = cv2.fitLine(points.astype(np.float32), cv2.DIST_L2, 0, 1e-4, 1e-4).ravel().tolist()
    return -vy, vx, -vy * x0 + vx * y0


def crossing_rows(
    prof: np.ndarray, rows: np.ndarray, level: np.ndarray, last_i: np.ndarray
) -> Tuple[np.ndarray, np.ndarray]:
    """``crossing`` of profiles of unequal length: row r's samples end at ``last_i[r]`` (the
    ones after it are -inf, never above a level)."""
    j0 = np.minimum(np.maximum((prof >= level[:, None]).argmax(axis=1), 1), last_i) - 1
    lo, hi = prof[rows, j0], prof[rows, j0 + 1]
    rise = hi - lo
    frac = np.minimum(np.maximum((level - lo) / np.maximum(rise, 1e-9), 0.0), 1.0)
    return j0 + frac, rise
