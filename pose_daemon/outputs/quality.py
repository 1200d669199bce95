"""How good a pose is, for the autopilot: a 1-100 quality and a covariance from residual and ambiguity.

A pose from four corners is as good as the corners: lateral position error grows as
d * e / f and depth error as d^2 * e / (f * W) (d distance, e corner error in pixels, f focal
length in pixels, W marker width), and an ambiguous planar pose (ambiguity_ratio near 1: the
mirror solution fits almost as well) may be the wrong one altogether.
"""

from __future__ import annotations

import math
from typing import List

import numpy as np

from ..geometry import VehicleFrames, rotate_covariance
from ..pose.types import Pose

# Corners are never located better than this, whatever the residual says (four points fit
# eight numbers with six unknowns: a small residual does not prove a small error).
MIN_CORNER_ERROR_PX = 0.25
# A residual of this many pixels halves the quality.
HALF_QUALITY_ERROR_PX = 1.0
LOST_QUALITY = -1


def pose_quality(reprojection_error_px: float, ambiguity_ratio: float) -> int:
    """1 (worst) .. 100 (best) for a pose; -1 (LOST_QUALITY) is kept for "no pose"."""
    e = float(reprojection_error_px)
    r = float(ambiguity_ratio)
    if not math.isfinite(e) or not math.isfinite(r):
        return 1
    f_residual = 1.0 / (1.0 + (max(e, 0.0) / HALF_QUALITY_ERROR_PX) ** 2)
    f_ambiguity = min(max(1.0 - r, 0.0), 1.0)
    return int(min(100, max(1, round(100.0 * f_residual * f_ambiguity))))


def _inflation(ambiguity_ratio: float) -> float:
    # A near-tie between the two planar solutions makes the chosen one a guess: widen the
    # covariance up to 20x rather than claim a precision the pose does not have.
    r = float(ambiguity_ratio) if math.isfinite(float(ambiguity_ratio)) else 1.0
    return 1.0 / max(1.0 - min(max(r, 0.0), 1.0), 0.05)


def position_covariance_cam(pose: Pose, fx_px: float, marker_width_m: float) -> np.ndarray:
    """3x3 covariance of the camera position (m^2), in the camera frame."""
    solved = getattr(pose, "camera_position_covariance_cam", None)
    if solved is not None:  # a map pose carries the covariance of its own solve
        return solved
    t = np.asarray(pose.tvec, dtype=np.float64)
    d = float(np.linalg.norm(t))
    e = max(float(pose.reprojection_error_px), MIN_CORNER_ERROR_PX)
    k = _inflation(pose.ambiguity_ratio)
    s_lat = k * d * e / fx_px
    s_depth = k * d * d * e / (fx_px * marker_width_m)
    u = t / d if d > 0 else np.array([0.0, 0.0, 1.0])
    return s_lat ** 2 * np.eye(3) + (s_depth ** 2 - s_lat ** 2) * np.outer(u, u)


def attitude_std_rad(pose: Pose, fx_px: float, marker_width_m: float) -> float:
    """Standard deviation of each attitude angle (rad): corner error over the marker's size in pixels."""
    solved = getattr(pose, "attitude_std_rad", None)
    if solved is not None:
        return float(solved)
    d = float(np.linalg.norm(pose.tvec))
    e = max(float(pose.reprojection_error_px), MIN_CORNER_ERROR_PX)
    side_px = max(fx_px * marker_width_m / max(d, 1e-6), 1.0)
    return _inflation(pose.ambiguity_ratio) * 2.0 * e / side_px


def pose_covariance_local(pose: Pose, frames: VehicleFrames, fx_px: float, marker_width_m: float) -> List[float]:
    """MAVLink's 21-element upper-right triangle (row-major) of the 6x6 covariance of
    (x, y, z, roll, pitch, yaw) in the local frame: m^2 and rad^2."""
    cov_local = rotate_covariance(frames.R_local_cam(pose.R), position_covariance_cam(pose, fx_px, marker_width_m))
    s_att = attitude_std_rad(pose, fx_px, marker_width_m)
    full = np.zeros((6, 6))
    full[:3, :3] = cov_local
    full[3:, 3:] = np.eye(3) * s_att ** 2
    return [float(full[i, j]) for i in range(6) for j in range(i, 6)]
