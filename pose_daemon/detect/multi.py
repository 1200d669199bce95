"""MapDetector: every marker of a marker map in a grey frame, each tracked like the single marker.

Per frame and per tracked marker, cheapest first: follow its last corners (edge fits where it
is predicted to be), then search a region around them. A followed marker keeps the id its
track was decoded with: its bits are read again only every ``id_check_every`` frames, or at
once when the fit looks unlike the marker it has been (see ``ID_CHECK_EVERY``). A marker partly
out of the frame is followed by the edge fit of its visible sides (its corners outside the
frame are extrapolated; the solve leaves them out). Markers not
tracked but predicted in view (the caller projects the map with the last pose) are followed
from the prediction. A whole-frame search, which decodes each dark quadrilateral's bits once
against every id of the map, runs when nothing is tracked, when a track was lost this frame,
and every ``full_every`` frames to pick up what the prediction missed (a moved marker).
OpenCV's ArUco detector is the fallback when our own quadrilaterals give nothing.

The whole-frame search is the costly step (several times a tracked frame with many markers in
view). While some markers are followed it need not hold up the frame: with ``search`` =
"next_frame" or "when_done" it runs on a worker thread (OpenCV's threshold, contours and ArUco
detector release the GIL, so it runs on another core) and the frame goes on with what it
followed. What the search found (markers not followed) becomes tracks that later frames follow
from there. "next_frame" hands them to the next frame, which waits for the search if needed:
the same frames give the same output every run (replay, tests). "when_done" hands them to the
first frame after the search ends, never waiting (the live daemon: a tracked frame is never
late for it). Acquisition (nothing followed) searches in the frame itself in every mode.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Any, Dict, Optional, Tuple

import cv2
import numpy as np

from ..camera import Camera
from ..image import as_gray
from ..marker_map import MarkerMap
from . import aruco_compat
from .aruco import ArucoFinder, FrameFinders
from .edge_profiles import EdgeFit, signed_area
from .map_decode import MapDecoder
from .partial import MIN_PARTIAL_CORNERS, corners_inside, fit_partial
from .quads import Roi, find_quads, inside_any
from .refine import SEARCH_CONVERGED_PX
from .refine_many import fit_edges_many
from .square import SquareOptions, darker_inside, side_lengths

#: A followed marker's bits are read again once in this many frames (and at once when its edge
#: fit turns poor, below). Between reads the fit alone checks it: straight sides, dark border
#: against a light quiet zone, its size. That catches a marker covered, bent or gone (the fit
#: fails) but not one replaced by another marker of the same dictionary in the same place (the
#: outline is the same); such a swap is noticed at the next read, so it keeps the wrong id for
#: at most this many frames (0.13 s at 30 fps), during which the solve's outlier test has it;
#: the frame it is noticed, the whole-frame search decodes what is there now. The read is
#: about an eighth of a follow's cost (the edge fit is the rest).
ID_CHECK_EVERY = 4
#: ... read at once when the fit's RMS residual passes this share of ``max_edge_residual_px``,
ID_CHECK_RESIDUAL_SHARE = 0.5
#: ... or its edge contrast falls below this share of the contrast at the last read (a shadow,
#: a print over it, another marker's lighter cells touching the border).
ID_CHECK_CONTRAST_SHARE = 0.7

#: Where a whole-frame search runs while markers are followed (see the module's notes).
SEARCH_MODES = ("inline", "next_frame", "when_done")

#: Edge-fit passes of a follow (it starts from a prediction that is nearly right).
FOLLOW_ITERATIONS = 2
#: ``_find_tracked``'s ``fit`` when no batch fitted the marker (it is fitted on its own).
_NOT_FITTED = object()


class _Track:
    __slots__ = ("last", "previous", "misses", "since_read", "contrast")

    def __init__(self, corners: np.ndarray) -> None:
        self.last = corners
        self.previous: Optional[np.ndarray] = None
        self.misses = 0
        #: Followed frames since its bits were last read (0: read on the frame it started).
        self.since_read = 0
        #: Edge contrast of the fit when its bits were last read (None: not followed yet).
        self.contrast: Optional[float] = None

    def predict(self) -> np.ndarray:
        if self.previous is None or self.misses:
            return self.last.copy()
        return self.last + (self.last - self.previous)


class MapDetector:
    """Corners {id: (4, 2) TL, TR, BR, BL pixels} of every marker of ``marker_map`` in view.

    Options as MarkerDetector's (``max_misses``, ``min_side_px``, ``camera`` and the finder's
    thresholds), plus ``full_every``: frames between whole-frame searches while tracking,
    ``id_check_every``: a followed marker's bits are read once in this many frames (1: every
    frame), at once when its fit turns poor, and ``search``: where a whole-frame search runs
    while markers are followed, one of ``SEARCH_MODES`` ("inline": in the frame itself;
    "next_frame", "when_done": on a worker thread, see the module's notes).
    """

    def __init__(
        self,
        marker_map: MarkerMap,
        *,
        camera: Optional[Camera] = None,
        max_misses: int = 5,
        min_side_px: float = 10.0,
        full_every: int = 10,
        id_check_every: int = ID_CHECK_EVERY,
        block_px: int = 25,
        threshold_offset: float = 10.0,
        min_contrast: float = 20.0,
        max_edge_residual_px: float = 0.4,
        max_aspect_ratio_error: float = 3.0,
        roi_margin: float = 0.5,
        search: str = "inline",
    ) -> None:
        if not isinstance(marker_map, MarkerMap):
            raise ValueError(f"marker_map must be a MarkerMap, got {type(marker_map).__name__}")
        if isinstance(max_misses, bool) or not isinstance(max_misses, int) or max_misses < 0:
            raise ValueError(f"max_misses must be a non-negative integer, got {max_misses!r}")
        if isinstance(full_every, bool) or not isinstance(full_every, int) or full_every < 1:
            raise ValueError(f"full_every must be a positive integer, got {full_every!r}")
        if isinstance(id_check_every, bool) or not isinstance(id_check_every, int) or id_check_every < 1:
            raise ValueError(f"id_check_every must be a positive integer, got {id_check_every!r}")
        if search not in SEARCH_MODES:
            raise ValueError(f"search must be one of {', '.join(SEARCH_MODES)}, got {search!r}")
        self.search = search
        self._worker: Optional[ThreadPoolExecutor] = None
        self._pending: Optional[Future] = None
        self.map = marker_map
        self.id_check_every = id_check_every
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
        self._decoder = MapDecoder(dictionary, list(marker_map.ids), self.options)
        self._nests = {i: marker_map.contains_others(i) for i in marker_map.ids}
        self._opencv = FrameFinders(dictionary, self.options.min_side_px)
        #: How each marker was found in the last call: id -> "follow", "partial" (partly out of the
        #: frame), "roi", "predicted" or "full".
        self.last_stages: Dict[int, str] = {}
        #: Whole-frame searches run so far (the costly step), and those run on the worker.
        self.full_searches = 0
        self.background_searches = 0
        #: Markers the worker's searches found that were not followed (new tracks).
        self.background_found = 0
        #: Bit reads of followed markers so far, and those that found another marker (a swap).
        self.id_reads = 0
        self.id_mismatches = 0
        self.reset()

    def reset(self) -> None:
        """Forget every track: the next frame is searched whole."""
        self._drop_pending()
        self._tracks: Dict[int, _Track] = {}
        self._since_full = 0

    def close(self) -> None:
        """Stop the worker thread (a search under way is waited for); the detector still works
        afterwards (a new worker starts when one is needed)."""
        self._drop_pending()
        if self._worker is not None:
            self._worker.shutdown(wait=True)
            self._worker = None

    def wait_for_search(self, timeout_s: Optional[float] = None) -> bool:
        """Wait until the worker's search (if any) has ended; False when ``timeout_s`` passed
        first. Its result is taken by the next ``detect``."""
        pending = self._pending
        if pending is None:
            return True
        try:
            pending.exception(timeout=timeout_s)
        except FutureTimeout:  # (not the builtin TimeoutError before Python 3.11)
            return False
        return True

    @property
    def search_pending(self) -> bool:
        """Is a whole-frame search under way on the worker (or done and not yet taken)?"""
        return self._pending is not None

    def _drop_pending(self) -> None:
        pending, self._pending = getattr(self, "_pending", None), None
        if pending is not None:
            pending.exception()  # finished before anything else uses the detector; its result is not needed

    def _take_search(self, wait: bool) -> None:
        """The worker's search into the tracks: each marker it found that is not tracked now
        starts a track from where the search saw it (its bits were read there)."""
        if self._pending is None or not (wait or self._pending.done()):
            return
        pending, self._pending = self._pending, None
        try:
            result = pending.result()
        except (ValueError, cv2.error):
            return  # a frame the search could not take: the next search looks again
        for marker_id, corners in result.items():
            if marker_id not in self._tracks:
                self._tracks[marker_id] = _Track(corners)
                self.background_found += 1

    def _start_search(self, gray: np.ndarray, known: Dict[int, np.ndarray]) -> None:
        if self._worker is None:
            self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="map-search")
        self.background_searches += 1
        self._pending = self._worker.submit(self._search_full, gray.copy(), {i: c.copy() for i, c in known.items()})

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
        self._take_search(wait=self.search == "next_frame")
        if h >= 8 and w >= 8:
            starts: Dict[int, np.ndarray] = {}
            for marker_id, track in self._tracks.items():
                start = track.predict()
                if marker_id in (predicted or {}) and not corners_inside(start, w, h).all():
                    # Partly out of the frame: where the map pose puts its corners outside is
                    # better than where its track (corners extrapolated before) would.
                    pts = np.asarray(predicted[marker_id], dtype=np.float64).reshape(4, 2)  # type: ignore[index]
                    if np.all(np.isfinite(pts)):
                        start = pts + (start - track.last).mean(axis=0)
                starts[marker_id] = start
            untracked: Dict[int, np.ndarray] = {}
            for marker_id, corners in (predicted or {}).items():
                if marker_id in self._tracks or marker_id not in self.finders:
                    continue
                pts = np.asarray(corners, dtype=np.float64).reshape(4, 2)
                if not np.all(np.isfinite(pts)):
                    continue
                if int(((pts >= 1.0) & (pts <= [w - 2.0, h - 2.0])).all(axis=1).sum()) < MIN_PARTIAL_CORNERS:
                    continue
                if signed_area(pts) <= 0 or side_lengths(pts).min() < self.options.min_side_px:
                    continue
                untracked[marker_id] = pts
            # The edge fits of every marker followed this frame, all in one batch.
            fits = self._follow_fits(gray, {**starts, **untracked})
            for marker_id, track in self._tracks.items():
                got, stage = self._find_tracked(
                    gray, marker_id, starts[marker_id], track.last, track, fits.get(marker_id, _NOT_FITTED)
                )
                if got is not None and stage is not None:
                    found[marker_id], stages[marker_id] = got, stage
                elif track.misses == 0:
                    lost = True  # lost this frame: look for it (and what replaced it) everywhere once
            for marker_id, pts in untracked.items():
                got, _ = self._find_tracked(gray, marker_id, pts, pts, None, fits.get(marker_id, _NOT_FITTED))
                if got is not None:
                    found[marker_id], stages[marker_id] = got, "predicted"
            self._since_full += 1
            if found and self.search != "inline":
                # Tracking: the search goes to the worker (one at a time), the frame on.
                if (lost or self._since_full >= self.full_every) and self._pending is None:
                    self._since_full = 0
                    self.full_searches += 1
                    self._start_search(gray, found)
            elif not found or lost or self._since_full >= self.full_every:
                self._drop_pending()  # nothing followed: this frame's own search finds it all
                self._since_full = 0
                self.full_searches += 1
                for marker_id, corners in self._search_full(gray, found).items():
                    found[marker_id], stages[marker_id] = corners, "full"
        self._update(found)
        self.last_stages = stages
        return {i: c.copy() for i, c in found.items()}

    def _find_tracked(
        self,
        gray: np.ndarray,
        marker_id: int,
        predicted: np.ndarray,
        last: np.ndarray,
        track: Optional[_Track] = None,
        fit: Any = _NOT_FITTED,
    ) -> Tuple[Optional[np.ndarray], Optional[str]]:
        """``fit``: the edge fit of ``predicted`` from ``_follow_fits`` (``_NOT_FITTED``: none)."""
        h, w = gray.shape
        finder = self.finders[marker_id]
        inside = corners_inside(predicted, w, h)
        if inside.all():
            corners = self._follow(gray, finder, predicted, track, fit)
            if corners is not None:
                return corners, "follow"
        elif int(inside.sum()) >= MIN_PARTIAL_CORNERS:
            corners = self._follow_partial(gray, finder, predicted)
            if corners is not None:
                if track is not None:  # its bits cannot be read here: due a read once wholly in view
                    track.since_read += 1
                return corners, "partial"
            return None, None
        side = float(side_lengths(last).max())
        roi = self._roi(np.vstack([predicted, last]), side, w, h)
        if roi is not None:
            cands = finder.search(gray, roi, side)
            if cands:
                best = min(cands, key=lambda c: float(np.sum((c.corners - predicted) ** 2)))
                if track is not None:  # the region search read its bits
                    track.since_read, track.contrast = 0, best.fit.contrast if best.fit is not None else None
                return best.corners, "roi"
        return None, None

    def _follow_fits(self, gray: np.ndarray, starts: Dict[int, np.ndarray]) -> Dict[int, Optional[EdgeFit]]:
        """The follow's edge fit (``_follow``) of every marker whose start lies wholly in the
        frame, all in one ``fit_edges_many`` batch: what one ``finder.refine`` each gives, but
        for the border model of defocused ArUco edges (``fit_edges``'s ``border_fraction``),
        which the batch does not take: on `bench map`'s frames (0.15-0.20 m markers 30-100 px
        across, 0.8 px blur) it moved the map's figures slightly the wrong way."""
        h, w = gray.shape
        ids = [i for i, c in starts.items() if corners_inside(c, w, h).all()]
        if not ids:
            return {}
        reach = [self.finders[i].reach_px(starts[i]) for i in ids]
        finder = self.finders[ids[0]]
        fits = fit_edges_many(
            gray,
            [starts[i] for i in ids],
            reach,
            max_move_px=[0.8 * min(inner, outer) + 0.5 for inner, outer in reach],
            iterations=FOLLOW_ITERATIONS,
            camera=finder.camera,
            min_contrast=0.5 * self.options.min_contrast,
            lut=finder.lut,
            check_blur=False,
        )
        return dict(zip(ids, fits))

    def _follow(
        self,
        gray: np.ndarray,
        finder: ArucoFinder,
        predicted: np.ndarray,
        track: Optional[_Track],
        fit: Any = _NOT_FITTED,
    ) -> Optional[np.ndarray]:
        """The marker near ``predicted`` (all corners in the frame): the edge fit of
        ``finder.follow`` (``fit``, when ``_follow_fits`` made it), its bits read only when
        ``track`` is due a read (``ID_CHECK_EVERY``), its fit turned poor, or there is no
        track (a marker predicted from the map pose)."""
        o = self.options
        if fit is _NOT_FITTED:
            inner, outer = finder.reach_px(predicted)
            fit = finder.refine(
                gray,
                predicted,
                iterations=FOLLOW_ITERATIONS,
                max_move_px=0.8 * min(inner, outer) + 0.5,
                reach=(inner, outer),
                check_blur=False,
            )
        if fit is None:
            return None
        # The fit's own checks (those the bit read starts with): they cost nothing more.
        if fit.residual_px > o.max_edge_residual_px or fit.valid_fraction < 0.6:
            return None
        if fit.contrast < o.min_contrast or side_lengths(fit.corners).min() < o.min_side_px:
            return None
        if track is not None:
            if track.contrast is None:
                track.contrast = fit.contrast  # the first follow after its bits were decoded
            due = (
                track.since_read + 1 >= self.id_check_every
                or fit.residual_px > ID_CHECK_RESIDUAL_SHARE * o.max_edge_residual_px
                or fit.contrast < ID_CHECK_CONTRAST_SHARE * track.contrast
            )
            if not due:
                track.since_read += 1
                return fit.corners
        self.id_reads += 1
        if not finder.verify(gray, fit):
            if track is not None:
                self.id_mismatches += 1
                track.since_read = self.id_check_every  # read again until it is found by its bits
            return None
        if track is not None:
            track.since_read, track.contrast = 0, fit.contrast
        return fit.corners

    def _follow_partial(self, gray: np.ndarray, finder: ArucoFinder, predicted: np.ndarray) -> Optional[np.ndarray]:
        """A map marker partly out of the frame, where the track or the map pose puts it
        (``partial.fit_partial``)."""
        inner, outer = finder.reach_px(predicted)
        return fit_partial(
            gray,
            predicted,
            inner_px=inner,
            outer_px=outer,
            lut=getattr(finder, "lut", None),
            options=self.options,
            camera=self.camera,
        )

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
        corners_list, ids = self._opencv.get(gray).detect(gray)
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
            known = self._tracks.get(marker_id)
            if known is None:
                self._tracks[marker_id] = _Track(corners)
            else:
                known.previous = known.last if known.misses == 0 else None
                known.last = corners
                known.misses = 0
