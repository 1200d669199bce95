"""MapDetector: every marker of a marker map in a grey frame, each tracked like the single marker.

Per frame and per tracked marker, cheapest first: follow its last corners (edge fits where it
is predicted to be, its known bits checked), then search a region around them. Markers not
tracked but predicted in view (the caller projects the map with the last pose) are followed
from the prediction. A whole-frame search, which decodes each dark quadrilateral's bits once
against every id of the map, runs when nothing is tracked, when a track was lost this frame,
and every ``full_every`` frames to pick up what the prediction missed (a moved marker).
OpenCV's ArUco detector is the fallback when our own quadrilaterals give nothing.
"""

from __future__ import annotations

from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np

from ..camera import Camera
from ..capture.base import as_gray
from ..marker_map import MarkerMap
from . import aruco_compat
from .aruco import ArucoFinder
from .quads import Roi, find_quads, inside_any
from .refine import SEARCH_CONVERGED_PX, signed_area
from .square import SquareOptions, darker_inside, median_of, sample_canonical, side_lengths

_UNIT = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=np.float32)


class _Track:
    __slots__ = ("last", "previous", "misses")

    def __init__(self, corners: np.ndarray) -> None:
        self.last = corners
        self.previous: Optional[np.ndarray] = None
        self.misses = 0

    def predict(self) -> np.ndarray:
        if self.previous is None or self.misses:
            return self.last.copy()
        return self.last + (self.last - self.previous)


class _Decoder:
    """Reads a quadrilateral's cells once and finds which map id (and rotation) it is."""

    def __init__(self, dictionary, ids: List[int], options: SquareOptions) -> None:
        self.options = options
        n = int(dictionary.markerSize)
        self.n_bits = n
        cells = n + 2
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
        self.max_bit_errors = int(getattr(dictionary, "maxCorrectionBits", 0))
        perms = []
        for k in range(4):
            H = cv2.getPerspectiveTransform(_UNIT, np.roll(_UNIT, -k, axis=0))
            uv = cv2.perspectiveTransform(self.cell_uv.reshape(-1, 1, 2), H).reshape(-1, 2)
            idx = np.floor(uv * cells).astype(int).clip(0, cells - 1)
            perms.append(idx[:, 1] * cells + idx[:, 0])
        self.perms = np.array(perms)
        expected = []
        for marker_id in ids:
            grid = np.zeros((cells, cells), dtype=bool)
            grid[1:-1, 1:-1] = aruco_compat.marker_bits(dictionary, marker_id).astype(bool)
            expected.append(grid.ravel()[self.inner])
        self.ids = np.array(ids, dtype=np.int64)
        self.expected = np.array(expected)  # (n_ids, n*n)

    def decode(self, gray: np.ndarray, fit) -> Optional[Tuple[int, int]]:
        """(id, k) with the corners rolled by k starting at the marker's top-left, or None."""
        o = self.options
        if fit.residual_px > o.max_edge_residual_px or fit.valid_fraction < 0.6:
            return None
        if fit.contrast < o.min_contrast or side_lengths(fit.corners).min() < o.min_side_px:
            return None
        values = sample_canonical(gray, fit.corners, self.uv)
        n_cells = len(self.cell_uv)
        cells, ring = values[:n_cells], values[n_cells:]
        ring = ring[np.isfinite(ring)]
        if not np.isfinite(cells).all() or len(ring) < 10:
            return None
        dark, light = median_of(cells[self.border]), median_of(ring)
        if light - dark < o.min_contrast:
            return None
        white = cells > 0.5 * (dark + light)
        if np.count_nonzero(white[self.border]) > 1:
            return None
        read = white[self.perms][:, self.inner]  # (4, n*n): the grid as each rotation reads it
        errors = (read[:, None, :] != self.expected[None, :, :]).sum(axis=2)  # (4, n_ids)
        k, j = np.unravel_index(int(np.argmin(errors)), errors.shape)
        if errors[k, j] > self.max_bit_errors:
            return None
        return int(self.ids[j]), int(k)


