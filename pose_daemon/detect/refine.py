"""Sub-pixel corners from straight-edge fits: each side's edge is located along many normals
at the half-way level between dark and light, a line is fitted per side, corners are the
intersections of neighbouring lines.

On blurred frames this beats a corner-window search (cv2.cornerSubPix), which is pulled
towards the inside of the blurred corner; an edge fit uses the whole side.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import cv2
import numpy as np

#: Step between profile samples along an edge normal, pixels.
PROFILE_STEP_PX = 0.5

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
    x, y = corners[:, 0], corners[:, 1]
    return 0.5 * float(np.dot(x, y[_NEXT]) - np.dot(x[_NEXT], y))


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
    current = start.copy()
    offsets = np.arange(-inner_px, outer_px + 1e-9, PROFILE_STEP_PX)
    if len(offsets) < 4:
        return None
    n_end = 2  # samples averaged for the dark and the light level of one profile
    distorted = camera is not None and camera.has_distortion
    fit: Optional[EdgeFit] = None
    m = int(samples_per_side)
    rows = np.arange(4 * m)
    last = float(len(offsets) - 1)
    frac_along = (np.arange(m) + 0.5) / m
    for _ in range(iterations):
        p0 = current
        d = current[_NEXT] - p0
        length = np.hypot(d[:, 0], d[:, 1])
        if length.min() < 4.0:
            return None
        u = d / length[:, None]
        normal_out = np.column_stack([u[:, 1], -u[:, 0]])
        # Keep clear of the rounded, blurred corners where the side is not a straight edge.
        end = np.maximum(1.5 + inner_px, 0.1 * length)
        span = length - 2 * end
        if span.min() < 2.0:
            return None
        t = end[:, None] + frac_along[None, :] * span[:, None]                  # (4, m)
        base = p0[:, None, :] + t[..., None] * u[:, None, :]                     # (4, m, 2)
        grid = base[:, :, None, :] + offsets[None, None, :, None] * normal_out[:, None, None, :]
        gx = grid[..., 0].reshape(4 * m, -1).astype(np.float32)
        gy = grid[..., 1].reshape(4 * m, -1).astype(np.float32)
        inside = ((gx >= 0) & (gx <= w - 1) & (gy >= 0) & (gy <= h - 1)).all(axis=1)
        prof = cv2.remap(gray, gx, gy, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
        dark = prof[:, :n_end].mean(axis=1)
        light = prof[:, -n_end:].mean(axis=1)
        contrast = light - dark
        mid = 0.5 * (dark + light)
        above = prof >= mid[:, None]
        # A clean crossing: dark at the inner end, light at the outer end.
        ok = inside & (contrast >= min_contrast) & (above.argmax(axis=1) > 0) & above[:, -1]
        x = _crossing(prof, rows, mid)
        # Re-take the dark and light levels symmetrically about the edge just found: a
        # symmetric blur leaks the same amount into both, so their mean stays the
        # half-way level even when the profile is too short to reach either plateau.
        for _ in range(2):
            r = np.maximum(np.minimum(x, last - x), 1.0)
            x = _crossing(prof, rows, 0.5 * (_interp(prof, rows, x - r) + _interp(prof, rows, x + r)))
        s_edge = offsets[0] + x * PROFILE_STEP_PX
        pts = base + s_edge.reshape(4, m)[..., None] * normal_out[:, None, :]
        if distorted:
            pts = _undistort_px(pts.reshape(-1, 2), camera).reshape(4, m, 2)
        weights = ok.reshape(4, m).astype(np.float64)
        if (weights.sum(axis=1) < 3).any():
            return None
        normal, offset, res = _fit_lines(pts, weights)
        # One pass of outlier rejection: texture or a neighbouring blob on a few profiles.
        abs_sorted = np.sort(np.where(weights > 0, np.abs(res), np.inf), axis=1)
        mad = abs_sorted[_SIDES, (weights.sum(axis=1).astype(int) - 1) // 2]
        keep = (weights > 0) & (np.abs(res) <= np.maximum(3.0 * 1.4826 * mad, 0.25)[:, None])
        if (keep.sum(axis=1) >= 3).all():
            weights = keep.astype(np.float64)
            normal, offset, res = _fit_lines(pts, weights)
        # Corner i is where side i-1 (into it) meets side i (out of it).
        n_a, c_a = normal[_PREV], offset[_PREV]
        det = n_a[:, 0] * normal[:, 1] - n_a[:, 1] * normal[:, 0]
        if np.abs(det).min() < 1e-6:
            return None
        refined = np.column_stack([(c_a * normal[:, 1] - n_a[:, 1] * offset) / det,
                                   (n_a[:, 0] * offset - c_a * normal[:, 0]) / det])
        if distorted:
            refined = _distort_px(refined, camera)
        if not np.isfinite(refined).all() or signed_area(refined) <= 0:
            return None
        used = weights > 0
        fit = EdgeFit(corners=refined, residual_px=float(np.sqrt(np.mean(res[used] ** 2))),
                      contrast=float(np.mean(contrast[used.reshape(-1)])),
                      valid_fraction=float(used.mean()))
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
