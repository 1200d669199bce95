"""The ArUco marker: found among the dark quadrilaterals by reading its bits (OpenCV's ArUco
detector as the fallback); its dictionary and id give the orientation. Corners refined by
edge fits, and followed between frames by reading its bits again.
"""

from __future__ import annotations

import math
from typing import Any, List, Optional, Tuple

import cv2
import numpy as np

from ..camera import Marker
from . import aruco_compat, blur_model
from .edge_profiles import EdgeFit, signed_area
from .quads import MIN_COMPACTNESS_CODED, Roi, inside_any
from .refine import SEARCH_CONVERGED_PX, SEARCH_ITERATIONS
from .square import (
    MAX_REACH_PX,
    UNIT_SQUARE,
    Candidate,
    OutlineFinder,
    SquareOptions,
    clamp,
    corner_reach,
    least_width,
    median_of,
    medians_of_rows,
    sample_canonical,
    sample_canonical_many,
    side_lengths,
)

#: OpenCV's ArUco detector, the whole-frame search's safety net, runs in one of every this many
#: whole-frame searches that find nothing with our own passes (and in every region search of
#: a lost track). On the benchmark's frames (main, clutter, blur sweep: 460 with the marker)
#: it never found a marker the own passes missed, and on marker-free clutter it costs more
#: than both own passes together: run every time, it made a marker-free search 1.6-3.4x
#: OpenCV's time, and with the full-size pass in turns (``FULL_PASS_EVERY``) one in 4 still
#: cost as much as OpenCV on a carpet (mean 1.0x); one in 8 keeps a marker only it sees found
#: within 8 frames. It falls on searches without the full-size pass (``FULL_PASS_EVERY``
#: divides it): the two costly steps of a marker-free run take turns.
OPENCV_EVERY = 8


#: Outlines whose cells are narrower than this (pixels) get a second reading, grown ...
SMALL_CELL_PX = 3.0
#: ... by this much at each side (pixels).
GROW_SMALL_PX = 0.7


def grown(quads: np.ndarray, px: float) -> np.ndarray:
    """Outlines (N, 4, 2), image-clockwise, with every side moved ``px`` outwards (each corner
    to where its two moved sides meet)."""
    q = np.asarray(quads, dtype=np.float64)
    d = np.roll(q, -1, axis=1) - q  # side i: corner i -> i + 1
    u = d / np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-12)
    normal = np.stack([u[..., 1], -u[..., 0]], axis=2)  # outward for an image-clockwise outline
    n_in, n_out = np.roll(normal, 1, axis=1), normal  # the sides into and out of each corner
    # The corner moves by px (n_in + n_out) / (1 + n_in . n_out): on both moved lines.
    dot = np.sum(n_in * n_out, axis=2, keepdims=True)
    return q + px * (n_in + n_out) / np.maximum(1.0 + dot, 0.1)


