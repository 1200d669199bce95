"""Sub-pixel corners from straight-edge fits: each side's edge is located along many normals
at the half-way level between dark and light, a line is fitted per side, corners are the
intersections of neighbouring lines.

On blurred frames this beats a corner-window search (cv2.cornerSubPix), which is pulled
towards the inside of the blurred corner; an edge fit uses the whole side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import cv2
import numpy as np

#: Step between profile samples along an edge normal, pixels.
PROFILE_STEP_PX = 0.5
RECENTER = 2

_SIDES = np.arange(4)
_NEXT = np.array([1, 2, 3, 0])
_PREV = np.array([3, 0, 1, 2])


@dataclass
class EdgeFit:
    """Refined corners (4, 2) pixels in the input order, and how well the sides fitted."""

    corners: np.ndarray
    residual_px: float          # RMS distance of the edge points to their side's line
    contrast: float             # median light - dark grey levels across the edges
    valid_fraction: float       # share of profiles that crossed the edge cleanly


def signed_area(corners: np.ndarray) -> float:
    """Shoelace area in pixels^2; positive for TL,TR,BR,BL order in an image (y down)."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = np.asarray(corners, dtype=np.float64).tolist()
    return 0.5 * (x0 * y1 - x1 * y0 + x1 * y2 - x2 * y1 + x2 * y3 - x3 * y2 + x3 * y0 - x0 * y3)


def _undistort_px(points: np.ndarray, camera) -> np.ndarray:
    norm = camera.undistort_normalized(points)
    return norm * np.array([camera.fx, camera.fy]) + np.array([camera.cx, camera.cy])


def _distort_px(points: np.ndarray, camera) -> np.ndarray:
    norm = (points - np.array([camera.cx, camera.cy])) / np.array([camera.fx, camera.fy])
    return camera.project(np.column_stack([norm, np.ones(len(norm))]))


