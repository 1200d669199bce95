"""Per-frame processing with a marker map: detect every map marker in view, one pose from all.

The same face as processing.FrameProcessor (``process(frame) -> FrameResult``, ``reset()``,
``from_config(cfg)``), so the daemon, replay and the outputs take either. The last pose
predicts where untracked map markers should appear (the detector follows them from there)
and is a start of the next solve (continuity on the planar branch).
"""

from __future__ import annotations

import time
from typing import Dict, Optional, Tuple

import cv2
import numpy as np

from .camera import Camera
from .capture.base import Frame
from .marker_map import MarkerMap
from .pose.map_solve import GravityPrior, map_corners_px, solve_map_pose
from .pose.types import EstimationError
from .result import FrameResult


class MapFrameProcessor:
    """detect (MapDetector) -> solve (solve_map_pose) for one map and one camera."""

    def __init__(
        self, camera: Camera, marker_map: MarkerMap, *, method: str = "iterative", iterations: int = 5, detector=None
    ) -> None:
        from .detect.multi import MapDetector

        self.camera = camera
        self.map = marker_map
        self.method = method
        self.iterations = iterations
        self.detector = detector if detector is not None else MapDetector(marker_map, camera=camera)
        self._last: Optional[Tuple[np.ndarray, np.ndarray]] = None
        #: The corners found in the last frame, by id (outliers included).
        self.last_found: Dict[int, np.ndarray] = {}
        #: An attitude prior for the next frame (set by whoever knows the attitude), or None.
        self.prior: Optional[GravityPrior] = None

    @classmethod
    def from_models(cls, camera: Camera, marker_map: MarkerMap, estimator, detector) -> MapFrameProcessor:
        """The processor for a camera and a map with a Config's [estimator] and [detector] keys."""
        from .detect.multi import MapDetector

        return cls(
            camera,
            marker_map,
            method=estimator.method,
            iterations=estimator.iterations,
            detector=MapDetector(
                marker_map, camera=camera, max_misses=detector.max_misses, min_side_px=detector.min_side_px
            ),
        )

    @classmethod
    def from_config(cls, cfg) -> MapFrameProcessor:
        """The processor of a Config with a [map]."""
        return cls.from_models(cfg.camera.model(), cfg.map.model(), cfg.estimator, cfg.detector)

    def reset(self) -> None:
        self.detector.reset()
        self._last = None

    def process(self, frame: Frame) -> FrameResult:
        result = FrameResult(seq=frame.seq, t_capture_s=frame.t_capture_s)
        t0 = time.perf_counter()
        predicted = None
        if self._last is not None:
            predicted = map_corners_px(self.camera, self.map, self._last[0], self._last[1])
        try:
            found = self.detector.detect(frame.image, predicted)
        except (ValueError, cv2.error) as exc:
            result.stage_s["detect"] = time.perf_counter() - t0
            result.error = f"bad frame: {exc}"
            self._last = None
            return result
        t1 = time.perf_counter()
        result.stage_s["detect"] = t1 - t0
        self.last_found = found
        if not found:
            result.error = "no marker"
            self._last = None
            return result
        try:
            pose = solve_map_pose(
                found,
                self.camera,
                self.map,
                previous=self._last,
                prior=self.prior,
                method=self.method,
                iterations=self.iterations,
            )
        except EstimationError as exc:
            result.error = f"pose: {exc}"
            self._last = None
        else:
            result.pose = pose
            # The largest marker used stands for the frame in the 4-corner "corners" key.
            used = max(pose.marker_ids, key=lambda i: float(np.ptp(found[i], axis=0).sum()))
            result.corners = found[used]
            self._last = (pose.R, pose.tvec)
        result.stage_s["estimate"] = time.perf_counter() - t1
        return result
