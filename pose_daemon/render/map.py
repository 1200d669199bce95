"""The renderer for marker maps: every marker of a map in one frame, with the same camera effects
as one marker (scene.py), and trajectories that fly over a floor map or along a wall map.

A map pose is the map frame in the camera frame: X_cam = R(rvec) X_map + tvec.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np

from ..camera import Camera
from ..geometry import R_from_rvec, rot_x, rot_y, rvec_from_R
from ..marker_map import MarkerMap
from .effects import Effects, apply_effects
from .plane import render_plane_layer
from .poses import TruePose
from .scene import pose_arrays, scene_background
from .texture import marker_pyramid

__all__ = [
    "MapFrame",
    "render_map",
    "MapTrajectory",
    "map_pose_looking_down",
    "camera_position_map",
    "MAP_TRAJECTORIES",
]

MAP_TRAJECTORIES = ("floor", "wall")


@dataclass
class MapFrame:
    """A rendered map frame: ``corners_px`` {id: (4, 2) true corners TL, TR, BR, BL, pixels} of
    every marker in front of the camera with its face towards it; ``visible`` the ids wholly
    inside the image."""

    image: np.ndarray
    corners_px: Dict[int, np.ndarray]
    visible: Tuple[int, ...]


_DEFAULT_EFFECTS = Effects()


def render_map(
    camera: Camera,
    marker_map: MarkerMap,
    rvec,
    tvec,
    *,
    effects: Effects = _DEFAULT_EFFECTS,
    rng: Optional[np.random.Generator] = None,
    background: Optional[np.ndarray] = None,
) -> MapFrame:
    """Render every marker of ``marker_map`` with the map at pose (rvec, tvec) in the camera frame.

    Larger markers are drawn first, so a marker nested inside another (a landing pad) lies on
    top of it. Markers whose back faces the camera are not drawn (paper on a wall seen from
    behind the wall).
    """
    rng = rng if rng is not None else np.random.default_rng()
    R_cm, t_cm = pose_arrays(rvec, tvec)
    scene = scene_background(camera, effects, rng, background)
    if background is not None:
        scene = scene.copy()
    ss = max(1, int(effects.supersample))
    corners: Dict[int, np.ndarray] = {}
    visible = []
    lim = np.array([camera.width - 0.5, camera.height - 0.5])
    for m in sorted(marker_map.markers, key=lambda k: -k.size_m):
        R_map_marker, p = marker_map.T_map_marker(m.id)
        R = R_cm @ R_map_marker
        t = R_cm @ p + t_cm
        if float(R[:, 2] @ t) >= 0.0:
            continue  # its back faces the camera
        layer = render_plane_layer(camera, marker_pyramid(marker_map.single(m.id), effects), R, t, ss)
        if layer is not None:
            (u0, v0, u1, v1), grey, alpha = layer
            roi = scene[v0:v1, u0:u1]
            roi *= 1.0 - alpha
            roi += grey
        pts = marker_map.corners_map(m.id) @ R_cm.T + t_cm
        if np.all(pts[:, 2] > 1e-6):
            px = camera.project(pts)
            corners[m.id] = px
            if np.all((px >= -0.5) & (px <= lim)):
                visible.append(m.id)
    return MapFrame(image=apply_effects(scene, effects, rng), corners_px=corners, visible=tuple(sorted(visible)))


def map_pose_looking_down(
    x_m: float, y_m: float, height_m: float, yaw_rad: float = 0.0, tilt_x_rad: float = 0.0, tilt_y_rad: float = 0.0
) -> Tuple[np.ndarray, np.ndarray]:
    """(rvec, tvec) of the map in the camera frame for a camera at (x, y, height) over a floor
    map (or in front of a wall map at that distance) looking along the map's -z, image top
    along the map's +y turned by ``yaw_rad``, then tilted about its own x and y axes."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    R_map_cam = np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])
    R_map_cam = R_map_cam @ rot_x(tilt_x_rad) @ rot_y(tilt_y_rad)
    R_cam_map = R_map_cam.T
    p = np.array([x_m, y_m, height_m], dtype=np.float64)
    return rvec_from_R(R_cam_map), -R_cam_map @ p


class MapTrajectory:
    """An endless smooth flight over a map: ``at(t_s)`` gives the map's true pose in the camera.

    "floor": the camera looks down from ``height_m`` (low, high) while drifting over the map's
    extent and turning about the vertical (any heading), tilting up to ``max_tilt_deg``;
    "wall": the same in front of a wall map (distance ``height_m``), with a small roll.
    ``speed`` scales every motion (1 = a slow walk: about 0.3 m/s over a 3 m map).
    """

    def __init__(
        self,
        kind: str,
        marker_map: MarkerMap,
        seed: int = 0,
        height_m: Tuple[float, float] = (0.8, 2.5),
        max_tilt_deg: float = 8.0,
        speed: float = 1.0,
        margin_m: float = 0.0,
    ) -> None:
        if kind not in MAP_TRAJECTORIES:
            raise ValueError(f"map trajectory must be one of {', '.join(MAP_TRAJECTORIES)}, got {kind!r}")
        lo, hi = float(height_m[0]), float(height_m[1])
        if not 0.0 < lo <= hi:
            raise ValueError(f"height_m must be 0 < low <= high, got {height_m}")
        self.kind = kind
        self.height_m = (lo, hi)
        pts = np.vstack([marker_map.corners_map(i) for i in marker_map.ids])
        self.centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        self.half = np.maximum(0.5 * (pts.max(axis=0) - pts.min(axis=0)) - margin_m, 0.0)
        self.max_tilt = math.radians(max_tilt_deg)
        rng = np.random.default_rng(seed)
        self.phases = rng.uniform(0, 2 * math.pi, 8)
        self.periods = rng.uniform(0.8, 1.2, 8) * np.array([19.0, 23.0, 29.0, 7.0, 9.0, 31.0, 11.0, 13.0])
        self.periods /= max(float(speed), 1e-6)

    def at(self, t_s: float) -> TruePose:
        s = np.sin(2 * math.pi * t_s / self.periods + self.phases)
        lo, hi = self.height_m
        h = lo + (hi - lo) * (0.5 + 0.5 * s[0])
        x = self.centre[0] + self.half[0] * s[1]
        y = self.centre[1] + self.half[1] * s[2]
        if self.kind == "floor":
            yaw = self.phases[7] + 2 * math.pi * t_s / self.periods[5] + 0.6 * s[6]
        else:
            yaw = math.radians(12.0) * s[6]
        rvec, tvec = map_pose_looking_down(x, y, self.centre[2] + h, yaw, self.max_tilt * s[3], self.max_tilt * s[4])
        return TruePose(t_s=float(t_s), rvec=rvec, tvec=tvec)


def camera_position_map(rvec, tvec) -> np.ndarray:
    """The camera centre in the map frame for a map pose: -R^T t."""
    R = R_from_rvec(np.asarray(rvec, dtype=np.float64).reshape(3))
    return -R.T @ np.asarray(tvec, dtype=np.float64).reshape(3)
