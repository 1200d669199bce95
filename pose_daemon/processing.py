"""Per-frame processing shared by the daemon and replay: detect the corners, estimate the pose.

FrameProcessor only runs the stages; each runs inside ``timed(result, stage)``, so the
per-stage latency in ``FrameResult.stage_s`` is a by-product. Never raises for a bad frame:
the FrameResult says what went wrong. The choice between a plain square's two planar
solutions is pose/continuity.py's.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Iterator, Optional

import cv2
import numpy as np

from .camera import Camera, Marker
from .capture.base import Frame
from .config import DetectorConfig, EstimatorConfig
from .detect import MarkerDetector
from .pose.continuity import Track
from .pose.estimator import estimate_pose
from .pose.types import EstimationError
from .result import FrameResult


@contextmanager
def timed(result: FrameResult, stage: str) -> Iterator[None]:
    """Record the wall time of the block in ``result.stage_s[stage]`` (seconds), also when the
    block raises."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        result.stage_s[stage] = time.perf_counter() - t0


class FrameProcessor:
    """detect -> estimate for one marker and one camera."""

    def __init__(self, camera: Camera, marker: Marker, *, method: str = "iterative",
                 iterations: int = 5, refine: bool = True, detector=None) -> None:
        self.camera = camera
        self.marker = marker
        self.method = method
        self.iterations = iterations
        self.refine = refine
        self.detector = detector if detector is not None else MarkerDetector(marker, camera=camera)
        self.track = Track()

    @classmethod
    def from_models(cls, camera: Camera, marker: Marker, estimator: EstimatorConfig,
                    detector: DetectorConfig) -> FrameProcessor:
        """The processor for a camera and marker model with the [estimator] and [detector]
        keys of a Config (replay takes the camera and marker from the recording)."""
        return cls(camera, marker, method=estimator.method, iterations=estimator.iterations,
                   refine=estimator.refine,
                   detector=MarkerDetector(marker, max_misses=detector.max_misses,
                                           min_side_px=detector.min_side_px, camera=camera,
                                           gamma=detector.gamma))

    @classmethod
    def from_config(cls, cfg) -> FrameProcessor:
        """The processor a Config asks for: its camera, marker (or map), estimator and detector keys."""
        if getattr(cfg, "map", None) is not None:
            from .map_processing import MapFrameProcessor

            return MapFrameProcessor.from_config(cfg)
        return cls.from_models(cfg.camera.model(), cfg.marker.model(), cfg.estimator, cfg.detector)

    @property
    def flips(self) -> int:
        """Frames whose ambiguous pose was flipped to the alternative by continuity."""
        return self.track.flips

    def reset(self) -> None:
        """Forget tracking state (after a source restart or a long gap)."""
        self.detector.reset()
        self.track.reset()

    def process(self, frame: Frame) -> FrameResult:
        result = FrameResult(seq=frame.seq, t_capture_s=frame.t_capture_s)
        try:
            with timed(result, "detect"):
                corners: Optional[np.ndarray] = self.detector.detect(frame.image)
        except (ValueError, cv2.error) as exc:
            # A camera glitch (wrong size, empty or corrupt buffer) costs this frame only.
            result.error = f"bad frame: {exc}"
            self.track.reset()
            return result
        if corners is None:
            result.error = "no marker"
            self.track.reset()  # lost: the next sighting starts a new track
            return result
        result.corners = corners
        with timed(result, "estimate"):
            try:
                pose = estimate_pose(corners, self.camera, self.marker, method=self.method,
                                     iterations=self.iterations, refine=self.refine)
            except EstimationError as exc:
                result.error = f"pose: {exc}"
                self.track.reset()
            else:
                result.pose = self.track.choose(pose)
        return result
