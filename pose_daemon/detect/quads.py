"""Candidate quadrilaterals: dark convex four-sided regions outlined by a local threshold.

Shared by the square and the aruco detectors: threshold (adaptive mean, so lighting
gradients do not matter), outer contours, polygon fit, convexity and size checks.
"""

from __future__ import annotations

import math
from typing import List, Optional, Tuple

import cv2
import numpy as np

#: Least compactness (4 pi area / perimeter^2 of the contour) of a candidate outline; a
#: convex quadrilateral with sides in ratio up to 6:1 is above it.
MIN_COMPACTNESS = 0.3
#: ... for a marker whose code is read before any edge fit (ArUco): a square seen 80 deg off
#: its face along a diagonal is a thin rhombus of compactness pi cos / (2 (1 + cos^2)) = 0.26,
#: its thresholded outline thinner still.
MIN_COMPACTNESS_CODED = 0.15

#: (x0, y0, x1, y1) pixel bounds, x1/y1 exclusive.
Roi = Tuple[int, int, int, int]


def odd(n: float, lo: int = 3, hi: int = 255) -> int:
    """The odd window size nearest ``n`` within [lo, hi]."""
    k = min(max(int(round(float(n))), lo), hi)
    return k if k % 2 else k + 1


def find_quads(
    gray: np.ndarray,
    *,
    min_side_px: float,
    block_px: int,
    offset_gray: float = 7.0,
    roi: Optional[Roi] = None,
    approx_rate: float = 0.04,
    max_candidates: int = 64,
    downscale: int = 1,
    traced: Optional[tuple] = None,
    min_compactness: float = MIN_COMPACTNESS,
) -> List[np.ndarray]:
    """Dark convex quadrilaterals in ``gray`` (within ``roi``), largest first.

    Each is (4, 2) float64 pixels of the full image, in image-clockwise order (positive
    signed area) from an arbitrary start corner, accurate to about a pixel.
    ``block_px``: the adaptive threshold's window; ``offset_gray``: how much darker than
    the local mean a pixel must be to count as dark (well above sensor noise).
    ``downscale`` 2 thresholds a half-size image (4x fewer pixels; for large search areas).
    ``traced``: what ``trace_dark_regions`` gave for these same arguments (computed on
    another thread), else it is computed here. ``min_compactness``: the least 4 pi area /
    perimeter^2 of an outline (``MIN_COMPACTNESS``).
    """
    if traced is None:
        traced = trace_dark_regions(gray, block_px=block_px, offset_gray=offset_gray, roi=roi, downscale=downscale)
    contours, hierarchy = traced
    if hierarchy is None:
        return []
    x0, y0 = (0, 0) if roi is None else roi[:2]
    scale = float(downscale)
    min_side_px = min_side_px / scale
    min_perimeter = 4.0 * min_side_px
    min_area = min_side_px * min_side_px * 0.5
    quads: List[Tuple[float, np.ndarray]] = []
    perimeters = _outer_perimeters(contours, hierarchy, min_area, min_compactness)
    # Plain floats per polygon: a handful of points, where numpy's call overhead dominates.
    for index in np.flatnonzero(perimeters >= min_perimeter).tolist():
        contour, perimeter = contours[index], float(perimeters[index])
        poly = cv2.approxPolyDP(contour, approx_rate * perimeter, True)
        if len(poly) != 4 or not cv2.isContourConvex(poly):
            continue
        pts = [(float(x), float(y)) for x, y in poly.reshape(4, 2).tolist()]
        area = 0.5 * sum(pts[i][0] * pts[(i + 1) % 4][1] - pts[(i + 1) % 4][0] * pts[i][1] for i in range(4))
        if area < 0:
            pts.reverse()
            area = -area
        if area < min_area:
            continue
        if (
            min(math.hypot(pts[(i + 1) % 4][0] - pts[i][0], pts[(i + 1) % 4][1] - pts[i][1]) for i in range(4))
            < min_side_px
        ):
            continue
        # Boundary pixels of the dark region lie half a pixel inside its true edge; then
        # pixel centres of the half-size image: full-size x = scale * x_small + (scale - 1) / 2.
        cx = sum(p[0] for p in pts) / 4.0
        cy = sum(p[1] for p in pts) / 4.0
        out = []
        for x, y in pts:
            norm = max(math.hypot(x - cx, y - cy), 1e-9)
            x, y = x + 0.5 * (x - cx) / norm, y + 0.5 * (y - cy) / norm
            out.append((x * scale + 0.5 * (scale - 1.0) + x0, y * scale + 0.5 * (scale - 1.0) + y0))
        quads.append((area, np.array(out)))
    quads.sort(key=lambda item: -item[0])
    return [q for _, q in quads[:max_candidates]]


