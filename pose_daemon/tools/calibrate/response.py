"""The camera's response exponent (``[detector] gamma``) measured on the calibration's board views.

A board's inner corners are saddle points, unbiased by blur and by the camera's tone curve: the
straight line through two neighbouring corners is where a square's edge truly lies. Each dark
square between four found corners is fitted by the detector's edge fit (started from them,
reaching as a plain square's does) read at a trial exponent, and its fitted sides are held
against the corners' lines; the exponent at which the mean size bias is zero is the camera's
(scripts/real_edge_bias.py does the same on a folder of frames, docs/accuracy.md).

One exponent is right for a camera whose curve is a power law. A webcam's may have a shoulder
(``[detector] gamma_shoulder``, detect/response.py): its exponent rises towards white, so each
view's bias at the exponent depends on the view's exposure (the LifeCam HD-3000's views: -2 to
+2.3 % at the one exponent, from the dim views to the bright). With views of several exposures
the shoulder shows as that spread between views: the shoulder kept is the one that leaves the
least spread between the views' mean size biases (each at the exponent that zeroes their
overall mean), and only when it takes at least ``SHOULDER_MIN_GAIN`` of the power law's spread
away (views of one exposure cannot tell a shoulder: it stays 0). A power law that leaves less
than ``SHOULDER_MIN_SPREAD_PCT`` between the views is kept without looking.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ...detect.edge_profiles import signed_area
from ...detect.refine import fit_edges
from ...detect.response import MIN_BLACK_EXPONENT, Response, decode_lut
from ...detect.square import clamp, least_width
from .board import BoardView

#: The exponents searched (bisection), the bounds of ``[detector] gamma``'s useful range.
EXPONENT_RANGE = (0.5, 4.0)
#: Bisection steps: the range / 2**9 = 0.007.
BISECTION_STEPS = 9
#: Fewer dark squares than this measured: no exponent.
MIN_SQUARES = 20
#: The shoulders tried (detect/response.py), then a parabola through the best and its neighbours.
SHOULDER_GRID = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
#: A shoulder is kept when it takes at least this share off the power law's spread between views.
SHOULDER_MIN_GAIN = 0.25
#: Views (with a dark square fitted) needed before a spread between them is looked at.
MIN_VIEWS_FOR_SHOULDER = 4
#: A shoulder is looked for only when the power law leaves more spread than this between the
#: views (%, half the issue's bound on the size bias): less is not worth a second parameter.
SHOULDER_MIN_SPREAD_PCT = 0.15
#: With a guess, the exponent is first bracketed this far either side of it.
GUESS_BRACKET = 0.25
#: The exponent is searched until the mean size bias is within this (%) of zero, or for
#: ``BISECTION_STEPS`` steps.
ZERO_TOLERANCE_PCT = 0.005


@dataclass
class ResponseMeasurement:
    """The exponent that zeroes the edge fit's mean size bias on the board's dark squares (None
    when it lies outside EXPONENT_RANGE or too few squares were measured), the squares used,
    and the size bias (%) read as linear and as sRGB, for the report."""

    exponent: Optional[float]
    squares: int
    bias_linear_pct: float
    bias_srgb_pct: float
    shoulder: float = 0.0  # [detector] gamma_shoulder (0 = a power law)
    views: int = 0  # views with a dark square fitted
    spread_pct: float = 0.0  # standard deviation of the views' mean size biases, at the result
    spread_power_pct: float = 0.0  # the same at the best power law (shoulder 0)


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


def size_bias_pct(
    squares: List[Tuple[np.ndarray, np.ndarray]], response: Response, shoulder: float = 0.0
) -> Tuple[float, int]:
    """The edge fit's mean size bias (%, fitted / true side - 1) over ``squares`` (gray, quad)
    read at ``response`` (and ``shoulder``), and the number of squares fitted."""
    sizes = _square_biases(squares, decode_lut(response, shoulder))
    return (float(np.nanmean(sizes)) if np.isfinite(sizes).any() else 0.0), int(np.isfinite(sizes).sum())


def _square_biases(squares: List[Tuple[np.ndarray, np.ndarray]], lut: Optional[np.ndarray]) -> np.ndarray:
    """Each square's size bias (%), NaN where the edge fit failed."""
    sizes = np.full(len(squares), np.nan)
    for k, (gray, quad) in enumerate(squares):
        side = least_width(quad)
        inner, outer = clamp(0.2 * side, 1.5, 3.0), clamp(0.15 * side, 1.5, 3.0)
        fit = fit_edges(gray, quad, inner_px=inner, outer_px=outer, iterations=3, lut=lut)
        if fit is None:
            continue
        lengths = np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)
        sizes[k] = 200.0 * float(_offsets(fit.corners, quad).mean()) / float(lengths.mean())
    return sizes


