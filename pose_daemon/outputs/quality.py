"""How good a pose is, for the autopilot: a 1-100 quality and a covariance from the solve.

A pose from four corners is as good as the corners: its expected error is the linearised
least-squares covariance of the solve (``solve_covariance``: corner error e over the
derivative of the corners with respect to the pose), which near face-on is dominated by the
weakly seen tilt and the camera centre swinging with it (distance x tilt). Beyond that precision a planar pose has one real risk: the
other planar solution (``pose.alternative``) fits almost as well (``ambiguity_ratio`` near 1)
*and* is a different pose, so the one sent may be the wrong one altogether. Two solutions that
agree within the pose's own expected error are no risk: a level camera over a floor square is
where the two coincide (ratio -> 1) and either one is right.

The quality is the product of three factors, each 0..1:
- fit: the reprojection residual against what corner noise explains (a residual of
  ``HALF_QUALITY_ERROR_PX`` halves it, 4th power beyond: a gate on the fit);
- precision: the expected position error of the solve (1 .. 0.5, 0.75 at ``HALF_QUALITY_POSITION_M``);
- flip: 1 - (ambiguity_ratio x how far the alternative disagrees beyond the expected error),
  unless the choice between the two was settled by the vehicle's attitude (``flip_resolved``).
The covariance is widened by the same flip risk.
"""

from __future__ import annotations

import math
from typing import List, Optional, Tuple

import numpy as np

from ..geometry import VehicleFrames, rotate_covariance, rotation_angle_deg_3x3
from ..pose.types import Pose

# Corners are never located better than this, whatever the residual says (four points fit
# eight numbers with six unknowns: a small residual does not prove a small error).
MIN_CORNER_ERROR_PX = 0.25
# A residual of this many pixels halves the quality, and it falls with the 4th power beyond:
# four corners leave two redundant numbers, so the RMS residual is about half the corner
# noise (~0.1-0.2 px on a good frame); 0.5 px means a corner is off by a pixel or more.
HALF_QUALITY_ERROR_PX = 0.5
# The expected position error (1 sigma, all axes) takes off at most PRECISION_WEIGHT of the
# quality, half of that at HALF_QUALITY_POSITION_M: an imprecise but right pose still helps
# an EKF that weighs it (and ArduPilot floors the noise at VISO_POS_M_NSE anyway); only a
# bad fit or a real flip risk may push a pose below a minimum quality.
HALF_QUALITY_POSITION_M = 0.05
PRECISION_WEIGHT = 0.5
# Two planar solutions closer than this (and than 3 sigma of the attitude) are the same pose
# for the autopilot: the choice between them cannot be wrong.
AGREE_DEG = 2.0
LOST_QUALITY = -1


def _finite(*values: float) -> bool:
    return all(math.isfinite(float(v)) for v in values)


def _side_px(pose: Pose, fx_px: float, marker_width_m: float) -> float:
    d = float(np.linalg.norm(pose.tvec))
    return max(fx_px * marker_width_m / max(d, 1e-6), 1.0)


def _corner_error_px(pose: Pose) -> float:
    e = float(pose.reprojection_error_px)
    return max(e, MIN_CORNER_ERROR_PX) if math.isfinite(e) else math.inf


