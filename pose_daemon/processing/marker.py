"""Per-frame processing shared by the daemon and replay: detect the corners, estimate the pose.

FrameProcessor only runs the stages; each runs inside ``timed(result, stage)``, so the
per-stage latency in ``FrameResult.stage_s`` is a by-product. Never raises for a bad frame:
the FrameResult says what went wrong. The choice between a plain square's two planar
solutions is pose/prior.py's (attitude, tilt prior and quality gate), falling back on
pose/continuity.py's track.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Optional

import cv2
import numpy as np

from ..attitude import attitude_status
from ..camera import Camera, Marker
from ..capture.base import Frame
from ..config import Config, DetectorConfig, EstimatorConfig
from ..detect import MarkerDetector
from ..geometry import VehicleFrames, angle_between_deg
from ..pose.continuity import Track, choose_by_continuity
from ..pose.estimator import estimate_pose
from ..pose.heading_reference import HeadingReference
from ..pose.heading_track import HeadingTrack
from ..pose.prior import PriorSettings, choose_solution
from ..pose.prior_noise import MIN_PRIOR_SIGMA_DEG, AttitudeAccuracy, CornerNoise
from ..pose.types import EstimationError, Pose
from ..result import FrameResult

#: A tracked plain square is the same square while one of its planar solutions' normals stays
#: within this of the track's smoothed normal (degrees): far more than a frame's turn at 30 fps.
TRACK_SAME_SQUARE_DEG = 20.0


def mean_side_px(corners: np.ndarray) -> float:
    """The mean side length of four corners (4, 2), pixels: on plain floats, to the bit what
    ``np.mean(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1))`` gives at a
    sixteenth of its cost (numpy's per-call overhead on four points, every frame)."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = np.asarray(corners, dtype=np.float64).tolist()
    s = math.sqrt((x0 - x3) * (x0 - x3) + (y0 - y3) * (y0 - y3))
    s += math.sqrt((x1 - x0) * (x1 - x0) + (y1 - y0) * (y1 - y0))
    s += math.sqrt((x2 - x1) * (x2 - x1) + (y2 - y1) * (y2 - y1))
    s += math.sqrt((x3 - x2) * (x3 - x2) + (y3 - y2) * (y3 - y2))
    return s / 4.0


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
    """detect -> estimate -> choose the planar solution, for one marker and one camera."""

    def __init__(
        self,
        camera: Camera,
        marker: Marker,
        *,
        method: str = "iterative",
        iterations: int = 5,
        refine: bool = True,
        detector=None,
        frames: Optional[VehicleFrames] = None,
        prior: Optional[PriorSettings] = None,
        attitude_source: Any = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``frames``: mount and placement (default: forward camera, wall marker); ``prior``:
        the gate and tilt bounds; ``attitude_source``: an ``attitude_at(t_capture_s, t_now_s)``
        (attitude.AutopilotAttitude) asked when a frame carries no attitude of its own."""
        self.camera = camera
        self.marker = marker
        self.method = method
        self.iterations = iterations
        self.refine = refine
        self.detector = detector if detector is not None else MarkerDetector(marker, camera=camera)
        self.track = Track()
        self.frames = frames if frames is not None else VehicleFrames.from_settings()
        self.prior = prior if prior is not None else PriorSettings()
        self.attitude_source = attitude_source
        self._clock = clock
        # The autopilot's heading reference against the marker's: outlives tracks.
        self.heading = HeadingReference()
        # Without attitude, a wall marker's recent headings (the tilt prior's): one per track.
        window_s = self.prior.heading_window_s
        self.heading_track = HeadingTrack(window_s) if window_s > 0 else None
        self.corner_noise = CornerNoise()
        # How well the attitude agrees with the image (its lag, the mount): outlives tracks.
        self.attitude_accuracy = AttitudeAccuracy()
        self.frames_seen = self.frames_with_own_attitude = 0

    @classmethod
    def from_models(
        cls,
        camera: Camera,
        marker: Marker,
        estimator: EstimatorConfig,
        detector: DetectorConfig,
        *,
        frames: Optional[VehicleFrames] = None,
        prior: Optional[PriorSettings] = None,
        attitude_source: Any = None,
    ) -> FrameProcessor:
        """The processor for a camera and marker model with the [estimator] and [detector]
        keys of a Config (replay takes the camera and marker from the recording); ``frames``,
        ``prior`` and ``attitude_source`` as for the constructor (defaults: its defaults)."""
        return cls(
            camera,
            marker,
            method=estimator.method,
            iterations=estimator.iterations,
            refine=estimator.refine,
            detector=MarkerDetector(
                marker,
                max_misses=detector.max_misses,
                min_side_px=detector.min_side_px,
                camera=camera,
                gamma=detector.gamma,
                gamma_shoulder=detector.gamma_shoulder,
                search_budget_ms=detector.search_budget_ms or None,
                blur_model=detector.blur_model,
            ),
            frames=frames,
            prior=prior,
            attitude_source=attitude_source,
        )

    @classmethod
    def from_config(cls, cfg: Config, *, attitude_source: Any = None) -> FrameProcessor:
        """The processor a Config asks for: its camera, marker (or map), estimator, detector,
        mount, [attitude] and [gate] keys; ``attitude_source`` as for the constructor (a [map]
        gives a MapFrameProcessor, asking the same source)."""
        if cfg.map is not None:
            from .map import MapFrameProcessor

            return MapFrameProcessor.from_config(cfg, attitude_source=attitude_source)  # type: ignore[return-value]
        return cls.from_models(
            cfg.camera.model(),
            cfg.marker.model(),
            cfg.estimator,
            cfg.detector,
            frames=VehicleFrames.from_config(cfg.mount, cfg.placement),
            prior=PriorSettings.from_config(cfg),
            attitude_source=attitude_source,
        )

    @property
    def flips(self) -> int:
        """Frames whose ambiguous pose was flipped to the alternative (by continuity or a prior)."""
        return self.track.flips

    def status(self) -> Optional[str]:
        """The attitude's freshness for the status line: the live source's figures, or how
        many frames came with an attitude of their own (None when none ever did); then, once
        measured, how well its down agrees with the image's (AttitudeAccuracy)."""
        text = attitude_status(self.attitude_source, self._clock(), self.frames_with_own_attitude, self.frames_seen)
        measured = self.attitude_accuracy.measured_deg
        if text is None or measured is None:
            return text
        return f"{text}, agrees with the image to {measured:.1f} deg"

    def reset(self) -> None:
        """Forget tracking state (after a source restart or a long gap)."""
        self.detector.reset()
        self._lose_track()

    def _lose_track(self) -> None:
        self.track.reset()
        if self.heading_track is not None:
            self.heading_track.reset()

    def process(self, frame: Frame) -> FrameResult:
        result = FrameResult(seq=frame.seq, t_capture_s=frame.t_capture_s, attitude=frame.attitude)
        if result.attitude is None and self.attitude_source is not None:
            result.attitude = self.attitude_source.attitude_at(frame.t_capture_s, self._clock())
        self.frames_seen += 1
        self.frames_with_own_attitude += frame.attitude is not None
        try:
            with timed(result, "detect"):
                corners: Optional[np.ndarray] = (
                    # The capture time scales the track's prediction; other detectors take the image only.
                    self.detector.detect(frame.image, t_capture_s=frame.t_capture_s)
                    if isinstance(self.detector, MarkerDetector)
                    else self.detector.detect(frame.image)
                )
        except (ValueError, cv2.error) as exc:
            # A camera glitch (wrong size, empty or corrupt buffer) costs this frame only.
            result.error = f"bad frame: {exc}"
            self._lose_track()
            return result
        if corners is None:
            result.error = "no marker"
            self._lose_track()  # lost: the next sighting starts a new track
            return result
        result.corners = corners
        with timed(result, "estimate"):
            try:
                pose = estimate_pose(
                    corners,
                    self.camera,
                    self.marker,
                    method=self.method,
                    iterations=self.iterations,
                    refine=self.refine,
                )
            except EstimationError as exc:
                result.error = f"pose: {exc}"
                self._lose_track()
            else:
                result.pose = self._choose(pose, corners, result)
        return result

    def _identified(self, pose: Pose) -> bool:
        """Whether the corners are known to be the marker's whatever the view: an ArUco marker's
        id was decoded; a plain square was followed by the detector's track (not searched
        afresh) from a pose already sent, and one of its planar solutions turns no more than
        TRACK_SAME_SQUARE_DEG from the track's normal. Only then is a plain square past
        ``max_view_deg`` sent (a long rectangle fits a square seen that obliquely)."""
        if self.marker.type == "aruco":
            return True
        if self.track.normal_ref is None or getattr(self.detector, "last_stage", None) not in ("follow", "roi"):
            return False
        normals = [pose.R[:, 2]] + ([pose.alternative.R[:, 2]] if pose.alternative is not None else [])
        return min(angle_between_deg(n, self.track.normal_ref) for n in normals) <= TRACK_SAME_SQUARE_DEG

    def _choose(self, pose: Pose, corners: np.ndarray, result: FrameResult) -> Optional[Pose]:
        """The prior's choice between the planar solutions (the track's where the prior has no
        say), or None with ``result.error`` saying why the pose is withheld. The track follows
        the pose finally sent; a withheld pose leaves it as it was."""
        side_px = mean_side_px(corners)
        choice = choose_solution(
            pose,
            self.frames,
            attitude=result.attitude,
            settings=self.prior,
            side_px=side_px,
            by_continuity=lambda p: choose_by_continuity(p, self.track.normal_ref),
            corners_px=corners,
            camera=self.camera,
            marker=self.marker,
            heading=self.heading,
            corner_sigma_px=self.corner_noise.estimate_px(pose.reprojection_error_px),
            heading_track=self.heading_track,
            t_capture_s=float(result.t_capture_s),
            attitude_accuracy=self.attitude_accuracy,
            identified=self._identified(pose),
        )
        result.corner_sigma_px = self.corner_noise.sigma_px
        result.corner_noise_pending = result.corner_sigma_px is None
        self.corner_noise.observe(pose.reprojection_error_px)
        result.choice = choice
        if choice.pose is None:
            result.error = f"{choice.withheld}: {choice.reason}"
            if choice.withheld == "inconsistent":
                # No solution agrees with the attitude or the tilt bound: the track's corner
                # labels may be what is wrong (a plain square's are kept by continuity, and a
                # gap of a second or more can turn them a quarter turn): the next frame is
                # searched and labelled afresh.
                self.detector.reset()
            return None
        if self.prior.polish and choice.attitude_sigma_deg is not None:
            # The choice re-fitted the pose towards the attitude's down (or found it agreeing):
            # the covariance sent takes that information in, at the accuracy it was weighed at.
            result.prior_down_sigma_rad = math.radians(max(choice.attitude_sigma_deg, MIN_PRIOR_SIGMA_DEG))
        t_s = float(result.t_capture_s)
        result.track_innovation = self.track.follow(choice.pose, flipped=choice.flipped, t_capture_s=t_s)
        return choice.pose
