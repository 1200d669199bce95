"""Input checks of the estimator: options, corner arrays and whether four corners can be the
image of a marker at all (``quad_problem``)."""

from __future__ import annotations

import math
from typing import List, Optional, Sequence

import numpy as np

from .loop import METHODS

__all__ = [
    "METHODS",
    "DEGENERATE_REL",
    "MAX_CORNER_PX",
    "check_options",
    "quad_problem",
    "corners_as_floats",
    "corner_range_problem",
    "all_finite",
]
from .types import EstimationError

# Relative size below which two corners coincide / three corners are collinear.
DEGENERATE_REL = 1e-9
_NAMES = ("top-left", "top-right", "bottom-right", "bottom-left")
# No camera's image reaches this far from its origin (pixels); past it the other corners would
# look like one point next to the far one ("repeated corners"), which misnames the mistake.
MAX_CORNER_PX = 1e6


def check_options(method: str, iterations: int) -> None:
    """Raise EstimationError for an unknown method or a number of passes below 1."""
    if method not in METHODS:
        raise EstimationError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    if not isinstance(iterations, (int, np.integer)) or isinstance(iterations, bool) or iterations < 1:
        raise EstimationError(f"iterations must be a positive integer, got {iterations!r}")


def quad_problem(xs: Sequence[float], ys: Sequence[float]) -> Optional[str]:
    """Why four corners (TL, TR, BR, BL, y down) cannot be a marker's image, or None.

    Checks repeated corners, zero area, collinear corners, crossed (bow-tie) and non-convex
    shapes, and the corner order going the wrong way round (a marker seen from behind, or
    lying behind the camera)."""
    extent = max(max(xs) - min(xs), max(ys) - min(ys))
    if not extent > 0.0:
        return "all four corners are the same point"
    tiny = DEGENERATE_REL * extent
    for i in range(4):
        for j in range(i + 1, 4):
            if abs(xs[i] - xs[j]) <= tiny and abs(ys[i] - ys[j]) <= tiny:
                return f"repeated corners: {_NAMES[i]} and {_NAMES[j]} are the same point"
    area = 0.5 * sum(xs[j] * ys[(j + 1) % 4] - xs[(j + 1) % 4] * ys[j] for j in range(4))
    if abs(area) <= tiny * extent:
        return "the corners enclose zero area"
    turns = []
    for j in range(4):
        ax, ay = xs[j] - xs[j - 1], ys[j] - ys[j - 1]
        bx, by = xs[(j + 1) % 4] - xs[j], ys[(j + 1) % 4] - ys[j]
        cross = ax * by - ay * bx
        if abs(cross) <= DEGENERATE_REL * math.hypot(ax, ay) * math.hypot(bx, by):
            return f"collinear corners: {_NAMES[j - 1]}, {_NAMES[j]} and {_NAMES[(j + 1) % 4]} lie on one line"
        turns.append(cross > 0)
    n_pos = sum(turns)
    if n_pos == 2:
        return "crossed quadrilateral (bow-tie): two edges intersect; check the corner order"
    if n_pos in (1, 3):
        return "non-convex quadrilateral: a rectangle's image is always convex"
    if n_pos == 0:
        return (
            "corners go counter-clockwise on the image: the marker would be behind the "
            "camera or seen from its back; expected the order TL, TR, BR, BL"
        )
    return None


def corners_as_floats(corners_px) -> List[float]:
    """Four corners (4, 2) as 8 finite floats x0, y0, x1, ...; EstimationError otherwise."""
    try:
        arr = np.asarray(corners_px, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise EstimationError(f"corners must be numbers, shape (4, 2): {exc}") from None
    if arr.shape != (4, 2):
        raise EstimationError(f"corners must have shape (4, 2) (TL, TR, BR, BL pixels), got {arr.shape}")
    flat = arr.ravel().tolist()
    for v in flat:
        if not math.isfinite(v):
            raise EstimationError("corners contain NaN or infinity")
    problem = corner_range_problem(flat)
    if problem:
        raise EstimationError(problem)
    return flat


def corner_range_problem(flat: Sequence[float]) -> Optional[str]:
    """The first corner (of 8 finite floats x0, y0, x1, ...) past MAX_CORNER_PX, named, or None."""
    for k in range(4):
        x, y = flat[2 * k], flat[2 * k + 1]
        if abs(x) > MAX_CORNER_PX or abs(y) > MAX_CORNER_PX:
            return (
                f"corner {_NAMES[k]} ({x:g}, {y:g}) is out of range: pixel coordinates are within "
                f"+-{MAX_CORNER_PX:g} of the image"
            )
    return None


def all_finite(values: Sequence[float]) -> bool:
    for v in values:
        if not math.isfinite(v):
            return False
    return True
