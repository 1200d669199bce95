"""The plain marker: a dark rectangle on a light surround, found, refined and checked.

A candidate is accepted only if it looks like the marker: straight sides that fit lines to
a fraction of a pixel, a uniformly dark inside and a light ring just outside it. Shapes
of a textured background fail these checks, so frames without the marker give nothing.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Callable, List, Optional, Tuple

import cv2
import numpy as np

from ..camera import Marker
from .edge_profiles import EdgeFit
from .quads import MIN_COMPACTNESS, Roi, find_quads, inside_any, odd, trace_dark_regions
from .refine import SEARCH_CONVERGED_PX, SEARCH_ITERATIONS, fit_edges
from .response import Response, decode_lut


@dataclass
class Candidate:
    """A verified marker outline: corners (4, 2) pixels in image-clockwise order.

    ``oriented``: the corners are already TL, TR, BR, BL (the marker's pattern says so);
    otherwise the start corner is arbitrary and the detector labels them.
    """

    corners: np.ndarray
    oriented: bool
    fit: EdgeFit


@dataclass(frozen=True)
class SquareOptions:
    """Tuning of the square finder (MarkerDetector keyword options of the same names)."""

    min_side_px: float = 10.0
    block_px: int = 25  # adaptive threshold window for a full-frame search
    threshold_offset: float = 10.0  # grey levels below the local mean that count as dark
    min_contrast: float = 20.0  # light surround - dark inside, grey levels
    max_edge_residual_px: float = 0.4
    max_aspect_ratio_error: float = 3.0  # measured W:H may differ from the marker's by this factor
    ring_px: float = 2.5  # how far outside the sides the light ring is sampled
    gamma: Response = 1.0  # the camera's response (response.py): edges fitted in linear light
    gamma_shoulder: float = 0.0  # its exponent's rise from black to white (0 = a power law)
    blur_model: bool = True  # ArUco: a blurred marker's corners from its whole pattern (blur_model.py)


def side_lengths(corners: np.ndarray) -> np.ndarray:
    """Lengths of the sides TL-TR, TR-BR, BR-BL, BL-TL (for any start corner), pixels."""
    # Plain floats: at four points numpy's per-call overhead costs more than the arithmetic.
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = np.asarray(corners, dtype=np.float64).tolist()
    return np.array(
        [
            math.hypot(x1 - x0, y1 - y0),
            math.hypot(x2 - x1, y2 - y1),
            math.hypot(x3 - x2, y3 - y2),
            math.hypot(x0 - x3, y0 - y3),
        ]
    )


def least_width(corners: np.ndarray) -> float:
    """The outline's least extent across a side, pixels: the shortest side, or, for a quad
    sheared thin (a square seen obliquely along a diagonal is a thin rhombus), its area over
    the mean length of two opposite sides where that is less (a parallelogram's height)."""
    sides = side_lengths(corners)
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = np.asarray(corners, dtype=np.float64).tolist()
    area = 0.5 * abs((x2 - x0) * (y3 - y1) - (x3 - x1) * (y2 - y0))
    heights = (area / max(0.5 * (sides[0] + sides[2]), 1e-9), area / max(0.5 * (sides[1] + sides[3]), 1e-9))
    return min(float(sides.min()), *heights)


#: A tracked plain square is followed until it looks as long as a square seen this far off
#: its face (W:H 1 / cos = 5.8), beyond ``max_aspect_ratio_error``'s 3 (70 deg).
TRACKED_VIEW_DEG = 80.0

#: ``corner_reach``'s cap: corners sharper than 29 deg move no further than this many times.
MAX_CORNER_REACH = 4.0


def corner_reach(corners: np.ndarray) -> float:
    """How much further a corner moves than the sides through it: 1 / sin(half the outline's
    sharpest angle), at most MAX_CORNER_REACH. A thin rhombus's sharp tips (a square seen
    obliquely along a diagonal) are rounded off by blur and the threshold, and the edge fits
    put them back several pixels further out than a side moves."""
    c = np.asarray(corners, dtype=np.float64)
    a, b = np.roll(c, 1, axis=0) - c, np.roll(c, -1, axis=0) - c
    cos = np.sum(a * b, axis=1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
    sharpest = math.acos(min(max(float(cos.max()), -1.0), 1.0))
    return min(1.0 / max(math.sin(0.5 * sharpest), 1e-9), MAX_CORNER_REACH)


# Canonical marker square [0, 1]^2, corners in image-clockwise order from its top-left.
UNIT_SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=np.float32)
_g = np.linspace(0.0, 1.0, 7)
_GRID = np.array([[u, v] for v in _g for u in _g], dtype=np.float64)
_GRID_RIM = (_GRID.min(axis=1) == 0.0) | (_GRID.max(axis=1) == 1.0)
_s = np.linspace(0.1, 0.9, 7)
# The 3 x 3 points around the middle (the inner part of _GRID).
_CENTRE = np.array([[u, v] for v in (1 / 3, 0.5, 2 / 3) for u in (1 / 3, 0.5, 2 / 3)], dtype=np.float64)


# Points just outside each side, spread along it: base + (ru, rv) * direction, where ru/rv
# are how far outside the left/right and top/bottom sides, in canonical units.
_RING_BASE = np.concatenate(
    [
        np.column_stack([_s, 0 * _s]),
        np.column_stack([1 + 0 * _s, _s]),
        np.column_stack([_s[::-1], 1 + 0 * _s]),
        np.column_stack([0 * _s, _s[::-1]]),
    ]
)
_RING_DIR = np.concatenate(
    [
        np.tile([0.0, -1.0], (7, 1)),
        np.tile([1.0, 0.0], (7, 1)),
        np.tile([0.0, 1.0], (7, 1)),
        np.tile([-1.0, 0.0], (7, 1)),
    ]
)
_N_GRID = len(_GRID)
_LEVELS = np.arange(256, dtype=np.float64)


#: The farthest any edge profile reaches outside a tracked outline (``reach_px``'s cap), pixels.
MAX_REACH_PX = 3.0
#: A follow whose edge fits led the outline further than its reach (a turn round) is
#: followed once more from there while they moved it at most this many reaches.
RELOCATE_MAX_REACHES = 3.0

#: A run of whole-frame searches that find nothing (no marker in view) runs the full-size
#: pass in one of every this many, the half-size pass in every one. The half-size pass finds
#: nearly every marker of 30 px or more (the ArUco marker on bench detector's frames: 299 of
#: 300 on the main scenes, 119 of 120 in clutter, 328 of the blur sweep's 334; the full-size
#: pass the rest, 30-54 px), the full-size pass most far ones under 20 px; on
#: marker-free clutter it is most of a search's cost (carpet: its outline tracing 1.7 ms of
#: 2.7). A marker only it sees is found within this many frames of coming into view; the
#: first search after a marker was seen (a lost track) and after ``MarkerDetector.reset``
#: has both passes.
FULL_PASS_EVERY = 4


def clamp(value: float, lo: float, hi: float) -> float:
    return min(max(float(value), lo), hi)


def median_of(values: np.ndarray) -> float:
    return float(np.partition(values, len(values) // 2)[len(values) // 2])


@functools.lru_cache(maxsize=64)
def _band(d: float) -> np.ndarray:
    """Points at canonical distance ``d`` inside (d > 0) or outside (d < 0) each side."""
    return np.concatenate(
        [
            np.column_stack([_s, 0 * _s + d]),
            np.column_stack([1 - d + 0 * _s, _s]),
            np.column_stack([_s[::-1], 1 - d + 0 * _s]),
            np.column_stack([d + 0 * _s, _s[::-1]]),
        ]
    )


def darker_inside(
    gray: np.ndarray, corners: np.ndarray, depth: float, min_contrast: float, solid: bool = False
) -> bool:
    """Quick look before a fit: is a polygon's band ``depth`` (canonical) inside its sides
    darker, by ``min_contrast`` grey levels, than a band outside? Rejects the dark halo a
    threshold draws around a bright sheet, and texture, at a tenth of a fit's cost.

    ``solid``: also dark in the middle (a plain square marker is one ink): at most one of 9
    points around the centre lighter than half-way between the band inside and the one
    outside. Rejects the outlines of hollow shapes (print's O, D, 0; frames), which pass the
    band test, before their fit; ``SquareFinder.verify`` allows no more (1 of 49)."""
    n = 4 * len(_s)
    uv = [_band(depth), _band(-0.1)]
    if solid:
        uv.append(_CENTRE)
    values = sample_canonical(gray, corners, np.concatenate(uv))
    inside, outside = values[:n], values[n : 2 * n]
    outside = outside[np.isfinite(outside)]
    if len(outside) < n // 3:
        return False
    dark, light = median_of(inside), median_of(outside)
    if light - dark < min_contrast:
        return False
    return not solid or np.count_nonzero(values[2 * n :] >= 0.5 * (dark + light)) <= 1


def sample_canonical(gray: np.ndarray, corners: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Grey levels at canonical marker coordinates ``uv`` (N, 2) in [0, 1]^2 (plus margins),
    NaN where the point falls outside the image."""
    H = cv2.getPerspectiveTransform(UNIT_SQUARE, np.asarray(corners, dtype=np.float32))
    pts = cv2.perspectiveTransform(uv.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
    h, w = gray.shape
    inside = (pts[:, 0] >= 0) & (pts[:, 0] <= w - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= h - 1)
    mx = pts[:, 0].astype(np.float32).reshape(1, -1)
    my = pts[:, 1].astype(np.float32).reshape(1, -1)
    values = cv2.remap(gray, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out = values.reshape(-1).astype(np.float64)
    out[~inside] = np.nan
    return out


def sample_canonical_many(gray: np.ndarray, corners: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``sample_canonical`` for many outlines at once: (N, len(uv)) grey levels of the outlines
    ``corners`` (N, 4, 2), NaN outside the image; one remap for all of them (a board or a page
    of print gives a hundred outlines, where one OpenCV call each cost more than the rest).

    The unit square's projective map onto each outline in closed form (Heckbert 1989), the
    homography ``cv2.getPerspectiveTransform`` solves for, from the same float32 corners."""
    n = len(corners)
    if n == 0:
        return np.zeros((0, len(uv)))
    c = np.asarray(corners, dtype=np.float32).astype(np.float64).reshape(n, 4, 2)
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = (c[:, k, :].T[:, :, None] for k in range(4))
    dx1, dx2, dx3 = x1 - x2, x3 - x2, x0 - x1 + x2 - x3
    dy1, dy2, dy3 = y1 - y2, y3 - y2, y0 - y1 + y2 - y3
    det = dx1 * dy2 - dx2 * dy1
    det = np.where(np.abs(det) > 1e-12, det, 1e-12)
    g = (dx3 * dy2 - dx2 * dy3) / det
    h = (dx1 * dy3 - dx3 * dy1) / det
    u, v = uv[:, 0], uv[:, 1]
    w = g * u + h * v + 1.0
    px = ((x1 - x0 + g * x1) * u + (x3 - x0 + h * x3) * v + x0) / w
    py = ((y1 - y0 + g * y1) * u + (y3 - y0 + h * y3) * v + y0) / w
    h_img, w_img = gray.shape
    inside = (px >= 0) & (px <= w_img - 1) & (py >= 0) & (py <= h_img - 1)
    values = cv2.remap(
        gray,
        px.astype(np.float32).reshape(1, -1),
        py.astype(np.float32).reshape(1, -1),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    out = values.reshape(n, -1).astype(np.float64)
    out[~inside] = np.nan
    return out


def medians_of_rows(values: np.ndarray) -> np.ndarray:
    """``median_of`` of each row of ``values`` (N, M), NaNs left out (NaN for a row of NaNs)."""
    if values.shape[1] == 0:
        return np.full(len(values), np.nan)
    finite = np.isfinite(values)
    count = finite.sum(axis=1)
    ordered = np.sort(np.where(finite, values, np.inf), axis=1)
    out = ordered[np.arange(len(values)), np.minimum(count // 2, values.shape[1] - 1)]
    return np.where(count > 0, out, np.nan)


def aspect_error(corners: np.ndarray, marker: Marker) -> float:
    """How far the outline's W:H is from the marker's, as |log ratio| (0 = equal).

    For unlabelled corners the smaller of the two possible readings is taken.
    """
    s = side_lengths(corners)
    a = 0.5 * (s[0] + s[2]) / max(0.5 * (s[1] + s[3]), 1e-9)
    want = marker.width / marker.height
    return float(min(abs(np.log(a / want)), abs(np.log(a * want))))


class OutlineFinder:
    """What the square and ArUco finders share: edge fits of a dark outline, and following it.

    Subclasses say how far the edge profiles reach (``reach_px``), whether a fit is the
    marker (``verify``) and whether their corners come out labelled (``oriented``).
    """

    oriented = False
    #: The dark border's width as a fraction of a side when light cells lie behind it (an
    #: ArUco marker's code), None for a solid dark shape: the edge fits then model them.
    border_fraction: Optional[float] = None
    #: The least compactness of a rough outline searched (quads.MIN_COMPACTNESS).
    min_compactness: float = MIN_COMPACTNESS

    def __init__(self, marker: Marker, options: SquareOptions, camera=None) -> None:
        self.marker = marker
        self.options = options
        self.camera = camera
        self.lut = decode_lut(options.gamma, options.gamma_shoulder)
        self._pool: Optional[Any] = None  # a ThreadPoolExecutor of one worker once use_threads(2+)
        #: The next threshold pass's traced dark regions, started on the worker while the
        #: current pass runs: (future, search, (stage, roi, block)), or None. ``search``
        #: counts search_from calls: a result is only ever taken by the search that started
        #: it (a later frame may come in the same array, refilled).
        self._early_outlines: Optional[tuple] = None
        self._search_serial = 0
        #: Whole-frame searches in a row that found nothing (the ArUco finder's OpenCV step
        #: runs by it; the worker starts work early only after a fruitless search).
        self.fruitless_searches = 0

    def use_threads(self, threads: int) -> None:
        """``threads`` >= 2: while a whole-frame search runs its half-size pass, the
        full-size pass's threshold and outline tracing (OpenCV calls, which let the other
        thread run) go on another core, so a frame without the marker costs about the longer
        of the two passes instead of their sum. Only after a fruitless whole-frame search:
        the first search after a track is lost usually finds the marker in its half-size
        pass, and work started for it on the other core would only slow it down. Results
        are the same; the tracked path never uses the worker."""
        if threads >= 2 and self._pool is None:
            # Imported here: the daemon's start-up does not pay for it on a single core.
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pose-daemon-search")

    def reach_px(self, corners: np.ndarray):
        raise NotImplementedError

    def verify(self, gray: np.ndarray, fit: EdgeFit) -> bool:
        raise NotImplementedError

    def refine(
        self,
        gray: np.ndarray,
        corners: np.ndarray,
        iterations: int,
        max_move_px: Optional[float] = None,
        converged_px: float = 0.5,
        reach: Optional[Tuple[float, float]] = None,
        check_blur: bool = True,
    ) -> Optional[EdgeFit]:
        inner, outer = self.reach_px(corners) if reach is None else reach
        return fit_edges(
            gray,
            corners,
            inner_px=inner,
            outer_px=outer,
            iterations=iterations,
            camera=self.camera,
            min_contrast=0.5 * self.options.min_contrast,
            max_move_px=max_move_px,
            converged_px=converged_px,
            lut=self.lut,
            check_blur=check_blur,
            border_fraction=self.border_fraction,
            border_model_below_px=self.border_model_below_px(),
        )

    def border_model_below_px(self) -> float:
        """Edges blurred less than this get the edge fits' border model (``fit_edges``)."""
        return math.inf

    # ------------------------------------------------------------------ search

    def try_quad(self, gray: np.ndarray, quad: np.ndarray, scale: int, found: List[Candidate]) -> Optional[Candidate]:
        raise NotImplementedError

    def stages(self, gray: np.ndarray, roi: Optional[Roi]) -> List[Tuple[str, int]]:
        """The steps of a search, cheapest first: ("quads", downscale) threshold passes. A
        whole frame is first searched at half size (4x cheaper); markers it misses are found
        by a full-size pass. A run of fruitless searches has it in turns: the first search of
        the run, then every FULL_PASS_EVERY-th (the 5th, 9th, ...; OpenCV's step of the ArUco
        finder falls on the 8th, 16th, ...)."""
        if roi is None and min(gray.shape) >= 240:
            if self.fruitless_searches % FULL_PASS_EVERY == 0:
                return [("quads", 2), ("quads", 1)]
            return [("quads", 2)]
        return [("quads", 1)]

    def _trace(self, gray: np.ndarray, stage: Tuple[str, int], roi: Optional[Roi], block: int) -> tuple:
        o = self.options
        return trace_dark_regions(gray, block_px=block, offset_gray=o.threshold_offset, roi=roi, downscale=stage[1])

    def stage_items(self, gray: np.ndarray, stage: Tuple[str, int], roi: Optional[Roi], block: int) -> list:
        """The work items of a stage: its rough outlines, largest first."""
        early = self._early_outlines
        if early is not None and early[1] == self._search_serial and early[2] == (stage, roi, block):
            self._early_outlines = None
            traced = early[0].result()
        else:
            traced = self._trace(gray, stage, roi, block)
        o = self.options
        return find_quads(
            gray,
            min_side_px=o.min_side_px,
            block_px=block,
            offset_gray=o.threshold_offset,
            roi=roi,
            downscale=stage[1],
            traced=traced,
            min_compactness=self.min_compactness,
        )

    def process(
        self, gray: np.ndarray, stage: Tuple[str, int], item, roi: Optional[Roi], found: List[Candidate]
    ) -> List[Candidate]:
        cand = self.try_quad(gray, item, stage[1], found)
        return [] if cand is None else [cand]

    def prepare_stage(
        self, gray: np.ndarray, plan: List[Tuple[str, int]], stage_i: int, roi: Optional[Roi], block: int
    ) -> None:
        """Called as stage ``stage_i`` of ``plan`` starts: with a worker (``use_threads``),
        the next stage's threshold and tracing start on it when that stage is a threshold
        pass."""
        if (
            self._pool is None
            or self.fruitless_searches == 0
            or stage_i + 1 >= len(plan)
            or plan[stage_i + 1][0] != "quads"
        ):
            return
        nxt = plan[stage_i + 1]
        future = self._pool.submit(self._trace, gray, nxt, roi, block)
        self._early_outlines = (future, self._search_serial, (nxt, roi, block))

    def restart_searches(self) -> None:
        """The next whole-frame search is the first of a run: it has every step."""
        self.fruitless_searches = 0

    def search_ended(self, roi: Optional[Roi], found: bool) -> None:
        """Called when a search ran to its end (not when it stopped at the time cap)."""
        if roi is None:
            self.fruitless_searches = 0 if found else self.fruitless_searches + 1

    def search(
        self, gray: np.ndarray, roi: Optional[Roi] = None, expected_side_px: Optional[float] = None
    ) -> List[Candidate]:
        """Every verified marker outline in ``roi`` (or the whole frame)."""
        return self.search_from(gray, roi, expected_side_px)[0]

    def search_from(
        self,
        gray: np.ndarray,
        roi: Optional[Roi] = None,
        expected_side_px: Optional[float] = None,
        start: Tuple[int, int] = (0, 0),
        over: Optional[Callable[[], bool]] = None,
    ) -> Tuple[List[Candidate], Optional[Tuple[int, int]]]:
        """A search that may stop early: (candidates, where to go on or None).

        Starts at ``start`` = (stage, item); stages run cheapest first and a stage that finds
        the marker ends the search. ``over()`` is asked before every item but the first of
        this call: once it says True the search stops and returns the (stage, item) to start
        the next frame's search from. None: the search ran to its end (found or not)."""
        self._search_serial += 1
        plan = self.stages(gray, roi)
        stage_i, skip = start
        if not 0 <= stage_i < len(plan):
            stage_i, skip = 0, 0
        o = self.options
        block = o.block_px if expected_side_px is None else odd(np.clip(expected_side_px / 3.0, 7, 41))
        first = True
        while stage_i < len(plan):
            stage = plan[stage_i]
            if not first and over is not None and over():
                return [], (stage_i, skip)
            self.prepare_stage(gray, plan, stage_i, roi, block)
            items = self.stage_items(gray, stage, roi, block)
            out: List[Candidate] = []
            for k in range(min(skip, len(items)), len(items)):
                if not first and over is not None and over():
                    if out:
                        self.search_ended(roi, True)
                        return out, None
                    return out, (stage_i, k)
                first = False
                out.extend(self.process(gray, stage, items[k], roi, out))
            first = False
            if out:
                self.search_ended(roi, True)
                return out, None
            stage_i, skip = stage_i + 1, 0
        self.search_ended(roi, False)
        return [], None

    def follow(self, gray: np.ndarray, predicted: np.ndarray) -> Optional[Candidate]:
        """The marker near ``predicted`` corners (tracked frames): edge fits from there, checked."""
        inner, outer = self.reach_px(predicted)
        max_move = 0.8 * min(inner, outer) + 0.5
        fit = self.refine(gray, predicted, iterations=2, reach=(inner, outer), check_blur=False)
        if fit is None:
            return None
        moved = float(np.abs(fit.corners - predicted).max())
        if moved > max_move:
            # The edges led the fit further than the follow's reach: where the camera turns
            # round, the prediction (a step ahead) is two steps from the marker. Followed
            # once more from where they led, within the same reach and checked as any: a
            # tracked frame's cost, where the region search that found the same outline
            # costs 3-5 times that (the frames of bench pipeline's p99).
            if moved > RELOCATE_MAX_REACHES * max_move:
                return None
            # A fit whose last pass settled (moved under its converged_px from the pass
            # before, profiles centred on the edges) was that follow already: a pass more
            # moved its corners by 0.01 px on bench pipeline's turns, at half a frame's cost.
            if not fit.settled:
                start = fit.corners
                inner, outer = self.reach_px(start)
                max_move = 0.8 * min(inner, outer) + 0.5
                fit = self.refine(
                    gray, start, iterations=2, max_move_px=max_move, reach=(inner, outer), check_blur=False
                )
                if fit is None:
                    return None
        if not self.verify_tracked(gray, fit):
            return None
        return Candidate(fit.corners, self.oriented, fit)

    def verify_tracked(self, gray: np.ndarray, fit: EdgeFit) -> bool:
        """``verify`` for an outline followed from the last frame's (the track vouches for
        its shape changing smoothly)."""
        return self.verify(gray, fit)


class SquareFinder(OutlineFinder):
    """Finds and checks the dark rectangle of a ``square`` marker."""

    oriented = False

    def reach_px(self, corners: np.ndarray):
        """(inside, outside) reach of the edge profiles for an outline of this size."""
        side = least_width(corners)
        return clamp(0.2 * side, 1.5, 3.0), clamp(0.15 * side, 1.5, MAX_REACH_PX)

    def shape_ok(self, corners: np.ndarray, max_aspect_ratio_error: Optional[float] = None) -> bool:
        if side_lengths(corners).min() < self.options.min_side_px:
            return False
        limit = self.options.max_aspect_ratio_error if max_aspect_ratio_error is None else max_aspect_ratio_error
        return aspect_error(corners, self.marker) <= np.log(limit)

    def verify_tracked(self, gray: np.ndarray, fit: EdgeFit) -> bool:
        """A followed square may look as long as one seen TRACKED_VIEW_DEG off its face: its
        first sighting was a square (the view gate stands for that), and the track is what
        follows it further (processing: ``_identified``)."""
        limit = max(self.options.max_aspect_ratio_error, 1.0 / math.cos(math.radians(TRACKED_VIEW_DEG)))
        return self.verify(gray, fit, limit)

    def verify(self, gray: np.ndarray, fit: EdgeFit, max_aspect_ratio_error: Optional[float] = None) -> bool:
        """Is this outline the marker? Straight sides, dark uniform inside, light ring outside
        (its W:H within ``max_aspect_ratio_error`` of the marker's, default the options')."""
        o = self.options
        if fit.residual_px > o.max_edge_residual_px or fit.valid_fraction < 0.6:
            return False
        if fit.contrast < o.min_contrast or not self.shape_ok(fit.corners, max_aspect_ratio_error):
            return False
        # The ring sits ring_px outside each side (but within a fifth of the side's length).
        s0, s1, s2, s3 = side_lengths(fit.corners).tolist()
        ru = min(max(o.ring_px / max(min(s0, s2), 1.0), 0.04), 0.2)
        rv = min(max(o.ring_px / max(min(s1, s3), 1.0), 0.04), 0.2)
        r = np.array([ru, rv])
        # The inside is sampled out to ring_px from the sides: a dark frame around a lighter
        # band (paper darker than the wall around it) is not a uniformly dark region.
        values = sample_canonical(
            gray, fit.corners, np.concatenate([r + _GRID * (1.0 - 2.0 * r), _RING_BASE + _RING_DIR * r])
        )
        inside, ring = values[:_N_GRID], values[_N_GRID:]
        ring = ring[np.isfinite(ring)]
        if len(ring) < 10:
            return False
        dark, light = median_of(inside), median_of(ring)
        if light - dark < o.min_contrast:
            return False
        if self.lut is not None:
            # The shape of the blur is judged in linear light: encoded, the blurred rim of
            # the inside looks like a lighter band.
            inside, ring = np.interp(inside, _LEVELS, self.lut), np.interp(ring, _LEVELS, self.lut)
            dark, light = median_of(inside), median_of(ring)
        mid = 0.5 * (dark + light)
        # The inside is one dark ink; the ring is paper (a shadow or glare may touch a few).
        if np.count_nonzero(inside >= mid) > 1 or float(inside.max() - inside.min()) > 0.5 * (light - dark):
            return False
        # ... also no lighter band along its sides (a grey sheet with the marker inside it).
        if abs(float(inside[_GRID_RIM].mean() - inside[~_GRID_RIM].mean())) > 0.2 * (light - dark):
            return False
        return np.count_nonzero(ring <= mid) <= 0.1 * len(ring)

    def try_quad(self, gray: np.ndarray, quad: np.ndarray, scale: int, found: List[Candidate]) -> Optional[Candidate]:
        """A rough outline from the threshold -> the verified marker, or None. Cheap checks
        first (shape, not inside one found, darker inside); the edge fit only for survivors."""
        o = self.options
        # Quads come largest first: one inside a marker already found is part of it.
        if not self.shape_ok(quad) or inside_any(quad.mean(axis=0), [c.corners for c in found]):
            return None
        if not darker_inside(gray, quad, 0.1, 0.5 * o.min_contrast, solid=True):
            return None
        fit = self.refine(
            gray, quad, iterations=SEARCH_ITERATIONS, max_move_px=1.5 * scale + 1.0, converged_px=SEARCH_CONVERGED_PX
        )
        if fit is not None and self.verify(gray, fit):
            return Candidate(fit.corners, False, fit)
        return None