class _Views:
    """Dark squares grouped by view: the mean size bias over all and each view's, per curve."""

    def __init__(self, groups: Sequence[List[Tuple[np.ndarray, np.ndarray]]]) -> None:
        self.squares = [sq for group in groups for sq in group]
        self.view = np.concatenate([np.full(len(g), i) for i, g in enumerate(groups)]) if self.squares else np.zeros(0)

    def biases(self, gamma: float, shoulder: float) -> Tuple[float, np.ndarray]:
        sizes = _square_biases(self.squares, decode_lut(gamma, shoulder))
        ok = np.isfinite(sizes)
        per_view = np.array([sizes[ok & (self.view == v)].mean() for v in np.unique(self.view[ok])])
        return (float(sizes[ok].mean()) if ok.any() else 0.0), per_view

    def zero(self, shoulder: float, guess: Optional[float] = None) -> Optional[Tuple[float, float]]:
        """The exponent that zeroes the mean size bias at ``shoulder``, and the spread between
        the views there; None when outside the range. ``guess``: where to look first (the zero
        at a neighbouring shoulder: ``gamma`` is the exponent at mid grey, and moves little)."""
        bottom, top = EXPONENT_RANGE
        bottom = max(bottom, 0.5 * shoulder + MIN_BLACK_EXPONENT + 0.01)
        lo, hi = bottom, top
        if guess is not None:
            guess = min(max(guess, bottom), top)
            lo, hi = max(bottom, guess - GUESS_BRACKET), min(top, guess + GUESS_BRACKET)
        # The bias grows with the exponent (a dark square read at a higher one comes out larger).
        b_lo, b_hi = self.biases(lo, shoulder)[0], self.biases(hi, shoulder)[0]
        if b_lo > 0.0 and lo > bottom:
            hi, b_hi, lo = lo, b_lo, bottom
            b_lo = self.biases(lo, shoulder)[0]
        elif b_hi < 0.0 and hi < top:
            lo, b_lo, hi = hi, b_hi, top
            b_hi = self.biases(hi, shoulder)[0]
        if not b_lo <= 0.0 <= b_hi:
            return None
        for _ in range(BISECTION_STEPS):
            # Regula falsi kept bracketing (the bias is near linear in the exponent), halved
            # towards the middle so that a stuck end cannot stall it.
            t = min(max(-b_lo / (b_hi - b_lo), 0.05), 0.95) if b_hi > b_lo else 0.5
            mid = lo + t * (hi - lo)
            b, per_view = self.biases(mid, shoulder)
            if abs(b) <= ZERO_TOLERANCE_PCT:
                return mid, float(np.std(per_view))
            if b < 0.0:
                lo, b_lo = mid, b
            else:
                hi, b_hi = mid, b
        mid = 0.5 * (lo + hi)
        return mid, float(np.std(self.biases(mid, shoulder)[1]))


def fit_response(
    groups: Sequence[List[Tuple[np.ndarray, np.ndarray]]], shoulders: Sequence[float] = SHOULDER_GRID
) -> ResponseMeasurement:
    """The camera's response from dark squares (gray, quad) grouped by view: the exponent that
    zeroes the mean size bias, with the shoulder that leaves the least spread between the views
    (see the module's notes); ``shoulders``: the grid tried ((0.0,): a power law only)."""
    data = _Views(groups)
    linear, n = size_bias_pct(data.squares, 1.0)
    srgb, _ = size_bias_pct(data.squares, "srgb")
    views = len([g for g in groups if g])
    if n < MIN_SQUARES:
        return ResponseMeasurement(None, n, linear, srgb, views=views)
    power = data.zero(0.0)
    tried: Dict[float, Tuple[float, float]] = {}
    grid = tuple(shoulders)
    spread = 0.0 if power is None else power[1]
    if views >= MIN_VIEWS_FOR_SHOULDER and len(grid) > 1 and spread > SHOULDER_MIN_SPREAD_PCT:
        guess = None if power is None else power[0]
        for shoulder in grid:
            found = power if shoulder == 0.0 else data.zero(shoulder, guess)
            if found is not None:
                tried[shoulder] = found
                guess = found[0]
    if tried:
        best = min(tried, key=lambda k: tried[k][1])
        k = grid.index(best)
        if 0 < k < len(grid) - 1 and all(grid[j] in tried for j in (k - 1, k + 1)):
            # The spread's minimum on a parabola through the best and its neighbours.
            x = np.array(grid[k - 1 : k + 2])
            a, b, _ = np.polyfit(x, [tried[v][1] for v in x], 2)
            if a > 0:
                refined = float(np.clip(-b / (2 * a), x[0], x[2]))
                found = data.zero(refined, tried[best][0])
                if found is not None and found[1] < tried[best][1]:
                    tried[refined] = found
                    best = refined
        if power is not None and best != 0.0 and tried[best][1] <= (1.0 - SHOULDER_MIN_GAIN) * power[1]:
            gamma, spread = tried[best]
            return ResponseMeasurement(gamma, n, linear, srgb, best, views, spread, power[1])
    if power is None:
        return ResponseMeasurement(None, n, linear, srgb, views=views)
    return ResponseMeasurement(power[0], n, linear, srgb, 0.0, views, power[1], power[1])


def measure_response(
    views: List[BoardView], square_m: float, shoulders: Sequence[float] = SHOULDER_GRID
) -> ResponseMeasurement:
    """The camera's response (exponent and shoulder) from board views that carry their frames
    (``view.gray``); ``shoulders`` as ``fit_response``'s."""
    return fit_response(
        [[(v.gray, q) for q in dark_squares(v.gray, v, square_m)] for v in views if v.gray is not None], shoulders
    )