def _skew(w: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    z = np.zeros(w.shape[:-1])
    return np.stack([np.stack([z, -w[..., 2], w[..., 1]], -1), np.stack([w[..., 2], z, -w[..., 0]], -1),
                     np.stack([-w[..., 1], w[..., 0], z], -1)], -2)


_STEP = 1e-6
# The 12 parameter perturbations (+-step on each of rotation (3, marker frame) and translation (3)).
_DELTAS = np.concatenate([np.eye(6), -np.eye(6)]) * _STEP


def solve_covariance(pose: Pose, fx_px: float, marker_width_m: float,
                     marker_height_m: Optional[float] = None) -> Tuple[np.ndarray, np.ndarray]:
    """The expected error of the solve: (3x3 covariance of the camera centre in the marker
    frame, m^2; 3x3 covariance of the rotation in the marker frame, rad^2).

    Linearised least squares on the four corners: Cov = e^2 (J^T J)^-1 with J the derivative of
    the corners' pixel positions with respect to the pose (rotation R_cam_marker exp([w]) and
    tvec), e the corner error (the residual, at least MIN_CORNER_ERROR_PX). Near face-on the
    marker's tilt is weakly seen and the camera centre moves with it (distance x tilt): this
    is where a planar pose's real error lies, and what a fixed d*e/f misses.
    """
    w2 = marker_width_m / 2.0
    h2 = (marker_height_m if marker_height_m is not None else marker_width_m) / 2.0
    X = np.array([[-w2, h2, 0.0], [w2, h2, 0.0], [w2, -h2, 0.0], [-w2, -h2, 0.0]])
    R0 = np.asarray(pose.R, dtype=np.float64)
    t0 = np.asarray(pose.tvec, dtype=np.float64).reshape(3)
    # First-order rotation perturbation is enough for a step of 1e-6 rad.
    Rs = R0 @ (np.eye(3) + _skew(_DELTAS[:, :3]))                  # (12, 3, 3)
    ts = t0 + _DELTAS[:, 3:]                                        # (12, 3)
    P = np.einsum("kij,nj->kni", Rs, X) + ts[:, None, :]            # (12, 4, 3)
    uv = fx_px * P[..., :2] / P[..., 2:3]                           # (12, 4, 2)
    J = ((uv[:6] - uv[6:]) / (2 * _STEP)).reshape(6, 8).T           # (8, 6)
    C = np.einsum("kji,kj->ki", Rs, ts)                             # R^T t, (12, 3)
    Jc = (-(C[:6] - C[6:]) / (2 * _STEP)).T                         # camera centre, (3, 6)
    e = _corner_error_px(pose)
    cov_x = e * e * np.linalg.pinv(J.T @ J)
    return Jc @ cov_x @ Jc.T, cov_x[:3, :3]


def _attitude_std_plain_rad(pose: Pose, fx_px: Optional[float], marker_width_m: Optional[float]) -> float:
    if fx_px is None or marker_width_m is None:
        return 0.0
    _, cov_w = solve_covariance(pose, fx_px, marker_width_m)
    return math.sqrt(max(float(np.max(np.linalg.eigvalsh(cov_w))), 0.0))


def flip_risk(pose: Pose, fx_px: Optional[float] = None, marker_width_m: Optional[float] = None) -> float:
    """0 (the other planar solution is no threat) .. 1 (a coin flip between two different poses).

    ``ambiguity_ratio`` (best residual / the alternative's) times how far the alternative's
    rotation lies beyond the agreement bound (max of ``AGREE_DEG`` and 3 sigma of the pose's
    attitude): 0 at the bound, full weight at twice it. Without ``pose.alternative`` there is
    nothing to confuse the pose with (a ratio without an alternative is not a risk).
    """
    alt = pose.alternative
    r = float(pose.ambiguity_ratio)
    if alt is None or not math.isfinite(r) or r <= 0.0:
        return 0.0
    if not (np.all(np.isfinite(alt.R)) and np.all(np.isfinite(pose.R))):
        return min(r, 1.0)
    bound_deg = max(AGREE_DEG, 3.0 * math.degrees(_attitude_std_plain_rad(pose, fx_px, marker_width_m)))
    apart_deg = rotation_angle_deg_3x3(pose.R, alt.R)
    weight = min(max((apart_deg - bound_deg) / bound_deg, 0.0), 1.0)
    return weight * min(r, 1.0)


def position_std_m(pose: Pose, fx_px: float, marker_width_m: float) -> float:
    """Expected error (1 sigma, root sum of the three axes) of the camera position, metres,
    from the solve alone (``solve_covariance``; no flip risk)."""
    cov_c, _ = solve_covariance(pose, fx_px, marker_width_m)
    return math.sqrt(max(float(np.trace(cov_c)), 0.0))


def pose_quality(pose: Pose, fx_px: Optional[float] = None, marker_width_m: Optional[float] = None, *,
                 flip_resolved: bool = False) -> int:
    """1 (worst) .. 100 (best) for a pose; -1 (LOST_QUALITY) is kept for "no pose".

    ``fx_px``/``marker_width_m``: the focal length (pixels) and marker width (metres) behind the
    expected error; without them the precision factor is left out. ``flip_resolved``: the
    planar solution was chosen by the vehicle's attitude, so the alternative is no risk.
    """
    e = float(pose.reprojection_error_px)
    r = float(pose.ambiguity_ratio)
    if not _finite(e, r) or not (np.all(np.isfinite(pose.tvec)) and np.all(np.isfinite(pose.R))):
        return 1
    f_fit = 1.0 / (1.0 + (max(e, 0.0) / HALF_QUALITY_ERROR_PX) ** 4)
    f_precision = 1.0
    if fx_px is not None and marker_width_m is not None:
        sigma_m = position_std_m(pose, fx_px, marker_width_m)
        f_precision = 1.0 - PRECISION_WEIGHT * (1.0 - 1.0 / (1.0 + (sigma_m / HALF_QUALITY_POSITION_M) ** 2))
    f_flip = 1.0 if flip_resolved else 1.0 - flip_risk(pose, fx_px, marker_width_m)
    return int(min(100, max(1, round(100.0 * f_fit * f_precision * f_flip))))


def _inflation(pose: Pose, fx_px: float, marker_width_m: float) -> float:
    # A real near-tie between two different poses makes the chosen one a guess: widen the
    # covariance up to 20x rather than claim a precision the pose does not have.
    return 1.0 / max(1.0 - flip_risk(pose, fx_px, marker_width_m), 0.05)


def position_covariance_cam(pose: Pose, fx_px: float, marker_width_m: float) -> np.ndarray:
    """3x3 covariance of the camera position (m^2), in the camera frame, widened by the flip risk."""
    cov_c, _ = solve_covariance(pose, fx_px, marker_width_m)
    R = np.asarray(pose.R, dtype=np.float64)
    return _inflation(pose, fx_px, marker_width_m) ** 2 * rotate_covariance(R, cov_c)


def attitude_std_rad(pose: Pose, fx_px: float, marker_width_m: float) -> float:
    """Standard deviation of the worst attitude angle (rad) from the solve, widened by the flip risk."""
    return _inflation(pose, fx_px, marker_width_m) * _attitude_std_plain_rad(pose, fx_px, marker_width_m)


def pose_covariance_local(pose: Pose, frames: VehicleFrames, fx_px: float, marker_width_m: float) -> List[float]:
    """MAVLink's 21-element upper-right triangle (row-major) of the 6x6 covariance of
    (x, y, z, roll, pitch, yaw) in the local frame: m^2 and rad^2 (``solve_covariance``
    rotated into the local frame, widened by the flip risk)."""
    cov_c, cov_w = solve_covariance(pose, fx_px, marker_width_m)
    k2 = _inflation(pose, fx_px, marker_width_m) ** 2
    full = np.zeros((6, 6))
    full[:3, :3] = k2 * rotate_covariance(frames.R_local_marker, cov_c)
    full[3:, 3:] = k2 * rotate_covariance(frames.R_local_marker, cov_w)
    return [float(full[i, j]) for i in range(6) for j in range(i, 6)]
