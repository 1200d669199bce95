"""A marker partly out of the frame: each side fitted on its part inside the frame, a corner
inside the frame where its two sides' lines meet (MapDetector follows such markers; the map
solve leaves the corners outside out)."""

from __future__ import annotations

from typing import List, Optional, Tuple

import cv2
import numpy as np

from ..camera import Camera
from .edge_profiles import distort_px, signed_area, undistort_px
from .square import SquareOptions, side_lengths

#: A marker partly out of the frame is followed while this many of its corners are inside.
MIN_PARTIAL_CORNERS = 2
#: ... and while this share of its edge profiles (most of them on the visible sides) fit.
#: Profiles across each side of a marker partly out of the frame (those inside are used).
PARTIAL_SAMPLES = 24


def fit_side(
    gray: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    inner_px: float,
    outer_px: float,
    margin_px: float,
    lut: Optional[np.ndarray],
    min_contrast: float,
    camera: Optional[Camera],
) -> Optional[Tuple[np.ndarray, float, float]]:
    """The line (nx, ny, c: nx x + ny y = c, in undistorted pixels when the lens distorts) of
    the dark-to-light edge from corner ``a`` to ``b`` of an image-clockwise outline, fitted
    on the profiles across it that lie inside the frame; with its RMS residual (px) and mean
    contrast (grey levels). None when too little of the side is in the frame."""
    h, w = gray.shape
    d = b - a
    length = float(np.hypot(d[0], d[1]))
    if length < 8.0:
        return None
    u = d / length
    normal = np.array([u[1], -u[0]])  # outward for an image-clockwise outline
    t = np.linspace(0.12, 0.88, PARTIAL_SAMPLES) * length
    base = a + t[:, None] * u
    ok = (base[:, 0] >= margin_px) & (base[:, 0] <= w - 1 - margin_px)
    ok &= (base[:, 1] >= margin_px) & (base[:, 1] <= h - 1 - margin_px)
    if int(ok.sum()) < 6:
        return None
    base = base[ok]
    offsets = np.arange(-inner_px, outer_px + 1e-9, 0.5)
    if len(offsets) < 4:
        return None
    pts = base[:, None, :] + offsets[None, :, None] * normal
    prof = cv2.remap(gray, pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32), cv2.INTER_LINEAR).astype(
        np.float64
    )
    if lut is not None:
        prof = np.interp(prof, np.arange(256.0), lut)
        levels = np.interp(prof[:, [0, 1, -2, -1]], np.arange(256.0), np.arange(256.0))
    dark = 0.5 * (prof[:, 0] + prof[:, 1])
    light = 0.5 * (prof[:, -1] + prof[:, -2])
    contrast = light - dark if lut is None else 0.5 * (levels[:, 2] + levels[:, 3] - levels[:, 0] - levels[:, 1])
    mid = 0.5 * (dark + light)
    above = prof >= mid[:, None]
    first = np.argmax(above, axis=1)
    good = (contrast >= min_contrast) & (first > 0) & above[np.arange(len(first)), first]
    # A clean crossing: dark before the first sample above the half-way level, light after.
    good &= ~above[:, 0] & above[:, -1]
    if int(good.sum()) < 6:
        return None
    rows = np.nonzero(good)[0]
    i1 = first[rows]
    p0, p1 = prof[rows, i1 - 1], prof[rows, i1]
    frac = (mid[rows] - p0) / np.maximum(p1 - p0, 1e-9)
    s_edge = offsets[0] + (i1 - 1 + frac) * 0.5
    edge = base[rows] + s_edge[:, None] * normal
    if camera is not None and camera.has_distortion:
        edge = undistort_px(edge, camera)
    centre = edge.mean(axis=0)
    _, _, vt = np.linalg.svd(edge - centre, full_matrices=False)
    n = vt[1]
    res = (edge - centre) @ n
    keep = np.abs(res) <= max(0.3, 3.0 * 1.4826 * float(np.median(np.abs(res))))
    if int(keep.sum()) < 6:
        return None
    centre = edge[keep].mean(axis=0)
    _, _, vt = np.linalg.svd(edge[keep] - centre, full_matrices=False)
    n = vt[1]
    res = (edge[keep] - centre) @ n
    return np.array([n[0], n[1], float(n @ centre)]), float(np.sqrt(np.mean(res * res))), float(contrast[rows].mean())


