"""The synthetic source: the renderer along a configured trajectory, paced at the camera's
frame rate; every frame's metadata carries its true pose and corners, and the frame the
vehicle's attitude as an autopilot would give it (the truth plus noise and lag)."""

from __future__ import annotations

import math
import time
from typing import Callable, Optional, Tuple

import numpy as np

from ..attitude import Attitude
from ..camera import Camera, Marker
from ..errors import EndOfStream, SourceError
from ..geometry import R_from_rvec, VehicleFrames
from ..render import TRAJECTORY_MOUNTS, Effects, Trajectory, make_background, prepare_marker, render_marker
from ..render.map import MapTrajectory, render_map
from .base import Frame


class SyntheticSource:
    """Frames of ``marker`` seen by ``camera`` moving along ``trajectory`` ("wall"/"floor").

    ``frames`` = 0: endless. ``realtime``: each frame is delivered at its time on the
    monotonic clock (``t_capture_s``); otherwise as fast as rendered, with ``t_capture_s``
    the start time plus the trajectory time. Metadata: ``true_rvec``, ``true_tvec`` (marker
    in camera frame, rad / m), ``true_corners`` (4, 2) px, ``trajectory_t_s`` (= seq / fps).

    In real time, a source that fell behind its schedule by more than a frame period (a
    slow render: the renderer's first use takes about a second; or a rate faster than it
    renders) restarts the schedule at the present frame, as a camera does: it never hands
    out a backlog of frames stamped in the past, which would all be too old to use. Each
    restart is counted in ``restarts``; the trajectory goes on from where it was.

    ``attitude``: each frame carries the body's attitude ``attitude_lag_s`` before its
    capture (an autopilot's estimate lags) plus Gaussian noise of ``attitude_noise_deg``
    per axis (its own random stream: the images do not change with it), stated with that
    sigma; for a camera on ``frames`` (default: the trajectory's mount and placement).
    """

    def __init__(
        self,
        camera: Camera,
        marker: Marker,
        *,
        trajectory: str = "wall",
        seed: int = 0,
        fps: float = 30.0,
        frames: int = 0,
        effects: Optional[Effects] = None,
        realtime: bool = True,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        attitude: bool = True,
        attitude_noise_deg: float = 0.5,
        attitude_lag_s: float = 0.0,
        frames_on_vehicle: Optional[VehicleFrames] = None,
        marker_map=None,
        height_m: Optional[Tuple[float, float]] = None,
    ) -> None:
        if fps <= 0:
            raise SourceError(f"synthetic source: fps must be positive, got {fps}")
        if not (attitude_noise_deg >= 0 and attitude_lag_s >= 0):
            raise SourceError("synthetic source: attitude noise and lag must be >= 0")
        self.attitude = attitude
        self.attitude_noise_deg, self.attitude_lag_s = float(attitude_noise_deg), float(attitude_lag_s)
        self.camera, self.marker = camera, marker
        #: A MarkerMap: the whole map is rendered and the trajectory flies over it (render_map);
        #: the truth is then the map's pose and ``true_marker_corners`` {id: (4, 2)}.
        self.marker_map = marker_map
        if marker_map is not None:
            self.path = MapTrajectory(trajectory, marker_map, seed, height_m or (0.8, 2.5))
        else:
            self.path = Trajectory(trajectory, seed, camera, marker)
        # The vehicle the camera rides on, for the attitude an autopilot would report.
        self.vehicle_frames = (
            frames_on_vehicle
            if frames_on_vehicle is not None
            else VehicleFrames.from_settings(TRAJECTORY_MOUNTS[trajectory], placement=trajectory)
        )
        self._attitude_rng: Optional[np.random.Generator] = None
        self.seed, self.fps, self.frames = seed, float(fps), int(frames)
        self.effects = effects if effects is not None else Effects()
        self.realtime = realtime
        self._clock, self._sleep = clock, sleep
        self._rng: Optional[np.random.Generator] = None
        self._background: Optional[np.ndarray] = None
        self._seq = 0
        self._t0: Optional[float] = None
        self.restarts = 0

    def open(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        self._attitude_rng = np.random.default_rng([self.seed, 1])
        # One background for the whole run: a camera on a robot sees the same room.
        self._background = make_background(
            self._rng, self.camera.width, self.camera.height, self.effects.background, self.effects.plain_gray
        )
        self._seq = 0
        self._warm_up()
        self._t0 = self._clock()

    def _warm_up(self) -> None:
        """Render the first pose once, unseen, before the schedule starts: the renderer's first
        use costs several frames' time (65-100 ms against 20-40 here), which frame 0 would
        otherwise carry as capture latency, late for the budget with its processing. Its own
        random stream: the frames' noise does not change. A marker's texture levels for every
        depth of the trajectory are made here too: the demo's frame 35, the first at a new
        level, took 50-170 ms to render on a loaded machine and was dropped as late."""
        truth = self.path.at(0.0)
        render = render_map if self.marker_map is not None else render_marker
        render(
            self.camera,
            self.marker_map if self.marker_map is not None else self.marker,
            truth.rvec,
            truth.tvec,
            effects=self.effects,
            rng=np.random.default_rng([self.seed, 2]),
            background=self._background,
        )
        if self.marker_map is None and isinstance(self.path, Trajectory):
            prepare_marker(self.camera, self.marker, self.path.depth_range_m(), self.effects)

    def read(self) -> Frame:
        if self._rng is None:
            raise SourceError("synthetic source: read() before open()")
        if self.frames and self._seq >= self.frames:
            raise EndOfStream(f"synthetic source: {self.frames} frames done")
        t_traj = self._seq / self.fps
        t_capture = self._t0 + t_traj
        if self.realtime:
            now = self._clock()
            wait = t_capture - now
            if wait > 0:
                self._sleep(wait)
            elif -wait > 1.0 / self.fps:
                self._t0 = now - t_traj
                t_capture = now
                self.restarts += 1
        truth = self.path.at(t_traj)
        if self.marker_map is not None:
            frame = self._map_frame(truth, t_capture, t_traj)
            self._seq += 1
            return frame
        rendered = render_marker(
            self.camera,
            self.marker,
            truth.rvec,
            truth.tvec,
            effects=self.effects,
            rng=self._rng,
            background=self._background,
        )
        frame = Frame(
            image=rendered.image,
            t_capture_s=t_capture,
            seq=self._seq,
            metadata={
                "true_rvec": truth.rvec,
                "true_tvec": truth.tvec,
                "true_corners": rendered.corners_px,
                "visible": rendered.visible,
                "trajectory_t_s": t_traj,
            },
            attitude=self._attitude(t_traj),
        )
        self._seq += 1
        return frame

    def _attitude(self, t_traj_s: float) -> Optional[Attitude]:
        if not self.attitude:
            return None
        truth = self.path.at(t_traj_s - self.attitude_lag_s)
        rpy = np.asarray(self.vehicle_frames.vehicle_pose(R_from_rvec(truth.rvec), truth.tvec).rpy_rad)
        assert self._attitude_rng is not None
        sigma = math.radians(self.attitude_noise_deg)
        rpy = rpy + self._attitude_rng.normal(0.0, 1.0, 3) * sigma
        return Attitude((float(rpy[0]), float(rpy[1]), float(rpy[2])), sigma)

    def _map_frame(self, truth, t_capture: float, t_traj: float) -> Frame:
        rendered = render_map(
            self.camera,
            self.marker_map,
            truth.rvec,
            truth.tvec,
            effects=self.effects,
            rng=self._rng,
            background=self._background,
        )
        return Frame(
            image=rendered.image,
            t_capture_s=t_capture,
            seq=self._seq,
            metadata={
                "true_rvec": truth.rvec,
                "true_tvec": truth.tvec,
                "true_marker_corners": rendered.corners_px,
                "visible_ids": rendered.visible,
                "visible": bool(rendered.visible),
                "trajectory_t_s": t_traj,
            },
            attitude=self._attitude(t_traj),
        )

    def close(self) -> None:
        self._rng = None