class CellGrid:
    """Where an ArUco marker of ``n_bits`` x ``n_bits`` is read, in unit-square coordinates:
    each cell's centre (the one-cell border included) and a ring of points in the quiet zone;
    which cells are border, and how each quarter turn of the corners permutes the cells (the
    grid read from corners rolled by k is grid[perms[k]])."""

    def __init__(self, n_bits: int) -> None:
        cells = int(n_bits) + 2
        centres = (np.arange(cells) + 0.5) / cells
        uu, vv = np.meshgrid(centres, centres)
        self.cell_uv = np.column_stack([uu.ravel(), vv.ravel()])
        s = np.linspace(0.1, 0.9, 7)
        ring = np.concatenate(
            [
                np.column_stack([s, np.full_like(s, -0.08)]),
                np.column_stack([np.full_like(s, 1.08), s]),
                np.column_stack([s, np.full_like(s, 1.08)]),
                np.column_stack([np.full_like(s, -0.08), s]),
            ]
        )
        self.uv = np.concatenate([self.cell_uv, ring])
        border = np.ones((cells, cells), dtype=bool)
        border[1:-1, 1:-1] = False
        self.border = border.ravel()
        self.inner = ~self.border
        perms = []
        for k in range(4):
            H = cv2.getPerspectiveTransform(UNIT_SQUARE, np.roll(UNIT_SQUARE, -k, axis=0))
            uv = cv2.perspectiveTransform(self.cell_uv.reshape(-1, 1, 2), H).reshape(-1, 2)
            idx = np.floor(uv * cells).astype(int).clip(0, cells - 1)
            perms.append(idx[:, 1] * cells + idx[:, 0])
        self.perms = np.array(perms)

    def read(self, gray: np.ndarray, corners: np.ndarray, min_contrast: float) -> Optional[np.ndarray]:
        """The cells read white (bool, one per cell, row by row) from the outline ``corners``,
        or None when a cell lies outside the frame, the ring is mostly outside, or the quiet
        zone is not lighter than the border by ``min_contrast`` grey levels."""
        values = sample_canonical(gray, corners, self.uv)
        n_cells = len(self.cell_uv)
        cells, ring = values[:n_cells], values[n_cells:]
        ring = ring[np.isfinite(ring)]
        if not np.isfinite(cells).all() or len(ring) < 10:
            return None
        dark, light = median_of(cells[self.border]), median_of(ring)
        if light - dark < min_contrast:
            return None
        return cells > 0.5 * (dark + light)

    def read_fit(self, gray: np.ndarray, fit: EdgeFit, options: SquareOptions) -> Optional[np.ndarray]:
        """``read`` from an edge fit that looks like a marker's outline (straight sides, enough
        contrast and size, by ``options``) whose border reads dark but for one cell; else None."""
        o = options
        if fit.residual_px > o.max_edge_residual_px or fit.valid_fraction < 0.6:
            return None
        if fit.contrast < o.min_contrast or side_lengths(fit.corners).min() < o.min_side_px:
            return None
        white = self.read(gray, fit.corners, o.min_contrast)
        if white is None or np.count_nonzero(white[self.border]) > 1:
            return None
        return white


class FrameFinders:
    """OpenCV's ArUco detector for whole frames (no corner refinement: our edge fits replace
    it), one per frame size, made on first use. One of these per thread that uses it:
    OpenCV's detector objects are never shared between threads.

    The detector's perimeter floor is 4 * (``min_side_px`` - 2) pixels: a candidate below
    it cannot pass the minimum side after its corners move out by half a pixel, so nothing
    we would keep is left out, and on textured clutter the floor of a region search (1 % of
    the larger side) made OpenCV's step 1.4x its own default's time (hundreds of tiny
    candidates)."""

    def __init__(self, dictionary: Any, min_side_px: float) -> None:
        self.dictionary = dictionary
        self.min_side_px = float(min_side_px)
        self._by_size: dict = {}

    def get(self, gray: np.ndarray) -> aruco_compat.ArucoMarkerFinder:
        """The detector for frames of ``gray``'s size."""
        larger = max(gray.shape[:2])
        finder = self._by_size.get(larger)
        if finder is None:
            # OpenCV's floor is a share of the larger side; its ceiling (maxMarkerPerimeterRate)
            # is 4 by default, and the floor may not pass it.
            rate = min(max(4.0 * (self.min_side_px - 2.0), 4.0) / float(larger), 4.0)
            finder = self._by_size[larger] = aruco_compat.ArucoMarkerFinder(
                self.dictionary,
                aruco_compat.make_parameters(
                    corner_refine="none", minMarkerPerimeterRate=rate, minCornerDistanceRate=0.02
                ),
            )
        return finder


