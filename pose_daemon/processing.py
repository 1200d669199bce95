"""Per-frame processing shared by the daemon and replay: detect the corners, estimate the pose.

Times itself per stage, so latency figures are a by-product. Never raises for a bad frame:
the FrameResult says what went wrong. A plain square has two planar solutions that fit its
corners almost equally well; when the estimator says the choice is a guess, the one closer to
the previous frame's pose is kept (continuity), and a lost marker starts a new track.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Optional

import cv2
import numpy as np

from .camera import Camera, Marker
from .capture.base import Frame
from .pose.types import EstimationError, Pose
from .result import FrameResult

# Pose.ambiguity_ratio (best residual / alternative's) from which the alternative is a real
# contender: with a small or distant square and 0.3 px of corner noise the wrong planar solution
# often fits best with a ratio as low as 0.15, so "near 1" is far too strict.
AMBIGUOUS_RATIO = 0.1
# Weight of the newest pose in the track's smoothed marker normal: one wrong pick must not
# drag the reference onto the wrong branch (measured: alone, the previous pose did worse).
NORMAL_SMOOTHING = 0.3


def _normal_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


def choose_by_continuity(pose: Pose, normal_ref: Optional[np.ndarray]) -> Pose:
    """The planar solution whose marker normal (R[:, 2], camera frame) is closer to the
    track's ``normal_ref`` when ``pose`` is ambiguous; else ``pose`` itself.

    The returned pose keeps the estimator's ambiguity_ratio and carries the other solution
    as its ``alternative``.
    """
    alt = pose.alternative
    if normal_ref is None or alt is None or not pose.ambiguity_ratio >= AMBIGUOUS_RATIO:
        return pose
    if _normal_angle_deg(alt.R[:, 2], normal_ref) >= _normal_angle_deg(pose.R[:, 2], normal_ref):
        return pose
    return dataclasses.replace(alt, alternative=dataclasses.replace(pose, alternative=None),
                               ambiguity_ratio=pose.ambiguity_ratio)


class FrameProcessor:
    """detect -> estimate for one marker and one camera."""

    def __init__(self, camera: Camera, marker: Marker, *, method: str = "iterative",
                 iterations: int = 5, refine: bool = True, detector=None) -> None:
        from .detect import MarkerDetector
        from .pose.estimator import estimate_pose

        self.camera = camera
        self.marker = marker
        self.method = method
        self.iterations = iterations
        self.refine = refine
        self.detector = detector if detector is not None else MarkerDetector(marker, camera=camera)
        self._estimate = estimate_pose
        # The track: smoothed marker normal in the camera frame (None = no track).
        self._normal_ref: Optional[np.ndarray] = None
        # Frames whose ambiguous pose was flipped to the alternative by continuity.
        self.flips = 0

    @classmethod
    def from_config(cls, cfg) -> FrameProcessor:
        """The processor a Config asks for: its camera, marker (or map), estimator and detector keys."""
        from .detect import MarkerDetector

        if getattr(cfg, "map", None) is not None:
            from .map_processing import MapFrameProcessor

            return MapFrameProcessor.from_config(cfg)

        camera, marker = cfg.camera.model(), cfg.marker.model()
        detector = MarkerDetector(marker, max_misses=cfg.detector.max_misses,
                                  min_side_px=cfg.detector.min_side_px, camera=camera)
        return cls(camera, marker, method=cfg.estimator.method,
                   iterations=cfg.estimator.iterations, refine=cfg.estimator.refine,
                   detector=detector)

    def reset(self) -> None:
        """Forget tracking state (after a source restart or a long gap)."""
        self.detector.reset()
        self._normal_ref = None

    def process(self, frame: Frame) -> FrameResult:
        result = FrameResult(seq=frame.seq, t_capture_s=frame.t_capture_s)
        t0 = time.perf_counter()
        try:
            corners: Optional[np.ndarray] = self.detector.detect(frame.image)
        except (ValueError, cv2.error) as exc:
            # A camera glitch (wrong size, empty or corrupt buffer) costs this frame only.
            result.stage_s["detect"] = time.perf_counter() - t0
            result.error = f"bad frame: {exc}"
            self._normal_ref = None
            return result
        t1 = time.perf_counter()
        result.stage_s["detect"] = t1 - t0
        if corners is None:
            result.error = "no marker"
            self._normal_ref = None  # lost: the next sighting starts a new track
            return result
        result.corners = corners
        try:
            pose = self._estimate(corners, self.camera, self.marker, method=self.method,
                                  iterations=self.iterations, refine=self.refine)
        except EstimationError as exc:
            result.error = f"pose: {exc}"
            self._normal_ref = None
        else:
            chosen = choose_by_continuity(pose, self._normal_ref)
            if chosen is not pose:
                self.flips += 1
            n = chosen.R[:, 2]
            self._normal_ref = n.copy() if self._normal_ref is None else (
                (1.0 - NORMAL_SMOOTHING) * self._normal_ref + NORMAL_SMOOTHING * n)
            result.pose = chosen
        result.stage_s["estimate"] = time.perf_counter() - t1
        return result
