"""Per-frame processing shared by the daemon and replay: detect the corners, estimate the pose.

Times itself per stage, so latency figures are a by-product. Never raises for a bad frame:
the FrameResult says what went wrong.
"""

from __future__ import annotations

import time
from typing import Optional

import numpy as np

from .camera import Camera, Marker
from .capture.base import Frame
from .pose.types import EstimationError
from .result import FrameResult


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
        self.detector = detector if detector is not None else MarkerDetector(marker)
        self._estimate = estimate_pose

    def reset(self) -> None:
        """Forget tracking state (after a source restart or a long gap)."""
        self.detector.reset()

    def process(self, frame: Frame) -> FrameResult:
        result = FrameResult(seq=frame.seq, t_capture_s=frame.t_capture_s)
        t0 = time.perf_counter()
        corners: Optional[np.ndarray] = self.detector.detect(frame.image)
        t1 = time.perf_counter()
        result.stage_s["detect"] = t1 - t0
        if corners is None:
            result.error = "no marker"
            return result
        result.corners = corners
        try:
            result.pose = self._estimate(corners, self.camera, self.marker, method=self.method,
                                         iterations=self.iterations, refine=self.refine)
        except EstimationError as exc:
            result.error = f"pose: {exc}"
        result.stage_s["estimate"] = time.perf_counter() - t1
        return result