class ArucoFinder(OutlineFinder):
    """Finds the configured dictionary + id; corners come out as TL, TR, BR, BL."""

    oriented = True
    # The code is read before any edge fit: thin outlines (oblique views) cost little.
    min_compactness = MIN_COMPACTNESS_CODED

    def __init__(self, marker: Marker, options: SquareOptions, camera=None) -> None:
        super().__init__(marker, options, camera)
        if marker.dictionary is None or marker.id is None:  # Marker refuses these already
            raise ValueError("an aruco marker needs a dictionary and an id")
        self.dictionary = aruco_compat.get_dictionary(marker.dictionary)
        n_ids = aruco_compat.dictionary_size(self.dictionary)
        if not 0 <= int(marker.id) < n_ids:
            raise ValueError(f"ArUco id {marker.id} is not in {marker.dictionary} (ids 0..{n_ids - 1})")
        self.marker_id = int(marker.id)
        self.bits = aruco_compat.marker_bits(self.dictionary, self.marker_id)
        self.n_bits = int(self.bits.shape[0])
        self.border_fraction = 1.0 / (self.n_bits + 2)
        self.max_bit_errors = int(getattr(self.dictionary, "maxCorrectionBits", 0))
        # Our own edge fits replace OpenCV's refinement, so it is switched off. This one
        # searches a lost track's region: OpenCV's perimeter floor is a share of the image's
        # larger side, and a region is small.
        self._finder = aruco_compat.ArucoMarkerFinder(
            self.dictionary,
            aruco_compat.make_parameters(corner_refine="none", minMarkerPerimeterRate=0.01, minCornerDistanceRate=0.02),
        )
        # Whole frames.
        self._frame_finders = FrameFinders(self.dictionary, options.min_side_px)
        self._grid = CellGrid(self.n_bits)
        cells = self.n_bits + 2
        expected = np.zeros((cells, cells), dtype=bool)
        expected[1:-1, 1:-1] = self.bits.astype(bool)
        self._expected_white = expected.ravel()
        self._model = blur_model.MarkerModel(expected)
        # The last accepted model fit's blur, where a tracked frame's fit starts (``polish``).
        self._model_start: Optional[blur_model.BlurStart] = None
        # The inner cells' indices in each rotation (4, n_bits^2), and their expected colour.
        self._inner_perms = np.array([perm[self._grid.inner] for perm in self._grid.perms])
        self._expected_inner = self._expected_white[self._grid.inner]

    def reach_px(self, corners: np.ndarray):
        # Across the border, not along it: a thin rhombus (seen obliquely along a diagonal)
        # has a border far thinner than its sides are long.
        side = least_width(corners)
        cell = side / (self.n_bits + 2)
        # Inside, stay within the one-cell black border; outside, within the quiet zone.
        return clamp(0.6 * cell, 1.0, 3.0), clamp(0.15 * side, 1.5, MAX_REACH_PX)

    def orientation(self, gray: np.ndarray, fit: EdgeFit) -> Optional[int]:
        """k such that the corners rolled by k start at the marker's top-left, or None if
        this is not the marker: straight sides, dark border, light quiet zone, its bits."""
        grid = self._grid
        white = grid.read_fit(gray, fit, self.options)
        if white is None:
            return None
        for k, perm in enumerate(grid.perms):
            errors = np.count_nonzero(white[perm][grid.inner] != self._expected_white[grid.inner])
            if errors <= self.max_bit_errors:
                return k
        return None

    def could_be(self, gray: np.ndarray, quad: np.ndarray) -> bool:
        """Early rejection, before any sub-pixel work: the code read from the rough outline
        (about a pixel off, so with one more bit error and border cell allowed). Rejects
        the dark squares of a board, print and texture at a fraction of an edge fit's cost."""
        white = self._grid.read(gray, quad, 0.5 * self.options.min_contrast)
        if white is None or np.count_nonzero(white[self._grid.border]) > 2:
            return False
        errors = np.count_nonzero(white[self._inner_perms] != self._expected_inner, axis=1)
        return bool(errors.min() <= self.max_bit_errors + 1)

    def could_be_many(self, gray: np.ndarray, quads: np.ndarray) -> np.ndarray:
        """``could_be`` of each outline in ``quads`` (N, 4, 2): (N,) bool. A small outline
        (cells under SMALL_CELL_PX) the code does not match is read again grown by
        GROW_SMALL_PX at each side: the threshold's outline runs along the dark region's
        boundary pixels, up to a pixel inside its edge, half a cell of a 16 px 6x6 marker."""
        quads = np.asarray(quads, dtype=np.float64).reshape(-1, 4, 2)
        ok = self._could_be_many(gray, quads)
        if ok.all():
            return ok
        least = np.array([least_width(q) for q in quads]) if len(quads) else np.zeros(0)
        again = np.flatnonzero(~ok & (least < SMALL_CELL_PX * (self.n_bits + 2)))
        if len(again):
            ok[again] = self._could_be_many(gray, grown(quads[again], GROW_SMALL_PX))
        return ok

    def _could_be_many(self, gray: np.ndarray, quads: np.ndarray) -> np.ndarray:
        """``could_be`` of each outline (N, 4, 2) as read. From 3 outlines on in one pass (one
        remap, the medians and bit counts as array operations: in clutter a pass gives
        20-100); below, one at a time is cheaper."""
        if len(quads) < 3:
            return np.array([self.could_be(gray, q) for q in quads], dtype=bool)
        values = sample_canonical_many(gray, quads, self._grid.uv)
        n_cells = len(self._grid.cell_uv)
        cells, ring = values[:, :n_cells], values[:, n_cells:]
        ok = np.isfinite(cells).all(axis=1) & (np.isfinite(ring).sum(axis=1) >= 10)
        cells = np.where(ok[:, None], cells, 0.0)
        border = cells[:, self._grid.border]
        dark = np.partition(border, border.shape[1] // 2, axis=1)[:, border.shape[1] // 2]
        light = medians_of_rows(np.where(ok[:, None], ring, 0.0))
        ok &= light - dark >= 0.5 * self.options.min_contrast
        white = cells > 0.5 * (dark + light)[:, None]
        ok &= white[:, self._grid.border].sum(axis=1) <= 2
        # Bit errors against the marker's code in each of its 4 rotations: (N, 4).
        errors = (white[:, self._inner_perms] != self._expected_inner).sum(axis=2)
        return ok & (errors.min(axis=1) <= self.max_bit_errors + 1)

    def verify(self, gray: np.ndarray, fit: EdgeFit) -> bool:
        """Is this the marker, with the corners already labelled TL, TR, BR, BL?"""
        return self.orientation(gray, fit) == 0

    def border_model_below_px(self) -> float:
        # Edges blurred enough for the model of the whole marker need no border model (it
        # would only cost: the model takes the code's light into account itself).
        return blur_model.MODEL_MIN_BLUR_PX if self.options.blur_model else math.inf

    def restart_searches(self) -> None:
        super().restart_searches()
        self._model_start = None

    def polish(self, gray: np.ndarray, cand: Candidate, tracked: bool = False) -> Candidate:
        """The marker's corners from the model of its whole blurred pattern (``blur_model``)
        where its edges are blurred and the model describes the frame; else ``cand``.
        ``tracked``: the marker followed from the last frame, whose model fit's blur the fit
        starts from (from a round blur again when that is not accepted)."""
        fit = cand.fit
        start, self._model_start = (self._model_start if tracked else None), None
        if not self.options.blur_model or fit is None or fit.blur_px < blur_model.MODEL_MIN_BLUR_PX:
            return cand
        quiet_px = self.reach_px(cand.corners)[1]
        least = None if fit.side_blur_px is None else float(fit.side_blur_px.min())
        model_fit = self._model.fit(gray, cand.corners, fit.blur_px, quiet_px, least, self.lut, start)
        if start is not None and not blur_model.accept(model_fit, cand.corners, fit.blur_px):
            model_fit = self._model.fit(gray, cand.corners, fit.blur_px, quiet_px, least, self.lut)
        if model_fit is None or not blur_model.accept(model_fit, cand.corners, fit.blur_px):
            return cand
        self._model_start = model_fit.start
        return Candidate(model_fit.corners, True, fit)

    def follow(self, gray: np.ndarray, predicted: np.ndarray) -> Optional[Candidate]:
        cand = super().follow(gray, predicted)
        return None if cand is None else self.polish(gray, cand, tracked=True)

    def try_quad(self, gray: np.ndarray, quad: np.ndarray, scale: int, found: List[Candidate]) -> Optional[Candidate]:
        """A rough outline -> the marker (refined, labelled) or None; the code is read from
        the rough outline first, the edges fitted only when it may be the marker."""
        # Quads come largest first: one inside a marker already found is part of it.
        if inside_any(quad.mean(axis=0), [c.corners for c in found]):
            return None
        # (could_be also checks that the border is darker than the quiet zone.)
        if not self.could_be(gray, quad):
            return None
        return self._fit_quad(gray, quad, scale)

    def _fit_quad(self, gray: np.ndarray, quad: np.ndarray, scale: int) -> Optional[Candidate]:
        """An outline that passed ``could_be`` -> the marker (edges fitted, labelled) or None."""
        fit = self.refine(
            gray,
            quad,
            iterations=SEARCH_ITERATIONS,
            max_move_px=(1.5 * scale + 1.0) * corner_reach(quad),
            converged_px=SEARCH_CONVERGED_PX,
        )
        if fit is None:
            return None
        k = self.orientation(gray, fit)
        return None if k is None else self.polish(gray, Candidate(np.roll(fit.corners, -k, axis=0), True, fit))

    def stages(self, gray: np.ndarray, roi: Optional[Roi]) -> List[Tuple[str, int]]:
        """Our own quadrilaterals and bit reading first (cheap); OpenCV's ArUco detector, with
        its several threshold scales, when they find nothing: in a region search always, in a
        whole-frame search in the first of a run (after ``reset`` or a lost track: a marker
        only it sees, such as one 70-80 deg off its face with 11-13 px short sides, is then
        found on first sight, not up to 8 frames later) and once in ``OPENCV_EVERY`` fruitless
        ones after it (the 8th, 16th, ...)."""
        own = super().stages(gray, roi)
        runs = self.fruitless_searches
        if roi is not None or runs == 0 or runs % OPENCV_EVERY == OPENCV_EVERY - 1:
            return own + [("opencv", 1)]
        return own

    def stage_items(self, gray: np.ndarray, stage: Tuple[str, int], roi: Optional[Roi], block: int) -> list:
        """A threshold pass's rough outlines that may be the marker (``could_be``, all at once)."""
        if stage[0] == "opencv":
            return [None]
        quads = super().stage_items(gray, stage, roi, block)
        if not quads:
            return quads
        keep = self.could_be_many(gray, np.array(quads)).tolist()
        return [q for q, k in zip(quads, keep) if k]

    def process(
        self, gray: np.ndarray, stage: Tuple[str, int], item, roi: Optional[Roi], found: List[Candidate]
    ) -> List[Candidate]:
        if stage[0] == "opencv":
            return self._search_opencv(gray, roi)
        # The stage's items passed could_be already (stage_items).
        if inside_any(item.mean(axis=0), [c.corners for c in found]):
            return []
        cand = self._fit_quad(gray, item, stage[1])
        return [] if cand is None else [cand]

    def _search_opencv(self, gray: np.ndarray, roi: Optional[Roi]) -> List[Candidate]:
        """OpenCV's step: the marker in ``roi`` (a lost track's region) or the whole frame."""
        x0, y0 = 0, 0
        if roi is not None:
            x0, y0, x1, y1 = roi
            img, finder = gray[y0:y1, x0:x1], self._finder
        else:
            img, finder = gray, self._frame_finders.get(gray)
        corners_list, ids = finder.detect(img)
        out: List[Candidate] = []
        for corners, marker_id in zip(corners_list, ids):
            if int(marker_id) != self.marker_id:
                continue
            # OpenCV's corners sit on the boundary pixels of the dark border: move them out
            # by half a pixel onto its edge before fitting.
            pts = corners.astype(np.float64)
            centre = pts.mean(axis=0)
            direction = pts - centre
            direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-9)
            pts = pts + 0.5 * direction + (x0, y0)
            if signed_area(pts) <= 0 or side_lengths(pts).min() < self.options.min_side_px:
                continue
            fit = self.refine(gray, pts, iterations=2, max_move_px=3.0)
            if fit is None:
                continue
            out.append(self.polish(gray, Candidate(fit.corners, True, fit)))
        return out
