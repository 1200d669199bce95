"""How good a pose is, for the autopilot: a 1-100 quality and a covariance from the solve.

A pose from four corners is as good as the corners: its expected error is the linearised
least-squares covariance of the solve (``solve_covariance``: corner error e over the
derivative of the corners with respect to the pose), which near face-on is dominated by the
weakly seen tilt and the camera centre swinging with it (distance x tilt). Beyond that
precision a planar pose has one real risk: the
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
from dataclasses import dataclass
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


def _skew3(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def solve_covariance(
    pose: Pose, fx_px: float, marker_width_m: float, marker_height_m: Optional[float] = None
) -> Tuple[np.ndarray, np.ndarray]:
    """The expected error of the solve: (3x3 covariance of the camera centre in the marker
    frame, m^2; 3x3 covariance of the rotation in the marker frame, rad^2).

    Linearised least squares on the four corners: Cov = e^2 (J^T J)^-1 with J the derivative of
    the corners' pixel positions with respect to the pose (rotation R_cam_marker exp([w]) and
    tvec), e the corner error (the residual, at least MIN_CORNER_ERROR_PX). Near face-on the
    marker's tilt is weakly seen and the camera centre moves with it (distance x tilt): this
    is where a planar pose's real error lies, and what a fixed d*e/f misses.
    """
    solved = getattr(pose, "solve_covariance_map", None)
    if solved is not None:  # a map pose (pose/map_solve.py) carries the covariance of its own solve
        return solved
    w2 = marker_width_m / 2.0
    h2 = (marker_height_m if marker_height_m is not None else marker_width_m) / 2.0
    R = np.asarray(pose.R, dtype=np.float64)
    t = np.asarray(pose.tvec, dtype=np.float64).reshape(3)
    # Corners in the camera frame, (4, 3); dP/dw = -R [X]x = -[R X]x R, dP/dt = I.
    X = np.array([[-w2, h2, 0.0], [w2, h2, 0.0], [w2, -h2, 0.0], [-w2, -h2, 0.0]])
    RX = X @ R.T
    P = RX + t
    inv_z = 1.0 / P[:, 2]
    # d(u, v)/dP per corner: f / z * [[1, 0, -x/z], [0, 1, -y/z]] -> (4, 2, 3)
    A = np.zeros((4, 2, 3))
    A[:, 0, 0] = A[:, 1, 1] = fx_px * inv_z
    A[:, 0, 2] = -fx_px * P[:, 0] * inv_z * inv_z
    A[:, 1, 2] = -fx_px * P[:, 1] * inv_z * inv_z
    # -[R X]x R for each corner: (4, 3, 3)
    S = np.zeros((4, 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -RX[:, 2], RX[:, 1], -RX[:, 0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = RX[:, 2], -RX[:, 1], RX[:, 0]
    J = np.concatenate([A @ (-S @ R), A], axis=2).reshape(8, 6)
    # Camera centre c = -R^T t: dc/dw = -[R^T t]x, dc/dt = -R^T.
    Rt = R.T
    Jc = np.hstack([-_skew3(Rt @ t), -Rt])
    e = _corner_error_px(pose)
    JtJ = J.T @ J
    try:
        cov_x = e * e * np.linalg.inv(JtJ)
    except np.linalg.LinAlgError:
        cov_x = e * e * np.linalg.pinv(JtJ)
    return Jc @ cov_x @ Jc.T, cov_x[:3, :3]


def _worst_std(cov: np.ndarray) -> float:
    return math.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0))


@dataclass(frozen=True)
class Uncertainty:
    """One pose's uncertainty, worked out once (``uncertainty``) for its quality and covariance:
    ``cov_centre_m2`` camera centre and ``cov_rotation_rad2`` rotation, both in the marker frame
    and from the solve alone; ``flip_risk`` 0..1 (see ``flip_risk``)."""

    cov_centre_m2: np.ndarray
    cov_rotation_rad2: np.ndarray
    flip_risk: float

    @property
    def position_std_m(self) -> float:
        return math.sqrt(max(float(np.trace(self.cov_centre_m2)), 0.0))

    @property
    def attitude_std_rad(self) -> float:
        """Sigma of the worst-seen rotation axis (the largest eigenvalue), rad."""
        return _worst_std(self.cov_rotation_rad2)

    @property
    def inflation(self) -> float:
        # A real near-tie between two different poses makes the chosen one a guess: widen the
        # covariance up to 20x rather than claim a precision the pose does not have.
        return 1.0 / max(1.0 - self.flip_risk, 0.05)


def _flip_risk(pose: Pose, attitude_std_rad: float) -> float:
    alt = pose.alternative
    r = float(pose.ambiguity_ratio)
    if alt is None or not math.isfinite(r) or r <= 0.0:
        return 0.0
    if not (np.all(np.isfinite(alt.R)) and np.all(np.isfinite(pose.R))):
        return min(r, 1.0)
    bound_deg = max(AGREE_DEG, 3.0 * math.degrees(attitude_std_rad))
    apart_deg = float(rotation_angle_deg_3x3(pose.R, alt.R))
    weight = min(max((apart_deg - bound_deg) / bound_deg, 0.0), 1.0)
    return weight * min(r, 1.0)


def uncertainty(pose: Pose, fx_px: float, marker_width_m: float) -> Uncertainty:
    """The solve's covariance and the flip risk of ``pose``, for ``pose_quality`` and the
    covariance functions (pass it as ``u`` to work it out once per pose)."""
    cov_c, cov_w = solve_covariance(pose, fx_px, marker_width_m)
    return Uncertainty(cov_c, cov_w, _flip_risk(pose, _worst_std(cov_w)))


def flip_risk(pose: Pose, fx_px: Optional[float] = None, marker_width_m: Optional[float] = None) -> float:
    """0 (the other planar solution is no threat) .. 1 (a coin flip between two different poses).

    ``ambiguity_ratio`` (best residual / the alternative's) times how far the alternative's
    rotation lies beyond the agreement bound (max of ``AGREE_DEG`` and 3 sigma of the pose's
    attitude; without ``fx_px``/``marker_width_m`` the bound is ``AGREE_DEG``): 0 at the bound,
    full weight at twice it. Without ``pose.alternative`` there is nothing to confuse the pose
    with (a ratio without an alternative is not a risk).
    """
    if fx_px is None or marker_width_m is None:
        return _flip_risk(pose, 0.0)
    return uncertainty(pose, fx_px, marker_width_m).flip_risk


def position_std_m(pose: Pose, fx_px: float, marker_width_m: float) -> float:
    """Expected error (1 sigma, root sum of the three axes) of the camera position, metres,
    from the solve alone (``solve_covariance``; no flip risk)."""
    cov_c, _ = solve_covariance(pose, fx_px, marker_width_m)
    return math.sqrt(max(float(np.trace(cov_c)), 0.0))


def pose_quality(
    pose: Pose,
    fx_px: Optional[float] = None,
    marker_width_m: Optional[float] = None,
    *,
    flip_resolved: bool = False,
    u: Optional[Uncertainty] = None,
) -> int:
    """1 (worst) .. 100 (best) for a pose; -1 (LOST_QUALITY) is kept for "no pose".

    ``fx_px``/``marker_width_m``: the focal length (pixels) and marker width (metres) behind the
    expected error; without them the precision factor is left out. ``flip_resolved``: the
    planar solution was chosen by the vehicle's attitude, so the alternative is no risk.
    ``u``: ``uncertainty(pose, fx_px, marker_width_m)`` when the caller has it already.
    """
    e = float(pose.reprojection_error_px)
    r = float(pose.ambiguity_ratio)
    if not _finite(e, r) or not (np.all(np.isfinite(pose.tvec)) and np.all(np.isfinite(pose.R))):
        return 1
    f_fit = 1.0 / (1.0 + (max(e, 0.0) / HALF_QUALITY_ERROR_PX) ** 4)
    f_precision = 1.0
    if u is None and fx_px is not None and marker_width_m is not None:
        u = uncertainty(pose, fx_px, marker_width_m)
    if u is not None:
        f_precision = 1.0 - PRECISION_WEIGHT * (1.0 - 1.0 / (1.0 + (u.position_std_m / HALF_QUALITY_POSITION_M) ** 2))
        risk = u.flip_risk
    else:
        risk = _flip_risk(pose, 0.0)
    f_flip = 1.0 if flip_resolved else 1.0 - risk
    return int(min(100, max(1, round(100.0 * f_fit * f_precision * f_flip))))


def position_covariance_cam(
    pose: Pose, fx_px: float, marker_width_m: float, u: Optional[Uncertainty] = None
) -> np.ndarray:
    """3x3 covariance of the camera position (m^2), in the camera frame, widened by the flip risk."""
    u = u if u is not None else uncertainty(pose, fx_px, marker_width_m)
    return u.inflation**2 * rotate_covariance(np.asarray(pose.R, dtype=np.float64), u.cov_centre_m2)


def attitude_std_rad(pose: Pose, fx_px: float, marker_width_m: float, u: Optional[Uncertainty] = None) -> float:
    """Standard deviation of the worst attitude angle (rad) from the solve, widened by the flip risk."""
    u = u if u is not None else uncertainty(pose, fx_px, marker_width_m)
    return u.inflation * u.attitude_std_rad


def pose_covariance_local(
    pose: Pose, frames: VehicleFrames, fx_px: float, marker_width_m: float, u: Optional[Uncertainty] = None
) -> List[float]:
    """MAVLink's 21-element upper-right triangle (row-major) of the 6x6 covariance of
    (x, y, z, roll, pitch, yaw) in the local frame: m^2 and rad^2 (``solve_covariance``
    rotated into the local frame, widened by the flip risk)."""
    u = u if u is not None else uncertainty(pose, fx_px, marker_width_m)
    k2 = u.inflation**2
    R = frames.R_local_marker
    full = np.zeros((6, 6))
    full[:3, :3] = k2 * (R @ u.cov_centre_m2 @ R.T)
    full[3:, 3:] = k2 * (R @ u.cov_rotation_rad2 @ R.T)
    return full[np.triu_indices(6)].tolist()
