"""MarkerDetector: the marker's four corners in a grey frame, tracked from frame to frame.

Per frame, cheapest first: follow the last corners (edge fits where the marker is predicted
to be), then search a region around them, then the whole frame. A track survives
``max_misses`` frames without the marker. Corner labels: an ArUco marker's pattern gives
them; a plain square is 4-fold symmetric, so the first detection assumes |roll| < 45 deg and
later ones keep the labels continuous with the previous frame (a rectangle clearly longer
one way reads right up to |roll| < 90 deg).
"""

from __future__ import annotations

import math
import os
import time
from typing import Callable, List, NamedTuple, Optional, Tuple

import numpy as np

from ..camera import Camera, Marker
from ..image import as_gray
from .quads import Roi
from .response import Response, check_response, check_shoulder
from .square import MAX_REACH_PX, Candidate, SquareFinder, SquareOptions, aspect_error, side_lengths

#: Which step found the marker in the last call: "follow", "roi", "full" or None (not found).
STAGES = ("follow", "roi", "full")


class SearchRecord(NamedTuple):
    """What one ``detect`` call searched (``MarkerDetector.last_search``), for the preview.

    Made once per frame from what the search had at hand (a tuple, no image copied); the
    rectangles are worked out only when asked for.
    """

    #: The step that found the marker ("follow", "roi", "full") or None.
    stage: Optional[str]
    #: The corners the follow step fitted edges from (4, 2) pixels, or None when it did not run.
    #: Not written to after the frame (each frame predicts a fresh array).
    predicted_px: Optional[np.ndarray]
    #: The region the roi step searched, (x0, y0, x1, y1) pixels (x1, y1 exclusive), or None.
    roi_px: Optional[Roi]
    #: The whole-frame search: None (did not run), "done" or "deferred" (stopped at the
    #: time cap, going on next frame).
    full: Optional[str]

    @property
    def steps(self) -> Tuple[str, ...]:
        """The steps that ran, in order."""
        ran = (
            ("follow", self.predicted_px is not None),
            ("roi", self.roi_px is not None),
            ("full", self.full is not None),
        )
        return tuple(name for name, did in ran if did)

    @property
    def regions(self) -> Tuple[Tuple[str, Roi], ...]:
        """(step, (x0, y0, x1, y1)) per region searched, pixels (x1, y1 exclusive): for follow
        the predicted corners' bounding box grown by the edge profiles' reach
        (``MAX_REACH_PX``), for roi its region. The whole frame is not listed (see ``full``)."""
        out: List[Tuple[str, Roi]] = []
        if self.predicted_px is not None:
            p = self.predicted_px
            x0, y0 = (math.floor(float(v) - MAX_REACH_PX) for v in p.min(axis=0))
            x1, y1 = (math.ceil(float(v) + MAX_REACH_PX) + 1 for v in p.max(axis=0))
            out.append(("follow", (x0, y0, x1, y1)))
        if self.roi_px is not None:
            out.append(("roi", self.roi_px))
        return tuple(out)


_NOTHING_SEARCHED = SearchRecord(None, None, None, None)