def _interp(prof: np.ndarray, rows: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Each profile (row) linearly interpolated at its own fractional sample index ``x``."""
    x = np.minimum(np.maximum(x, 0.0), prof.shape[1] - 1.000001)
    i = x.astype(np.intp)
    f = x - i
    return prof[rows, i] * (1.0 - f) + prof[rows, i + 1] * f


def _crossing(prof: np.ndarray, rows: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Fractional sample index where each profile first rises through ``level``."""
    j = np.minimum(np.maximum((prof >= level[:, None]).argmax(axis=1), 1), prof.shape[1] - 1)
    lo, hi = prof[rows, j - 1], prof[rows, j]
    frac = np.minimum(np.maximum((level - lo) / np.maximum(hi - lo, 1e-9), 0.0), 1.0)
    return j - 1 + frac


def _fit_lines(points: np.ndarray, weights: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted total least squares per side: points (4, m, 2), weights (4, m) -> unit
    normals (4, 2), offsets (4,) with n.x = c, and signed residuals (4, m)."""
    wsum = np.maximum(weights.sum(axis=1), 1e-12)
    centre = (weights[..., None] * points).sum(axis=1) / wsum[:, None]
    d = points - centre[:, None, :]
    sxx = (weights * d[..., 0] ** 2).sum(axis=1)
    syy = (weights * d[..., 1] ** 2).sum(axis=1)
    sxy = (weights * d[..., 0] * d[..., 1]).sum(axis=1)
    # Direction of greatest spread in closed form; the normal is perpendicular to it.
    theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    normal = np.column_stack([-np.sin(theta), np.cos(theta)])
    offset = (normal * centre).sum(axis=1)
    residual = (d * normal[:, None, :]).sum(axis=2)
    return normal, offset, residual


def fit_edges(gray: np.ndarray, corners: np.ndarray, *, inner_px: float, outer_px: float,
              iterations: int = 2, camera=None, min_contrast: float = 8.0,
              max_move_px: Optional[float] = None, samples_per_side: int = 24,
              converged_px: float = 0.5) -> Optional[EdgeFit]:
    """Refine approximate corners (4, 2) of a dark quadrilateral on a lighter surround.

    ``corners`` must be in image-clockwise order (positive ``signed_area``); the result
    keeps the order. ``inner_px``/``outer_px``: how far each profile reaches into the dark
    region and into the surround, pixels. With a ``camera`` that has lens distortion, lines
    are fitted in undistorted pixels (sides of a real marker are straight only there) and
    the corners mapped back. Stops after ``iterations`` passes or once corners move less
    than ``converged_px`` in a pass. None when the sides cannot be fitted (too few clean crossings,
    too little contrast, or corners that move further than ``max_move_px``).
    """
    h, w = gray.shape
    start = np.asarray(corners, dtype=np.float64).reshape(4, 2)
    current = start
    offsets = np.arange(-inner_px, outer_px + 1e-9, PROFILE_STEP_PX)
    n_off = len(offsets)
    if n_off < 4:
        return None
    distorted = camera is not None and camera.has_distortion
    fit: Optional[EdgeFit] = None
    m = int(samples_per_side)
    n = 4 * m
    rows = np.arange(n)
    rows2 = np.concatenate([rows, rows]) * n_off
    last = float(n_off - 1)
    frac_along = (np.arange(m) + 0.5) / m
    for _ in range(iterations):
        d = current[_NEXT] - current
        length = np.hypot(d[:, 0], d[:, 1])
        if length.min() < 4.0:
            return None
        u = d / length[:, None]
        # Keep clear of the rounded, blurred corners where the side is not a straight edge.
        end = np.maximum(1.5 + inner_px, 0.1 * length)
        span = length - 2.0 * end
        if span.min() < 2.0:
            return None
        t = end[:, None] + frac_along * span[:, None]                            # (4, m)
        bx = current[:, 0:1] + t * u[:, 0:1]                                      # (4, m)
        by = current[:, 1:2] + t * u[:, 1:2]
        # Outward normal of an image-clockwise outline: (u_y, -u_x).
        gx = (bx[:, :, None] + offsets * u[:, 1, None, None]).reshape(n, n_off).astype(np.float32)
        gy = (by[:, :, None] - offsets * u[:, 0, None, None]).reshape(n, n_off).astype(np.float32)
        ends_x, ends_y = gx[:, [0, -1]], gy[:, [0, -1]]
        inside = ((ends_x >= 0) & (ends_x <= w - 1) & (ends_y >= 0) & (ends_y <= h - 1)).all(axis=1)
        prof = cv2.remap(gray, gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
        dark = 0.5 * (prof[:, 0] + prof[:, 1])
        light = 0.5 * (prof[:, -1] + prof[:, -2])
        contrast = light - dark
        mid = 0.5 * (dark + light)
        # A clean crossing: dark at the inner end, light at the outer end.
        ok = inside & (contrast >= min_contrast) & (prof[:, 0] < mid) & (prof[:, -1] >= mid)
        x = _crossing(prof, rows, mid)
        # Re-take the dark and light levels symmetrically about the edge just found: a
        # symmetric blur leaks the same amount into both, so their mean stays the
        # half-way level even when the profile is too short to reach either plateau.
        flat = prof.ravel()
        for _ in range(RECENTER):
            r = np.maximum(np.minimum(x, last - x), 1.0)
            xs = np.minimum(np.maximum(np.concatenate([x - r, x + r]), 0.0), last - 1e-6)
            i = xs.astype(np.intp)
            f = xs - i
            k = rows2 + i
            v = flat[k] * (1.0 - f) + flat[k + 1] * f
            x = _crossing(prof, rows, 0.5 * (v[:n] + v[n:]))
        s_edge = (offsets[0] + x * PROFILE_STEP_PX).reshape(4, m)
        pts = np.stack([bx + s_edge * u[:, 1:2], by - s_edge * u[:, 0:1]], axis=-1)   # (4, m, 2)
        if distorted:
            pts = _undistort_px(pts.reshape(-1, 2), camera).reshape(4, m, 2)
        weights = ok.reshape(4, m).astype(np.float64)
        counts = weights.sum(axis=1)
        if counts.min() < 3:
            return None
        normal, offset, res = _fit_lines(pts, weights)
        abs_res = np.abs(res)
        if float((abs_res * weights).max()) > 0.25:
            # One pass of outlier rejection: texture or a neighbouring blob on a few profiles.
            abs_sorted = np.sort(np.where(weights > 0, abs_res, np.inf), axis=1)
            mad = abs_sorted[_SIDES, (counts.astype(int) - 1) // 2]
            keep = (weights > 0) & (abs_res <= np.maximum(3.0 * 1.4826 * mad, 0.25)[:, None])
            if (keep.sum(axis=1) >= 3).all():
                weights = keep.astype(np.float64)
                normal, offset, res = _fit_lines(pts, weights)
        # Corner i is where side i-1 (into it) meets side i (out of it).
        n_a, c_a = normal[_PREV], offset[_PREV]
        det = n_a[:, 0] * normal[:, 1] - n_a[:, 1] * normal[:, 0]
        if np.abs(det).min() < 1e-6:
            return None
        refined = np.empty((4, 2))
        refined[:, 0] = (c_a * normal[:, 1] - n_a[:, 1] * offset) / det
        refined[:, 1] = (n_a[:, 0] * offset - c_a * normal[:, 0]) / det
        if distorted:
            refined = _distort_px(refined, camera)
        if not np.isfinite(refined).all() or signed_area(refined) <= 0:
            return None
        n_used = float(weights.sum())
        fit = EdgeFit(corners=refined, residual_px=math.sqrt(float((res * res * weights).sum()) / n_used),
                      contrast=float((contrast * weights.ravel()).sum()) / n_used,
                      valid_fraction=n_used / n)
        moved = float(np.abs(refined - current).max())
        current = refined
        # Profiles along normals a fraction of a degree off find the same edge points.
        if moved < converged_px:
            break
    if fit is None:
        return None
    if max_move_px is not None and float(np.abs(fit.corners - start).max()) > max_move_px:
        return None
    return fit