def trace_dark_regions(
    gray: np.ndarray, *, block_px: int, offset_gray: float = 7.0, roi: Optional[Roi] = None, downscale: int = 1
) -> tuple:
    """The threshold pass of ``find_quads`` up to its outlines: (contours, hierarchy (N, 4)
    or None) of the dark regions, in pixels of the (``roi`` of the) image scaled down by
    ``downscale``. OpenCV calls only (they let other threads run): a worker thread can
    trace one pass while another runs."""
    img = gray
    if roi is not None:
        x0, y0, x1, y1 = roi
        img = gray[y0:y1, x0:x1]
    if img.shape[0] < 8 * downscale or img.shape[1] < 8 * downscale:
        return (), None
    if downscale > 1:
        img = cv2.resize(img, (img.shape[1] // downscale, img.shape[0] // downscale), interpolation=cv2.INTER_AREA)
        block_px = block_px / downscale
    binary = cv2.adaptiveThreshold(
        img, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY_INV, odd(block_px), offset_gray
    )
    found = cv2.findContours(binary, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    contours, hierarchy = found[-2], found[-1]
    return contours, None if hierarchy is None else hierarchy[0]


def _outer_perimeters(
    contours, hierarchy: np.ndarray, min_area: float, min_compactness: float = MIN_COMPACTNESS
) -> np.ndarray:
    """Perimeter (pixels, closed) of every contour that can hold a quadrilateral, else 0:
    outer boundaries only (a hole's outline is the inside of a dark ring) with at least 4
    points and an enclosed area of at least half ``min_area``. All contours at once: in
    clutter there are hundreds, and one OpenCV call each cost more than the rest of the
    search (the quadrilateral's own area is checked again after the polygon fit)."""
    counts = np.array(list(map(len, contours)), dtype=np.intp)  # indices: int32 on a 32-bit Pi
    out = np.zeros(len(contours))
    # Outer boundaries of 4 points or more only: the holes' outlines are half the points.
    chosen = np.flatnonzero((hierarchy[:, 3] == -1) & (counts >= 4))
    if len(chosen) == 0:
        return out
    counts = counts[chosen]
    ends = np.cumsum(counts)
    starts = ends - counts
    pts = np.concatenate([contours[i] for i in chosen.tolist()]).reshape(-1, 2).astype(np.float64)
    # Each point to its successor, the last point of a contour back to its first.
    d = np.empty_like(pts)
    d[:-1] = pts[1:] - pts[:-1]
    d[ends - 1] = pts[starts] - pts[ends - 1]
    dx, dy = d[:, 0], d[:, 1]
    perimeter = np.add.reduceat(np.sqrt(dx * dx + dy * dy), starts)
    area = 0.5 * np.abs(np.add.reduceat(pts[:, 0] * dy - dx * pts[:, 1], starts))
    # Compactness 4 pi area / perimeter^2: 0.79 for a square, 0.59 for a 3:1 rectangle, a
    # 60-degree tilt halving one side 0.70; strokes of print and thin texture far below.
    compact = 4.0 * np.pi * area >= min_compactness * np.maximum(perimeter, 1e-9) ** 2
    keep = (area >= 0.5 * min_area) & compact
    out[chosen[keep]] = perimeter[keep]
    return out


def inside_any(point: np.ndarray, outlines: List[np.ndarray]) -> bool:
    """Is ``point`` (2,) inside any of the convex image-clockwise ``outlines`` (4, 2)?"""
    px, py = float(point[0]), float(point[1])
    for outline in outlines:
        c = outline.tolist()
        if all(
            (c[(i + 1) % 4][0] - c[i][0]) * (py - c[i][1]) - (c[(i + 1) % 4][1] - c[i][1]) * (px - c[i][0]) >= 0
            for i in range(4)
        ):
            return True
    return False