def _cyclic_shift_to(corners: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Relabel clockwise corners so each lands nearest its previous label (continuity)."""
    c, r = corners.tolist(), reference.tolist()
    costs = [
        sum((c[(i + k) % 4][0] - r[i][0]) ** 2 + (c[(i + k) % 4][1] - r[i][1]) ** 2 for i in range(4)) for k in range(4)
    ]
    k = costs.index(min(costs))
    return corners[[(i + k) % 4 for i in range(4)]]


def _upright_labels(corners: np.ndarray, aspect_w_h: float = 1.0) -> np.ndarray:
    """Labels for a first sighting: the top side (TL->TR, and BL->BR) points closest to +x.

    For a rectangle clearly longer one way (``aspect_w_h`` = W/H), the sides that look
    longer are taken as its width first when the image agrees, so |roll| up to 90 deg reads
    right; a square's labels assume |roll| < 45 deg.
    """
    c = corners.tolist()
    best_k, best_key = 0, (2, 0.0)
    for k in range(4):
        tl, tr, br, bl = (c[(i + k) % 4] for i in range(4))
        top_x, top_y = tr[0] - tl[0] + br[0] - bl[0], tr[1] - tl[1] + br[1] - bl[1]
        cos = top_x / max(math.hypot(top_x, top_y), 1e-12)
        rank = 0
        if abs(math.log(aspect_w_h)) > 0.2:
            across = math.hypot(tr[0] - tl[0], tr[1] - tl[1]) + math.hypot(br[0] - bl[0], br[1] - bl[1])
            down = math.hypot(bl[0] - tl[0], bl[1] - tl[1]) + math.hypot(br[0] - tr[0], br[1] - tr[1])
            measured = math.log(max(across, 1e-9) / max(down, 1e-9))
            # Only a clear elongation in the image decides; perspective can squash either way.
            if abs(measured) > 0.2 and (measured > 0) != (aspect_w_h > 1.0):
                rank = 1
        key = (rank, -cos)
        if key < best_key:
            best_k, best_key = k, key
    return corners[[(i + best_k) % 4 for i in range(4)]]


def _rms_distance(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


class MarkerDetector:
    """Corners of ``marker`` (TL, TR, BR, BL, pixels) in grey frames, with tracking.

    Keyword options (all optional):
    - ``max_misses`` (5): frames the track survives without the marker; then it is forgotten.
    - ``min_side_px`` (10.0): shortest side accepted, pixels.
    - ``camera``: a Camera with lens distortion makes the side fits happen in undistorted
      pixels (sides are straight only there); without it the image is taken as distortion-free.
    - ``block_px`` (25): adaptive threshold window for a full-frame search of a square marker.
    - ``threshold_offset`` (10.0): grey levels below the local mean that count as dark.
    - ``min_contrast`` (20.0): least grey-level difference between surround and marker.
    - ``max_edge_residual_px`` (0.4): RMS distance of edge points to their fitted sides.
    - ``max_aspect_ratio_error`` (3.0): factor by which the outline's W:H may differ from
      the marker's (perspective).
    - ``roi_margin`` (0.5): the tracked search region extends this fraction of the marker's
      size (at least 16 px) around the predicted corners.
    - ``gamma`` (1.0): the camera's response, a power-law exponent (1.0 = linear intensity,
      about 2.2 for sRGB/Rec. 709 cameras) or "srgb"; edges are located in linear intensity,
      so that blur does not shrink the marker (see detect/response.py).
    - ``gamma_shoulder`` (0.0): how much the response's exponent rises from black to white
      (``gamma`` is its value at mid grey; 0 = a power law; detect/response.py).
    - ``blur_model`` (True): an ArUco marker whose edges are blurred (sigma >= 1.2 px) gets its
      corners from a model of its whole blurred pattern fitted to the frame (see
      detect/blur_model.py): unbiased by the code's light and less noisy than the edge fits,
      at 2-6 ms more per such frame here. False: edge fits only. A square marker has no
      pattern to model: it is unaffected.
    - ``search_budget_ms`` (None = no cap): time cap per frame, from the call to ``detect``,
      for a whole-frame search. The search runs cheapest first (half-size threshold, full
      size, then OpenCV's ArUco detector; in a run of searches that find nothing, the full
      size in one of every ``square.FULL_PASS_EVERY`` and OpenCV's detector in one of every
      ``aruco.OPENCV_EVERY``) and checks the clock before each candidate; at
      the cap it stops and the next frame's search goes on from there (``search_deferrals``
      counts such frames). Each frame does at least one step, so the search always advances.
    - ``clock`` (time.perf_counter): the clock of that cap, seconds.
    - ``search_threads`` (None = 2 on a machine with 4 or more cores, else 1): 2 lets a
      whole-frame search after a fruitless one trace the full-size pass's outlines on
      another core while its half-size pass runs. Same results.
    """

    def __init__(
        self,
        marker: Marker,
        *,
        max_misses: int = 5,
        min_side_px: float = 10.0,
        camera: Optional[Camera] = None,
        block_px: int = 25,
        threshold_offset: float = 10.0,
        min_contrast: float = 20.0,
        max_edge_residual_px: float = 0.4,
        max_aspect_ratio_error: float = 3.0,
        roi_margin: float = 0.5,
        gamma: Response = 1.0,
        gamma_shoulder: float = 0.0,
        search_budget_ms: Optional[float] = None,
        clock: Callable[[], float] = time.perf_counter,
        search_threads: Optional[int] = None,
        blur_model: bool = True,
    ) -> None:
        if not isinstance(marker, Marker):
            raise ValueError(f"marker must be a pose_daemon.Marker, got {type(marker).__name__}")
        if isinstance(max_misses, bool) or not isinstance(max_misses, (int, np.integer)) or max_misses < 0:
            raise ValueError(f"max_misses must be a non-negative integer, got {max_misses!r}")
        checks = (
            ("min_side_px", min_side_px, 1.0),
            ("block_px", block_px, 3),
            ("min_contrast", min_contrast, 1.0),
            ("max_edge_residual_px", max_edge_residual_px, 0.01),
            ("max_aspect_ratio_error", max_aspect_ratio_error, 1.0),
            ("roi_margin", roi_margin, 0.0),
            ("threshold_offset", threshold_offset, 0.0),
        )
        for name, value, lowest in checks:
            if not isinstance(value, (int, float)) or not np.isfinite(value) or value < lowest:
                raise ValueError(f"{name} must be a number >= {lowest}, got {value!r}")
        if search_budget_ms is not None and (
            isinstance(search_budget_ms, bool)
            or not isinstance(search_budget_ms, (int, float))
            or not np.isfinite(search_budget_ms)
            or search_budget_ms <= 0
        ):
            raise ValueError(f"search_budget_ms must be a number > 0 or None, got {search_budget_ms!r}")
        if search_threads is not None and (
            isinstance(search_threads, bool)
            or not isinstance(search_threads, (int, np.integer))
            or not 1 <= search_threads <= 64
        ):
            raise ValueError(f"search_threads must be an integer in [1, 64] or None, got {search_threads!r}")
        if not isinstance(blur_model, (bool, np.bool_)):
            raise ValueError(f"blur_model must be True or False, got {blur_model!r}")
        if not callable(clock):
            raise ValueError(f"clock must be a callable returning seconds, got {clock!r}")
        if camera is not None and not isinstance(camera, Camera):
            raise ValueError(f"camera must be a pose_daemon.Camera, got {type(camera).__name__}")
        self.marker = marker
        self.camera = camera
        self.max_misses = int(max_misses)
        self.roi_margin = float(roi_margin)
        self.options = SquareOptions(
            min_side_px=float(min_side_px),
            block_px=int(block_px),
            threshold_offset=float(threshold_offset),
            min_contrast=float(min_contrast),
            max_edge_residual_px=float(max_edge_residual_px),
            max_aspect_ratio_error=float(max_aspect_ratio_error),
            gamma=check_response(gamma),
            gamma_shoulder=check_shoulder(gamma_shoulder, check_response(gamma)),
            blur_model=bool(blur_model),
        )
        if marker.type == "aruco":
            from .aruco import ArucoFinder

            self._finder = ArucoFinder(marker, self.options, camera)
        else:
            self._finder = SquareFinder(marker, self.options, camera)
        if search_threads is None:
            search_threads = 2 if (os.cpu_count() or 1) >= 4 else 1
        self._finder.use_threads(int(search_threads))
        self.last_stage: Optional[str] = None
        #: What the last ``detect`` call searched (a SearchRecord), None before the first.
        self.last_search: Optional[SearchRecord] = None
        self.search_budget_s = None if search_budget_ms is None else float(search_budget_ms) / 1e3
        self._clock = clock
        #: Frames whose whole-frame search stopped at ``search_budget_ms``, leaving the rest
        #: of it to the next frame.
        self.search_deferrals = 0
        #: Whether the last frame's whole-frame search was cut short by the cap.
        self.last_search_deferred = False
        self._deadline = math.inf
        self.reset()

    # ------------------------------------------------------------------ state

    def reset(self) -> None:
        """Forget the track: the next frame is searched whole, with every step of the search
        (see ``FULL_PASS_EVERY``), and labelled afresh."""
        self._forget_track()
        self._finder.restart_searches()
        self._cursor: Tuple[int, int] = (0, 0)  # where an interrupted whole-frame search goes on

    def _forget_track(self) -> None:
        self._last: Optional[np.ndarray] = None
        self._previous: Optional[np.ndarray] = None
        # Capture times of _last and _previous (None when the caller gives no times).
        self._t_last: Optional[float] = None
        self._t_previous: Optional[float] = None
        self._t_now: Optional[float] = None
        self.misses = 0

    @property
    def tracking(self) -> bool:
        """True while a track exists (found in the last ``max_misses + 1`` frames)."""
        return self._last is not None

    # ------------------------------------------------------------------ detection

    def detect(self, image: np.ndarray, t_capture_s: Optional[float] = None) -> Optional[np.ndarray]:
        """The marker's corners (4, 2) float64 pixels TL, TR, BR, BL, or None if not seen.

        ``image``: grey uint8 (H, W) (BGR/BGRA and uint16 are converted). ValueError for
        something that is not an image. ``t_capture_s``: the frame's capture time; with it the
        track's velocity is scaled to the time since the last sighting (frames a pipeline
        dropped, an uneven rate), without it each frame is taken as one step.
        """
        self._t_now = None if t_capture_s is None else float(t_capture_s)
        if self.search_budget_s is not None:
            self._deadline = self._clock() + self.search_budget_s
        self.last_search_deferred = False
        gray = as_gray(image)
        if self.camera is not None and gray.shape != (self.camera.height, self.camera.width):
            raise ValueError(
                f"image is {gray.shape[1]}x{gray.shape[0]} but the camera model is "
                f"{self.camera.width}x{self.camera.height}"
            )
        found, search = self._find(gray)
        self.last_search = search
        self.last_stage = search.stage
        if found is None:
            self.misses += 1
            self._previous = None  # no velocity across a gap
            if self.misses > self.max_misses:
                # The track is lost; a capped whole-frame search still goes on where it stopped.
                self._forget_track()
            return None
        self._previous = self._last if self.misses == 0 else None
        self._t_previous = self._t_last if self.misses == 0 else None
        self._last, self._t_last = found, self._t_now
        self.misses = 0
        return found.copy()

    def _find(self, gray: np.ndarray) -> Tuple[Optional[np.ndarray], SearchRecord]:
        h, w = gray.shape
        if h < 8 or w < 8:
            return None, _NOTHING_SEARCHED
        if self._last is None:
            found = self._pick_first(self._full_search(gray))
            return found, SearchRecord("full" if found is not None else None, None, None, self._full_outcome())
        predicted = self._predict()
        inside = ((predicted >= 1.0) & (predicted <= [w - 2.0, h - 2.0])).all()
        followed = predicted if inside else None
        if inside:
            cand = self._finder.follow(gray, predicted)
            if cand is not None:
                return self._label(cand, predicted), SearchRecord("follow", followed, None, None)
        side = float(side_lengths(self._last).max())
        roi = self._roi(predicted, side, w, h)
        if roi is not None:
            found = self._pick_continuous(self._finder.search(gray, roi, side), predicted)
            if found is not None:
                return found, SearchRecord("roi", followed, roi, None)
        found = self._pick_continuous(self._full_search(gray), predicted)
        return found, SearchRecord("full" if found is not None else None, followed, roi, self._full_outcome())

    def _full_outcome(self) -> str:
        return "deferred" if self.last_search_deferred else "done"

    def _full_search(self, gray: np.ndarray) -> List[Candidate]:
        """The whole frame, within the frame's time cap (if any), going on from where the
        last capped search stopped."""
        if self.search_budget_s is None:
            return self._finder.search(gray)
        deadline, clock = self._deadline, self._clock
        cands, cursor = self._finder.search_from(gray, start=self._cursor, over=lambda: clock() >= deadline)
        if cursor is None:
            self._cursor = (0, 0)
        else:
            self._cursor = cursor
            self.search_deferrals += 1
            self.last_search_deferred = True
        return cands

    def _predict(self) -> np.ndarray:
        """Where the corners should be now: constant velocity over the last two frames.

        With capture times, the last step is scaled to the time since the last frame, never
        beyond one step: after a gap between the last two frames (frames dropped, 2 s at 2
        fps) a whole step extrapolated the gap's motion, turn included, into one frame
        period, and a plain square's labels, kept nearest the prediction, came out a quarter
        turn off for good (every frame then 'inconsistent' with the attitude)."""
        assert self._last is not None
        if self._previous is None:
            return self._last.copy()
        scale = 1.0
        if self._t_now is not None and self._t_last is not None and self._t_previous is not None:
            step_s = self._t_last - self._t_previous
            scale = min(max((self._t_now - self._t_last) / step_s, 0.0), 1.0) if step_s > 0 else 0.0
        return self._last + scale * (self._last - self._previous)

    def _roi(self, predicted: np.ndarray, side: float, w: int, h: int) -> Optional[Roi]:
        pts = np.vstack([predicted, self._last])
        margin = max(self.roi_margin * side, 16.0)
        x0 = int(max(0, np.floor(pts[:, 0].min() - margin)))
        y0 = int(max(0, np.floor(pts[:, 1].min() - margin)))
        x1 = int(min(w, np.ceil(pts[:, 0].max() + margin) + 1))
        y1 = int(min(h, np.ceil(pts[:, 1].max() + margin) + 1))
        if x1 - x0 < 16 or y1 - y0 < 16:
            return None
        if (x1 - x0) * (y1 - y0) > 0.6 * w * h:
            return None  # as costly as the whole frame: skip straight to it
        return x0, y0, x1, y1

    def _label(self, cand: Candidate, reference: Optional[np.ndarray]) -> np.ndarray:
        if cand.oriented:
            return cand.corners
        if reference is None:
            return _upright_labels(cand.corners, self.marker.width / self.marker.height)
        return _cyclic_shift_to(cand.corners, reference)

    def _pick_first(self, cands: List[Candidate]) -> Optional[np.ndarray]:
        """No track: the candidate closest to the marker's shape; the larger one on a tie."""
        if not cands:
            return None

        def key(c: Candidate):
            labelled = self._label(c, None)
            return (round(aspect_error(labelled, self.marker), 1), -float(side_lengths(labelled).sum()))

        return self._label(min(cands, key=key), None)

    def _pick_continuous(self, cands: List[Candidate], predicted: np.ndarray) -> Optional[np.ndarray]:
        """With a track: the candidate closest to where the marker was predicted."""
        if not cands:
            return None
        labelled = [self._label(c, predicted) for c in cands]
        return min(labelled, key=lambda c: _rms_distance(c, predicted))
