"""Where the renderer puts a marker: random poses facing the camera, and the smooth
trajectories the synthetic source follows (a wall marker ahead, a floor marker below)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np

from ..camera import Camera, Marker
from ..geometry import R_UNROT_MARKER, R_from_rvec, VehicleFrames, rot_z, rvec_from_R

TRAJECTORIES = ("wall", "floor")
# The camera mount each trajectory flies with: it looks at a wall marker ahead, a floor marker below.
TRAJECTORY_MOUNTS = {"wall": "forward", "floor": "down"}


@dataclass
class TruePose:
    """The marker's pose in the camera frame at time ``t_s``: X_cam = R(rvec) X_marker + tvec."""

    t_s: float
    rvec: np.ndarray
    tvec: np.ndarray


def _R_cam_marker_facing(ray_cam: np.ndarray, tilt_axis_angle: float, tilt_rad: float, roll_rad: float) -> np.ndarray:
    """R_cam_marker for a marker on the ray ``ray_cam`` facing the camera, tilted by ``tilt_rad``
    about an in-plane axis at ``tilt_axis_angle`` and turned by ``roll_rad`` in its plane."""
    d = ray_cam / np.linalg.norm(ray_cam)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d)
    s = np.linalg.norm(axis)
    angle = math.atan2(s, float(z @ d))
    R_align = R_from_rvec(axis / s * angle) if s > 1e-12 else np.eye(3)
    R_tilt = R_from_rvec(np.array([math.cos(tilt_axis_angle), math.sin(tilt_axis_angle), 0.0]) * tilt_rad)
    R_cam_unrot = R_align @ R_tilt @ rot_z(roll_rad)
    return R_cam_unrot @ R_UNROT_MARKER


def facing_pose(
    camera: Camera,
    centre_px: Tuple[float, float],
    distance_m: float,
    tilt_axis_rad: float,
    tilt_deg: float,
    roll_rad: float,
) -> Tuple[np.ndarray, np.ndarray]:
    """The pose (rvec, tvec) of a marker centred on the pixel ``centre_px`` at ``distance_m``,
    its face tilted ``tilt_deg`` away from the line of sight (the view angle) about an in-plane
    axis at ``tilt_axis_rad``, turned by ``roll_rad`` in its plane."""
    xn, yn = camera.undistort_normalized(np.array([[float(centre_px[0]), float(centre_px[1])]]))[0]
    ray = np.array([xn, yn, 1.0])
    R = _R_cam_marker_facing(ray, tilt_axis_rad, math.radians(tilt_deg), roll_rad)
    return rvec_from_R(R), ray / np.linalg.norm(ray) * distance_m


def inside_image(camera: Camera, marker: Marker, rvec, tvec, margin_px: float = 4.0) -> bool:
    """Whether the whole marker at (rvec, tvec) is in front of the camera and inside the image,
    ``margin_px`` from its edges."""
    pts = marker.object_points @ R_from_rvec(np.asarray(rvec, float)).T + np.asarray(tvec, float)
    if np.any(pts[:, 2] <= 0.05):
        return False
    px = camera.project(pts)
    return bool(np.all((px >= margin_px) & (px <= [camera.width - 1 - margin_px, camera.height - 1 - margin_px])))


def random_pose(
    rng: np.random.Generator,
    camera: Camera,
    marker: Marker,
    distance_m: Tuple[float, float] = (0.5, 3.0),
    max_tilt_deg: float = 60.0,
    margin_px: float = 4.0,
    max_tries: int = 1000,
    min_tilt_deg: float = 0.0,
) -> Tuple[np.ndarray, np.ndarray]:
    """A random pose (rvec, tvec) with the whole marker inside the image (``margin_px`` from
    its edges): distance of the marker centre uniform in ``distance_m``, tilt of its face
    away from the line of sight (the view angle) uniform in ``min_tilt_deg``..``max_tilt_deg``,
    any in-plane rotation."""
    for attempt in range(max_tries):
        dist = rng.uniform(*distance_m)
        # Shrink towards the image centre if the marker keeps falling out at this distance.
        spread = 1.0 if attempt < max_tries // 2 else 0.3
        u = camera.cx + spread * rng.uniform(-0.5, 0.5) * camera.width
        v = camera.cy + spread * rng.uniform(-0.5, 0.5) * camera.height
        rvec, t = facing_pose(
            camera,
            (u, v),
            dist,
            rng.uniform(0, 2 * math.pi),
            rng.uniform(min_tilt_deg, max_tilt_deg),
            rng.uniform(-math.pi, math.pi),
        )
        if inside_image(camera, marker, rvec, t, margin_px):
            return rvec, t
    raise ValueError(
        f"no pose keeps a {marker.width} x {marker.height} m marker inside the image at "
        f"{distance_m[0]}-{distance_m[1]} m; use a closer distance range"
    )