class MapDetector:
    """Corners {id: (4, 2) TL, TR, BR, BL pixels} of every marker of ``marker_map`` in view.

    Options as MarkerDetector's (``max_misses``, ``min_side_px``, ``camera`` and the finder's
    thresholds), plus ``full_every``: frames between whole-frame searches while tracking.
    """

    def __init__(
        self,
        marker_map: MarkerMap,
        *,
        camera: Optional[Camera] = None,
        max_misses: int = 5,
        min_side_px: float = 10.0,
        full_every: int = 10,
        block_px: int = 25,
        threshold_offset: float = 10.0,
        min_contrast: float = 20.0,
        max_edge_residual_px: float = 0.4,
        max_aspect_ratio_error: float = 3.0,
        roi_margin: float = 0.5,
    ) -> None:
        if not isinstance(marker_map, MarkerMap):
            raise ValueError(f"marker_map must be a MarkerMap, got {type(marker_map).__name__}")
        if isinstance(max_misses, bool) or not isinstance(max_misses, int) or max_misses < 0:
            raise ValueError(f"max_misses must be a non-negative integer, got {max_misses!r}")
        if isinstance(full_every, bool) or not isinstance(full_every, int) or full_every < 1:
            raise ValueError(f"full_every must be a positive integer, got {full_every!r}")
        self.map = marker_map
        self.camera = camera
        self.max_misses = max_misses
        self.full_every = full_every
        self.roi_margin = float(roi_margin)
        self.options = SquareOptions(
            min_side_px=float(min_side_px),
            block_px=int(block_px),
            threshold_offset=float(threshold_offset),
            min_contrast=float(min_contrast),
            max_edge_residual_px=float(max_edge_residual_px),
            max_aspect_ratio_error=float(max_aspect_ratio_error),
        )
        self.finders: Dict[int, ArucoFinder] = {
            i: ArucoFinder(marker_map.single(i), self.options, camera) for i in marker_map.ids
        }
        dictionary = aruco_compat.get_dictionary(marker_map.dictionary)
        self._decoder = _Decoder(dictionary, list(marker_map.ids), self.options)
        self._nests = {i: marker_map.contains_others(i) for i in marker_map.ids}
        self._opencv = aruco_compat.ArucoMarkerFinder(
            dictionary,
            aruco_compat.make_parameters(corner_refine="none", minMarkerPerimeterRate=0.01, minCornerDistanceRate=0.02),
        )
        #: How each marker was found in the last call: id -> "follow", "roi", "predicted" or "full".
        self.last_stages: Dict[int, str] = {}
        #: Whole-frame searches run so far (the costly step).
        self.full_searches = 0
        self.reset()

    def reset(self) -> None:
        """Forget every track: the next frame is searched whole."""
        self._tracks: Dict[int, _Track] = {}
        self._since_full = 0

    @property
    def tracking(self) -> bool:
        return bool(self._tracks)

    def detect(self, image: np.ndarray, predicted: Optional[Dict[int, np.ndarray]] = None) -> Dict[int, np.ndarray]:
        """Corners of every map marker found, by id. ``predicted``: where untracked map markers
        should be ({id: (4, 2) pixels}, e.g. the map projected with the last pose)."""
        gray = as_gray(image)
        if self.camera is not None and gray.shape != (self.camera.height, self.camera.width):
            raise ValueError(
                f"image is {gray.shape[1]}x{gray.shape[0]} but the camera model is "
                f"{self.camera.width}x{self.camera.height}"
            )
        h, w = gray.shape
        found: Dict[int, np.ndarray] = {}
        stages: Dict[int, str] = {}
        lost = False
        if h >= 8 and w >= 8:
            for marker_id, track in self._tracks.items():
                corners, stage = self._find_tracked(gray, marker_id, track.predict(), track.last)
                if corners is not None:
                    found[marker_id], stages[marker_id] = corners, stage
                elif track.misses == 0:
                    lost = True  # lost this frame: look for it (and what replaced it) everywhere once
            for marker_id, corners in (predicted or {}).items():
                if marker_id in found or marker_id in self._tracks or marker_id not in self.finders:
                    continue
                pts = np.asarray(corners, dtype=np.float64).reshape(4, 2)
                if not (np.all(np.isfinite(pts)) and ((pts >= 1.0) & (pts <= [w - 2.0, h - 2.0])).all()):
                    continue
                if signed_area(pts) <= 0 or side_lengths(pts).min() < self.options.min_side_px:
                    continue
                corners, _ = self._find_tracked(gray, marker_id, pts, pts)
                if corners is not None:
                    found[marker_id], stages[marker_id] = corners, "predicted"
            self._since_full += 1
            if not found or lost or self._since_full >= self.full_every:
                self._since_full = 0
                self.full_searches += 1
                for marker_id, corners in self._search_full(gray, found).items():
                    found[marker_id], stages[marker_id] = corners, "full"
        self._update(found)
        self.last_stages = stages
        return {i: c.copy() for i, c in found.items()}

    def _find_tracked(
        self, gray: np.ndarray, marker_id: int, predicted: np.ndarray, last: np.ndarray
    ) -> Tuple[Optional[np.ndarray], Optional[str]]:
        h, w = gray.shape
        finder = self.finders[marker_id]
        if ((predicted >= 1.0) & (predicted <= [w - 2.0, h - 2.0])).all():
            cand = finder.follow(gray, predicted)
            if cand is not None:
                return cand.corners, "follow"
        side = float(side_lengths(last).max())
        roi = self._roi(np.vstack([predicted, last]), side, w, h)
        if roi is not None:
            cands = finder.search(gray, roi, side)
            if cands:
                best = min(cands, key=lambda c: float(np.sum((c.corners - predicted) ** 2)))
                return best.corners, "roi"
        return None, None

    def _roi(self, pts: np.ndarray, side: float, w: int, h: int) -> Optional[Roi]:
        margin = max(self.roi_margin * side, 16.0)
        x0 = int(max(0, np.floor(pts[:, 0].min() - margin)))
        y0 = int(max(0, np.floor(pts[:, 1].min() - margin)))
        x1 = int(min(w, np.ceil(pts[:, 0].max() + margin) + 1))
        y1 = int(min(h, np.ceil(pts[:, 1].max() + margin) + 1))
        if x1 - x0 < 16 or y1 - y0 < 16 or (x1 - x0) * (y1 - y0) > 0.6 * w * h:
            return None
        return x0, y0, x1, y1

    def _search_full(self, gray: np.ndarray, known: Dict[int, np.ndarray]) -> Dict[int, np.ndarray]:
        """Markers not in ``known`` anywhere in the frame: our quadrilaterals, bits decoded once."""
        o = self.options
        out: Dict[int, np.ndarray] = {}
        # Outlines that hide nothing of the map: quads inside them are their own cells.
        blocking = [c for i, c in known.items() if not self._nests[i]]
        refiner = next(iter(self.finders.values()))
        depth = 0.5 / (self._decoder.n_bits + 2)
        scales = (2, 1) if min(gray.shape) >= 240 else (1,)
        for scale in scales:
            for quad in find_quads(
                gray, min_side_px=o.min_side_px, block_px=o.block_px, offset_gray=o.threshold_offset, downscale=scale
            ):
                if inside_any(quad.mean(axis=0), blocking):
                    continue
                if not darker_inside(gray, quad, depth, 0.5 * o.min_contrast):
                    continue
                fit = refiner.refine(
                    gray, quad, iterations=2, max_move_px=1.5 * scale + 1.0, converged_px=SEARCH_CONVERGED_PX
                )
                if fit is None:
                    continue
                decoded = self._decoder.decode(gray, fit)
                if decoded is None:
                    continue
                marker_id, k = decoded
                if marker_id in known or marker_id in out:
                    continue
                corners = np.roll(fit.corners, -k, axis=0)
                out[marker_id] = corners
                if not self._nests[marker_id]:
                    blocking.append(corners)
            if out:
                return out
        return self._search_opencv(gray, known)

    def _search_opencv(self, gray: np.ndarray, known: Dict[int, np.ndarray]) -> Dict[int, np.ndarray]:
        out: Dict[int, np.ndarray] = {}
        corners_list, ids = self._opencv.detect(gray)
        for corners, marker_id in zip(corners_list, ids.tolist()):
            if marker_id not in self.finders or marker_id in known or marker_id in out:
                continue
            pts = corners.astype(np.float64)
            centre = pts.mean(axis=0)
            direction = pts - centre
            direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-9)
            pts = pts + 0.5 * direction
            if signed_area(pts) <= 0 or side_lengths(pts).min() < self.options.min_side_px:
                continue
            fit = self.finders[marker_id].refine(gray, pts, iterations=2, max_move_px=3.0)
            if fit is not None:
                out[marker_id] = fit.corners
        return out

    def _update(self, found: Dict[int, np.ndarray]) -> None:
        for marker_id in list(self._tracks):
            if marker_id not in found:
                track = self._tracks[marker_id]
                track.misses += 1
                track.previous = None
                if track.misses > self.max_misses:
                    del self._tracks[marker_id]
        for marker_id, corners in found.items():
            track = self._tracks.get(marker_id)
            if track is None:
                self._tracks[marker_id] = _Track(corners)
            else:
                track.previous = track.last if track.misses == 0 else None
                track.last = corners
                track.misses = 0