def intersect(l1: np.ndarray, l2: np.ndarray) -> Optional[np.ndarray]:
    A = np.array([l1[:2], l2[:2]])
    det = float(np.linalg.det(A))
    if abs(det) < 1e-6:
        return None
    return np.linalg.solve(A, np.array([l1[2], l2[2]]))


def corners_inside(px: np.ndarray, width: int, height: int) -> np.ndarray:
    """Which corners lie in the frame, a pixel in from its border."""
    x, y = px[:, 0], px[:, 1]
    return (x >= 1.0) & (x <= width - 2.0) & (y >= 1.0) & (y <= height - 2.0)


def line_through(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b - a
    n = np.array([-d[1], d[0]]) / max(float(np.hypot(d[0], d[1])), 1e-12)
    return np.array([n[0], n[1], float(n @ a)])


def fit_partial(
    gray: np.ndarray,
    predicted: np.ndarray,
    *,
    inner_px: float,
    outer_px: float,
    lut: Optional[np.ndarray],
    options: SquareOptions,
    camera: Optional[Camera],
) -> Optional[np.ndarray]:
    """The corners of a marker partly out of the frame, from its ``predicted`` corners (4, 2)
    pixels (where the track or the map pose puts it), or None.

    ``inner_px``, ``outer_px``: the profiles' reach into the marker and its surround; ``lut``
    the camera's response (``response.decode_lut``) or None; ``options`` the finder's bounds.

    The edge fit of the whole outline needs all four sides; here each side is fitted on
    its part inside the frame (the sides wholly outside are not), and a corner inside the
    frame is where its two sides' lines meet (a corner outside keeps its predicted place:
    the solve leaves such corners out). Its bits cannot all be read, so it is checked by
    the fit alone (straight sides, contrast, near where it was predicted); a wrong one is
    the solve's outlier. Markers that leave (or enter) the frame so fade out of the solve
    corner by corner instead of dropping out whole."""
    o = options
    h, w = gray.shape
    inner, outer = inner_px, outer_px
    max_move = 0.8 * min(inner, outer) + 0.5
    corners = np.asarray(predicted, dtype=np.float64).copy()
    margin = max(inner, outer) + 1.0
    for _ in range(2):
        lines: List[Optional[np.ndarray]] = []
        residuals: List[float] = []
        contrasts: List[float] = []
        for k in range(4):
            line = fit_side(gray, corners[k], corners[(k + 1) % 4], inner, outer, margin, lut, o.min_contrast, camera)
            if line is None:
                lines.append(None)
                continue
            lines.append(line[0])
            residuals.append(line[1])
            contrasts.append(line[2])
        # A side wholly out of the frame keeps its predicted line; a corner is where its
        # two lines meet (a fitted one and a predicted one for a corner out of the frame).
        und = corners if camera is None or not camera.has_distortion else undistort_px(corners, camera)
        pred_lines = [line_through(und[k], und[(k + 1) % 4]) for k in range(4)]
        new = corners.copy()
        # Every corner in the image (the solve uses those) must be measured.
        inside = ((corners >= -0.5) & (corners <= [w - 0.5, h - 0.5])).all(axis=1)
        for k in range(4):
            a, b = lines[(k - 1) % 4], lines[k]
            if (a is None or b is None) and inside[k]:
                return None  # a corner in the frame whose sides cannot be fitted
            if a is None and b is None:
                continue
            pt = intersect(pred_lines[(k - 1) % 4] if a is None else a, pred_lines[k] if b is None else b)
            if pt is None:
                return None
            new[k] = pt if camera is None or not camera.has_distortion else distort_px(pt[None], camera)[0]
        corners = new
    if int(sum(line is not None for line in lines)) < 3:
        return None
    if max(residuals) > o.max_edge_residual_px or min(contrasts) < o.min_contrast:
        return None
    inside = ((corners >= 1.0) & (corners <= [w - 2.0, h - 2.0])).all(axis=1)
    if int(inside.sum()) < MIN_PARTIAL_CORNERS:
        return None
    moved = np.linalg.norm(corners[inside] - predicted[inside], axis=1)
    if float(moved.max()) > 2.0 * max_move + 1.0:
        return None
    if signed_area(corners) <= 0 or side_lengths(corners).min() < o.min_side_px:
        return None
    return corners