def trajectory(
    kind: str,
    n_frames: int,
    fps: float,
    seed: int = 0,
    camera: Optional[Camera] = None,
    marker: Optional[Marker] = None,
) -> List[TruePose]:
    """The marker's true pose in the camera frame for ``n_frames`` frames at ``fps``.

    "wall": the camera moves in front of a marker on a wall (distance, side-to-side and up and
    down sway, looking roughly at it, small roll); "floor": the camera flies over a floor
    marker looking down (height changes, lateral drift, turning about the vertical, i.e. any
    in-plane rotation). Smooth (sums of sines with seeded phases) and the marker stays whole
    in the image of ``camera`` (default: 640x480, fx = fy = 600, 0.2 m marker).
    """
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    path = Trajectory(kind, seed, camera, marker)
    return [path.at(i / fps) for i in range(int(n_frames))]


class Trajectory:
    """An endless smooth trajectory (see ``trajectory``): ``at(t_s)`` gives the true pose."""

    def __init__(
        self, kind: str, seed: int = 0, camera: Optional[Camera] = None, marker: Optional[Marker] = None
    ) -> None:
        if kind not in TRAJECTORIES:
            raise ValueError(f"trajectory must be one of {', '.join(TRAJECTORIES)}, got {kind!r}")
        self.kind = kind
        camera = camera or Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)
        marker = marker or Marker(0.2, 0.2)
        rng = np.random.default_rng(seed)
        f = min(camera.fx, camera.fy)
        size_m = max(marker.width, marker.height)
        # The marker spans between ~45 % of the short image side (near) and ~45 px (far).
        self.near = max(f * size_m * 1.45 / (0.45 * min(camera.width, camera.height)), 0.05)
        self.far = max(self.near * 1.5, min(f * size_m / 45.0, 6.0))
        self.phases = rng.uniform(0, 2 * math.pi, 8)
        self.periods = rng.uniform(0.8, 1.2, 8) * np.array([14.0, 9.0, 11.0, 7.0, 13.0, 17.0, 6.0, 23.0])
        # The floor heading starts within ~30 deg of upright: a plain square's labels are only
        # defined up to quarter turns, and a detector takes the first sighting as upright.
        self.phases[7] = rng.uniform(-1.0, 1.0) * math.radians(25.0)

    def at(self, t_s: float) -> TruePose:
        s = np.sin(2 * math.pi * t_s / self.periods + self.phases)
        dist = self.near + (self.far - self.near) * (0.5 + 0.5 * s[0])
        if self.kind == "wall":
            # Camera position in the marker frame (x right, y up, z out of the wall).
            lateral = 0.45 * dist * s[1]
            height = 0.25 * dist * s[2]
            roll = math.radians(12.0) * s[3]
            look_off = 0.08 * s[4:6]
        else:
            lateral = 0.3 * dist * s[1]
            height = 0.3 * dist * s[2]
            roll = 2 * math.pi * t_s / self.periods[7] + self.phases[7]  # heading: keeps turning
            look_off = 0.05 * s[4:6]
        p_marker = np.array([lateral, height, dist])
        # Roll about the optical axis, after aiming it (camera frame on the left).
        R_cam_unrot = rot_z(roll) @ _aim(p_marker, look_off)
        R = R_cam_unrot @ R_UNROT_MARKER
        return TruePose(t_s=float(t_s), rvec=rvec_from_R(R), tvec=-R @ p_marker)

    def depth_range_m(self) -> Tuple[float, float]:
        """Bounds of the marker centre's depth in the camera frame (tvec's z) along the whole
        trajectory, metres: the camera is ``dist`` (near..far) from the marker's plane and at
        most 1.13 ``dist`` from its centre with the sway, aimed within 7 deg of it."""
        return 0.95 * self.near, 1.15 * self.far

    def frames(self) -> VehicleFrames:
        """The mount and placement this trajectory flies with (TRAJECTORY_MOUNTS)."""
        return VehicleFrames.from_settings(TRAJECTORY_MOUNTS[self.kind], placement=self.kind)

    def attitude_at(self, t_s: float, frames: Optional[VehicleFrames] = None) -> Tuple[float, float, float]:
        """The vehicle body's true (roll, pitch, yaw) in the local frame at ``t_s``, radians,
        for a camera on ``frames`` (default: ``self.frames()``)."""
        truth = self.at(t_s)
        vehicle = (frames or self.frames()).vehicle_pose(R_from_rvec(truth.rvec), truth.tvec)
        return vehicle.rpy_rad


def _aim(p_marker: np.ndarray, look_off: np.ndarray) -> np.ndarray:
    """R_cam_unrot (before roll) of a camera at ``p_marker`` (marker frame) whose optical axis
    points at the marker centre offset by ``look_off`` (normalized image units)."""
    # Direction of the marker centre in the unrotated camera frame.
    d = R_UNROT_MARKER @ (-p_marker)
    target = np.array([d[0] / d[2] + look_off[0], d[1] / d[2] + look_off[1], 1.0])
    target /= np.linalg.norm(target)
    # The smallest rotation taking that direction onto the optical axis (no added roll).
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(target, z)
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        return np.eye(3)
    return R_from_rvec(v / s * math.atan2(s, float(target @ z)))
