"""Per-frame processing with a marker map: detect every map marker in view, one pose from all.

The same face as processing.FrameProcessor (``process(frame) -> FrameResult``, ``reset()``,
``status()``, ``from_config(cfg)``), so the daemon, replay and the outputs take either. The
last pose predicts where untracked map markers should appear (the detector follows them from
there) and is the start of the next solve (continuity on the planar branch).

The attitude (the frame's own, from a recording, else the live one: ``attitude_source``) is a
term of the solve: its roll and pitch give gravity in the camera frame (through the mount),
weighed at the attitude's accuracy. The branch it favours is taken; a pose whose down still
disagrees with it by more than ``[attitude] max_error_deg`` is withheld as "inconsistent",
as on the single-marker path (pose/prior.py).
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable, Dict, Optional, Tuple

import cv2
import numpy as np

from ..attitude import attitude_status
from ..camera import Camera
from ..capture.base import Frame
from ..detect.square import side_lengths
from ..geometry import VehicleFrames, angle_between_deg
from ..marker_map import MarkerMap
from ..pose.map_solve import GravityPrior, largest_marker, map_corners_px, solve_map_pose
from ..pose.prior import Choice, PriorSettings, gate_bound_px
from ..pose.prior_noise import MIN_PRIOR_SIGMA_DEG
from ..pose.types import EstimationError
from ..result import FrameResult


class MapFrameProcessor:
    """detect (MapDetector) -> solve (solve_map_pose) for one map and one camera.

    ``frames``: the camera mount and the map's placement (default: a forward camera);
    ``prior``: the attitude's bounds and default accuracy (PriorSettings);
    ``attitude_source``: an ``attitude_at(t_capture_s, t_now_s)`` (attitude.AutopilotAttitude) asked when a frame
    carries no attitude of its own; ``search``: the default detector's mode of whole-frame
    searches while tracking (MapDetector: "inline", "next_frame", "when_done").
    """

    def __init__(
        self,
        camera: Camera,
        marker_map: MarkerMap,
        *,
        method: str = "iterative",
        iterations: int = 5,
        detector=None,
        frames: Optional[VehicleFrames] = None,
        prior: Optional[PriorSettings] = None,
        attitude_source: Any = None,
        clock: Callable[[], float] = time.monotonic,
        search: str = "next_frame",
    ) -> None:
        from ..detect.multi import MapDetector

        self.camera = camera
        self.map = marker_map
        self.method = method
        self.iterations = iterations
        self.detector = detector if detector is not None else MapDetector(marker_map, camera=camera, search=search)
        self.frames = frames if frames is not None else VehicleFrames.from_settings(placement=marker_map.placement)
        self.prior = prior if prior is not None else PriorSettings()
        self.attitude_source = attitude_source
        self._clock = clock
        self._last: Optional[Tuple[np.ndarray, np.ndarray]] = None
        #: The corners found in the last frame, by id (outliers included).
        self.last_found: Dict[int, np.ndarray] = {}
        self.frames_seen = self.frames_with_own_attitude = 0

    @classmethod
    def from_models(
        cls,
        camera: Camera,
        marker_map: MarkerMap,
        estimator,
        detector,
        *,
        frames: Optional[VehicleFrames] = None,
        prior: Optional[PriorSettings] = None,
        attitude_source: Any = None,
        search: str = "next_frame",
    ) -> MapFrameProcessor:
        """The processor for a camera and a map with a Config's [estimator] and [detector] keys;
        ``frames``, ``prior`` and ``attitude_source`` as for the constructor; ``search``: where
        the detector's whole-frame searches run while tracking (MapDetector: "next_frame" gives
        the same output every run, "when_done" never holds up a tracked frame: the live daemon)."""
        from ..detect.multi import MapDetector

        return cls(
            camera,
            marker_map,
            method=estimator.method,
            iterations=estimator.iterations,
            detector=MapDetector(
                marker_map,
                camera=camera,
                max_misses=detector.max_misses,
                min_side_px=detector.min_side_px,
                search=search,
            ),
            frames=frames,
            prior=prior,
            attitude_source=attitude_source,
        )

    @classmethod
    def from_config(
        cls,
        cfg,
        *,
        attitude_source: Any = None,
        search: str = "next_frame",
        camera: Optional[Camera] = None,
        marker_map: Optional[MarkerMap] = None,
    ) -> MapFrameProcessor:
        """The processor of a Config with a [map]: its camera, map, estimator, detector, mount
        and [attitude] keys; ``attitude_source`` as for the constructor, ``search`` as for
        ``from_models``; ``camera`` and ``marker_map`` in place of the config's (a recording's
        own camera, the map ``map check`` holds against the frames)."""
        marker_map = marker_map if marker_map is not None else cfg.map.model()
        return cls.from_models(
            camera if camera is not None else cfg.camera.model(),
            marker_map,
            cfg.estimator,
            cfg.detector,
            frames=VehicleFrames.from_config(cfg.mount, marker_map.placement),
            prior=PriorSettings.from_config(cfg),
            attitude_source=attitude_source,
            search=search,
        )

    def status(self) -> Optional[str]:
        """The attitude's freshness for the status line (as FrameProcessor.status)."""
        return attitude_status(self.attitude_source, self._clock(), self.frames_with_own_attitude, self.frames_seen)

    def reset(self) -> None:
        self.detector.reset()
        self._last = None

    def close(self) -> None:
        """Stop the detector's worker thread, if it has one."""
        close = getattr(self.detector, "close", None)
        if close is not None:
            close()

    def gravity_prior(self, attitude) -> Optional[GravityPrior]:
        """The solve's prior term for an attitude.Attitude (None for None): gravity in the
        camera frame from roll and pitch through the mount, at the attitude's stated accuracy
        (else ``[attitude] sigma_deg``), never trusted below MIN_PRIOR_SIGMA_DEG."""
        if attitude is None:
            return None
        roll, pitch, _yaw = attitude.rpy_rad
        sigma_deg = (
            math.degrees(attitude.sigma_rad) if attitude.sigma_rad is not None else self.prior.attitude_sigma_deg
        )
        sigma_rad = math.radians(max(sigma_deg, MIN_PRIOR_SIGMA_DEG))
        return GravityPrior(self.frames.down_cam_from_attitude(roll, pitch), sigma_rad, self.map.down_map())

    def process(self, frame: Frame) -> FrameResult:
        result = FrameResult(seq=frame.seq, t_capture_s=frame.t_capture_s, attitude=frame.attitude)
        if result.attitude is None and self.attitude_source is not None:
            result.attitude = self.attitude_source.attitude_at(frame.t_capture_s, self._clock())
        self.frames_seen += 1
        self.frames_with_own_attitude += frame.attitude is not None
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
        prior = self.gravity_prior(result.attitude)
        try:
            pose = solve_map_pose(
                found,
                self.camera,
                self.map,
                previous=self._last,
                prior=prior,
                method=self.method,
                iterations=self.iterations,
            )
        except EstimationError as exc:
            result.error = f"pose: {exc}"
            self._last = None
        else:
            self._accept(pose, found, prior, result)
        result.stage_s["estimate"] = time.perf_counter() - t1
        return result

    def _accept(self, pose, found: Dict[int, np.ndarray], prior: Optional[GravityPrior], result: FrameResult) -> None:
        """The pose into ``result``, or withheld when it disagrees with the attitude."""
        down_err = None
        if prior is not None:
            down_err = angle_between_deg(pose.R @ prior.down_map, prior.down_cam)
            bound_deg = max(self.prior.attitude_bound_deg, 3.0 * math.degrees(prior.sigma_rad))
            # With the prior a term, a pose can follow an attitude the corners disagree with
            # (a small far marker hardly holds its tilt): the corners' fit says so then.
            side_px = max(float(np.mean(side_lengths(found[i]))) for i in pose.marker_ids)
            bound_px = gate_bound_px(self.prior, side_px)
            reason = ""
            if down_err > bound_deg:
                reason = f"the map's down is {down_err:.1f} deg from the attitude's (bound {bound_deg:.1f})"
            elif pose.reprojection_error_px > bound_px:
                reason = (
                    f"no pose agrees with the attitude and the corners: reprojection RMS "
                    f"{pose.reprojection_error_px:.2f} px (bound {bound_px:.2f}), down {down_err:.1f} deg off"
                )
            if reason:
                result.choice = Choice(None, withheld="inconsistent", reason=reason)
                result.error = f"inconsistent: {reason}"
                self._last = None
                return
        # The attitude settled the branch when there was one to settle (a map pose with an
        # ambiguity ratio > 0 had a distinct other branch).
        resolved = "attitude" if prior is not None and pose.ambiguity_ratio > 0 else "clear"
        result.choice = Choice(pose, resolved, down_error_deg=down_err)
        result.pose = pose
        # The largest marker used stands for the frame in the 4-corner "corners" key.
        used = largest_marker(found, pose.marker_ids)
        result.corners = found[used]
        self._last = (pose.R, pose.tvec)
