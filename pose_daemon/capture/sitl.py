"""The ``sitl`` source: frames rendered from a simulator's true vehicle pose (sitl_link.py), with
the configured camera at the configured mount, of the marker, map or pad lying under where the
vehicle stood when the source started; everything after it is the daemon as on the vehicle."""

from __future__ import annotations

import time
from typing import Callable, Optional, Tuple

import numpy as np

from ..camera import Camera, Marker
from ..errors import SourceError
from ..geometry import VehicleFrames, VehiclePose, rvec_from_R
from ..render import Effects, make_background, render_marker
from ..render.map import render_map
from ..render.scene import render_empty
from .base import Frame
from .sitl_link import SitlLink, TruthSample

__all__ = ["SitlSource"]


class SitlSource:
    """Frames at ``fps`` of ``marker`` (or ``marker_map``) as a camera on ``frames_on_vehicle``
    sees it from the simulator's vehicle.

    Each frame is rendered from one truth sample, never used twice, and stamped with that
    sample's time plus ``lag_s`` (``t_capture_s``, monotonic seconds): with ``lag_s`` > 0 the
    frame shows the vehicle as it was ``lag_s`` before its stamp, a camera slower than it says.
    ``link``: a SitlLink shared with a ground station (the rehearsal), opened and closed by its
    owner; without one the source opens its own on ``connection`` and keeps its origin over a
    reopen. No truth for ``truth_timeout_s``: SourceError (the pipeline reopens the source).
    ``blackout_until_s``: frames whose truth is older than this show no marker (a rehearsed
    loss of the marker). Metadata: ``true_rvec``/``true_tvec`` (marker or map in the camera
    frame), ``true_p_local_m`` (the vehicle, NED from the marker), ``truth_t_s``, ``blackout``.
    """

    def __init__(
        self,
        camera: Camera,
        frames_on_vehicle: VehicleFrames,
        *,
        marker: Optional[Marker] = None,
        marker_map=None,
        fps: float = 30.0,
        lag_s: float = 0.0,
        effects: Optional[Effects] = None,
        seed: int = 0,
        link: Optional[SitlLink] = None,
        connection: str = "tcp:127.0.0.1:5763",
        baud: int = 921600,
        source_system: int = 255,
        source_component: int = 190,
        marker_below_m: float = 0.4,
        truth_timeout_s: float = 2.0,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if (marker is None) == (marker_map is None):
            raise SourceError("sitl source: give a marker or a map, not both")
        if fps <= 0 or lag_s < 0:
            raise SourceError("sitl source: fps must be positive and lag_s >= 0")
        self.camera, self.frames_on_vehicle = camera, frames_on_vehicle
        self.marker, self.marker_map = marker, marker_map
        self.fps, self.lag_s = float(fps), float(lag_s)
        self.effects = effects if effects is not None else Effects()
        self.seed = seed
        self.shared_link = link
        self._link_args = dict(
            connection=connection,
            baud=baud,
            source_system=source_system,
            source_component=source_component,
            marker_below_m=marker_below_m,
            truth_rate_hz=fps,
        )
        self.connection = link.connection if link is not None else connection
        self.truth_timeout_s = float(truth_timeout_s)
        self._clock, self._sleep = clock, sleep
        self.link: Optional[SitlLink] = link
        self.blackout_until_s = -1e18
        self._origin: Optional[Tuple[int, int, float]] = None
        self._rng: Optional[np.random.Generator] = None
        self._background: Optional[np.ndarray] = None
        self._last_truth_s = -1e18
        self._next_frame_s: Optional[float] = None
        self._seq = 0

    def open(self) -> None:
        if self.shared_link is None:
            self.link = SitlLink(origin=self._origin, clock=self._clock, **self._link_args)  # type: ignore[arg-type]
            self.link.open()
        assert self.link is not None
        self.link.truth_rate_hz = max(self.link.truth_rate_hz, self.fps)
        self._rng = np.random.default_rng(self.seed)
        self._background = make_background(
            self._rng, self.camera.width, self.camera.height, self.effects.background, self.effects.plain_gray
        )
        self._next_frame_s = None
        if self.link.truth_after(-1e18, 0.0, self.truth_timeout_s) is None:
            self.close()
            raise SourceError(self._no_truth())
        self._origin = self.link.origin

    def _no_truth(self) -> str:
        link = self.link
        what = "HEARTBEAT" if link is None or link.autopilot is None else link.truth_name
        return f"sitl source: no {what} from {self.connection} in {self.truth_timeout_s:g} s"

    def read(self) -> Frame:
        link = self.link
        if link is None or self._rng is None:
            raise SourceError("sitl source: read() before open()")
        now = self._clock()
        if self._next_frame_s is not None and self._next_frame_s > now:
            self._sleep(self._next_frame_s - now)
            now = self._clock()
        # The newest truth at least lag_s old that no frame has used yet.
        sample = link.truth_after(self._last_truth_s, self.lag_s, self.truth_timeout_s + self.lag_s)
        if sample is None:
            raise SourceError(self._no_truth())
        self._last_truth_s = sample.t_s
        period = 1.0 / self.fps
        base = self._next_frame_s if self._next_frame_s is not None else now
        self._next_frame_s = max(base + period, self._clock() - period)
        frame = self._render(sample)
        self._seq += 1
        return frame

    def _render(self, sample: TruthSample) -> Frame:
        vehicle = VehiclePose(p_local_body_m=sample.p_local_m, R_local_body=sample.R_local_body)
        R_cam_marker, tvec = self.frames_on_vehicle.camera_pose(vehicle)
        rvec = rvec_from_R(R_cam_marker)
        blackout = sample.t_s < self.blackout_until_s
        metadata = {
            "true_rvec": rvec,
            "true_tvec": tvec,
            "true_p_local_m": sample.p_local_m,
            "truth_t_s": sample.t_s,
            "blackout": blackout,
        }
        if blackout:
            image = render_empty(self.camera, effects=self.effects, rng=self._rng, background=self._background)
            metadata["visible"] = False
        elif self.marker_map is not None:
            rendered = render_map(
                self.camera,
                self.marker_map,
                rvec,
                tvec,
                effects=self.effects,
                rng=self._rng,
                background=self._background,
            )
            image = rendered.image
            metadata["true_marker_corners"] = rendered.corners_px
            metadata["visible_ids"] = rendered.visible
            metadata["visible"] = bool(rendered.visible)
        else:
            assert self.marker is not None
            one = render_marker(
                self.camera, self.marker, rvec, tvec, effects=self.effects, rng=self._rng, background=self._background
            )
            image = one.image
            metadata["true_corners"] = one.corners_px
            metadata["visible"] = one.visible
        return Frame(image=image, t_capture_s=sample.t_s + self.lag_s, seq=self._seq, metadata=metadata)

    def close(self) -> None:
        if self.shared_link is None and self.link is not None:
            self._origin = self.link.origin or self._origin
            self.link.close()
            self.link = None
        self._rng = None
