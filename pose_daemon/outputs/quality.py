"""How good a pose is, for the autopilot: a 1-100 quality and a covariance from the solve.

A pose from four corners is as good as the corners, and as believable as its agreement with the
frames before it. Four things decide how far it can be trusted, and each is one factor (0..1) of
the quality:

- fit: the reprojection residual e against the corner noise sigma measured on this camera
  (``FrameResult.corner_sigma_px``, the processor's CornerNoise; ``DEFAULT_CORNER_SIGMA_PX``
  until measured). Four corners fit six unknowns with two numbers to spare, so on a good frame
  e ~ sigma sqrt(chi2_2 / 4) (median 0.59 sigma, above 2.5 sigma in 4 of a million frames);
  z = e / sigma of ``FIT_HALF_Z`` halves the quality, 4th power beyond. A corner knocked off
  by a bad edge fit shows here even when the residual is small in pixels.
- precision: the expected position error of the solve (``solve_covariance``: the corner noise
  over the derivative of the corners with respect to the pose, plus the attitude's down when
  the frame had one) against what the vehicle needs: ``NEED_POSITION_M``, the noise the
  autopilots assume for a vision position by default (PX4's EKF2_EVP_NOISE 0.1 m; ArduPilot
  floors at VISO_POS_M_NSE 0.2 m and ignores the covariance), so a pose whose own error is
  larger would be fused as better than it is. 1 / (1 + (sigma_pos / need)^2).
- flip: the other planar solution (``pose.alternative``) is a real risk only when it is still
  likely *and* a different pose. Likely: the chi-square likelihood of the two fits,
  p = 1 / (1 + exp((cost_other - cost_sent) / 2)), cost = 4 e^2 / sigma^2; different: its
  rotation beyond max(``AGREE_DEG``, 3 sigma of the pose's attitude). Left out when a prior
  ruled the other solution out (``flip_resolved``: the choice was the vehicle's attitude or
  the tilt prior, ``resolved_by_prior``).

- track: a pose whose rotation jumps off the track's constant-rate prediction
  (``FrameResult.track_innovation``) by more than the turn a vehicle can make in that time plus
  the poses' own noise (``pose.continuity.turn_allowance_deg``) is not the vehicle's motion: a
  corner knocked off along the direction four corners leave unchecked moves the pose (near
  face-on: the tilt) without leaving a residual. 1 / (1 + (angle / (``TRACK_HALF`` x
  allowance))^4); 1 at a track's first poses.

Until the processor has measured the corner noise (its first frames) the quality is the lowest
any camera could earn with these corners: the fit judged against the least noise a corner is
ever taken to have (``MIN_CORNER_SIGMA_PX``; the fit factor only falls as the noise falls), the
precision and the flip risk against ``DEFAULT_CORNER_SIGMA_PX`` (as the covariance sent). A real
camera's first corners (0.1-0.4 px off) are then far beyond that floor and not fused; corners
that fit to a few hundredths of a pixel are good whatever the camera's noise turns out to be.

The covariance sent is the solve's about the pose sent, plus p (the other solution's
probability left after the prior) times the outer product of the step to the other solution:
the mean squared error of sending one of two poses.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, List, Optional, Tuple

import numpy as np

from ..geometry import VehicleFrames, rotate_covariance, rotation_angle_deg_3x3, rvec_from_R
from ..pose.continuity import Innovation, turn_allowance_deg
from ..pose.types import Pose

if TYPE_CHECKING:
    from ..result import FrameResult

# The corner noise assumed until the processor measured it (pixels): a good real frame's
# corners; with FIT_HALF_Z the quality halves at a residual of 0.5 px.
DEFAULT_CORNER_SIGMA_PX = 0.2
# Corners are never taken as better than this, pixels (the processor's CornerNoise floor).
MIN_CORNER_SIGMA_PX = 0.01
# z = residual / corner noise at which the fit factor is 1/2 (4th power beyond).
FIT_HALF_Z = 2.5
# The expected position error (1 sigma, root sum of the three axes) at which the precision
# factor is 1/2: the default noise of a vision position in PX4's EKF2 (EKF2_EVP_NOISE).
NEED_POSITION_M = 0.1
# Two planar solutions closer than this (and than 3 sigma of the attitude) are the same pose
# for the autopilot: the choice between them cannot be wrong.
AGREE_DEG = 2.0
# The choices (prior.RESOLVED_BY) that ruled the other planar solution out.
RESOLVING_PRIORS = ("attitude", "tilt")
# No attitude's down is trusted to better than this in the covariance, radians (prior_noise.py's
# MIN_PRIOR_SIGMA_DEG).
MIN_DOWN_SIGMA_RAD = math.radians(0.25)
LOST_QUALITY = -1
# A rotation this many turn allowances off the track's prediction halves the quality (4th power
# beyond): the bound the track itself follows poses within (continuity.TRACK_OUTLIER_ALLOWANCES).
TRACK_HALF = 2.0
# MAVLink's upper-right triangle of a 6x6 covariance, row-major (built once: 20 us a call).
_TRIU6 = np.triu_indices(6)


def resolved_by_prior(resolved_by: Optional[str]) -> bool:
    """Whether a choice's ``resolved_by`` (FrameResult.choice) ruled the other solution out."""
    return resolved_by in RESOLVING_PRIORS


def _finite(*values: float) -> bool:
    return all(math.isfinite(float(v)) for v in values)


def noise_sigma_px(corner_sigma_px: Optional[float]) -> float:
    """The corner noise the quality works with: the measured one (or the default), floored."""
    s = DEFAULT_CORNER_SIGMA_PX if corner_sigma_px is None or not math.isfinite(corner_sigma_px) else corner_sigma_px
    return max(float(s), MIN_CORNER_SIGMA_PX)


def _cov_sigma_px(pose: Pose, corner_sigma_px: Optional[float]) -> float:
    """The corners' error behind the covariance: the noise, or this frame's residual when larger."""
    e = float(pose.reprojection_error_px)
    s = noise_sigma_px(corner_sigma_px)
    return max(e, s) if math.isfinite(e) else math.inf


def _skew3(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _solve(
    pose: Pose,
    fx_px: float,
    marker_width_m: float,
    marker_height_m: Optional[float] = None,
    *,
    corner_sigma_px: Optional[float] = None,
    down_m: Optional[np.ndarray] = None,
    down_sigma_rad: Optional[float] = None,
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``solve_covariance`` and the 3x3 covariance of tvec (the marker centre in the camera
    frame, m^2); a map pose's tvec covariance is its camera centre's, rotated (an upper bound:
    the two are correlated through the attitude)."""
    solved = getattr(pose, "solve_covariance_map", None)
    if solved is not None:  # a map pose (pose/map_solve.py) carries the covariance of its own solve
        R = np.asarray(pose.R, dtype=np.float64)
        return solved[0], solved[1], R @ solved[0] @ R.T
    return _linearised(pose, fx_px, marker_width_m, marker_height_m, corner_sigma_px, down_m, down_sigma_rad)


def solve_covariance(
    pose: Pose,
    fx_px: float,
    marker_width_m: float,
    marker_height_m: Optional[float] = None,
    *,
    corner_sigma_px: Optional[float] = None,
    down_m: Optional[np.ndarray] = None,
    down_sigma_rad: Optional[float] = None,
) -> Tuple[np.ndarray, np.ndarray]:
    """The expected error of the solve: (3x3 covariance of the camera centre in the marker
    frame, m^2; 3x3 covariance of the rotation in the marker frame, rad^2).

    Linearised least squares on the four corners: Cov = (J^T J / s^2 + P)^-1 with J the
    derivative of the corners' pixel positions with respect to the pose (rotation R_cam_marker
    exp([w]) and tvec), s the corner error (the measured noise ``corner_sigma_px``, at least
    MIN_CORNER_SIGMA_PX, or the residual when larger; DEFAULT_CORNER_SIGMA_PX unmeasured).
    P: with ``down_m`` (down in the marker frame) and ``down_sigma_rad``, the information of
    an attitude's down direction (the prior's polish term), which pins the tilt. Near face-on
    the marker's tilt is weakly seen and the camera centre moves with it (distance x tilt):
    this is where a planar pose's real error lies.
    """
    cov_c, cov_w, _ = _solve(
        pose,
        fx_px,
        marker_width_m,
        marker_height_m,
        corner_sigma_px=corner_sigma_px,
        down_m=down_m,
        down_sigma_rad=down_sigma_rad,
    )
    return cov_c, cov_w


def _linearised(
    pose: Pose,
    fx_px: float,
    marker_width_m: float,
    marker_height_m: Optional[float],
    corner_sigma_px: Optional[float],
    down_m: Optional[np.ndarray],
    down_sigma_rad: Optional[float],
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    s = _cov_sigma_px(pose, corner_sigma_px)
    info = J.T @ J / (s * s)
    if down_m is not None and down_sigma_rad is not None:
        # d(R exp([w]) d)/dw = -R [d]x: the down direction the pose implies, in the camera frame.
        Jd = -R @ _skew3(np.asarray(down_m, dtype=np.float64).reshape(3))
        sd = max(float(down_sigma_rad), MIN_DOWN_SIGMA_RAD)
        info[:3, :3] += Jd.T @ Jd / (sd * sd)
    try:
        cov_x = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        cov_x = np.linalg.pinv(info)
    return Jc @ cov_x @ Jc.T, cov_x[:3, :3], cov_x[3:, 3:]


def _worst_std(cov: np.ndarray) -> float:
    return math.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0))


@dataclass(frozen=True)
class Uncertainty:
    """One pose's uncertainty, worked out once (``uncertainty``) for its quality and covariance:
    ``cov_centre_m2`` camera centre and ``cov_rotation_rad2`` rotation, both in the marker frame
    and from the solve alone; ``flip_risk`` 0..1 (see ``flip_risk``); ``p_other`` the other
    planar solution's probability left after the prior, and ``step_centre_m`` /
    ``step_rotation_rad`` the step to it (marker frame) for the covariance sent;
    ``corner_sigma_px`` the corner noise the covariance was worked out with; ``pending``: that
    noise is not measured yet (the fit is then judged against MIN_CORNER_SIGMA_PX); ``innovation``:
    the pose's rotation against the track's prediction (None: no track to judge it by)."""

    cov_centre_m2: np.ndarray
    cov_rotation_rad2: np.ndarray
    flip_risk: float
    p_other: float = 0.0
    step_centre_m: Optional[np.ndarray] = None
    step_rotation_rad: Optional[np.ndarray] = None
    corner_sigma_px: float = DEFAULT_CORNER_SIGMA_PX
    pending: bool = False
    cov_tvec_cam_m2: Optional[np.ndarray] = None
    step_tvec_m: Optional[np.ndarray] = None
    innovation: Optional[Innovation] = None

    @property
    def position_std_m(self) -> float:
        return math.sqrt(max(float(np.trace(self.cov_centre_m2)), 0.0))

    @property
    def attitude_std_rad(self) -> float:
        """Sigma of the worst-seen rotation axis (the largest eigenvalue), rad."""
        return _worst_std(self.cov_rotation_rad2)

    @property
    def sent_cov_centre_m2(self) -> np.ndarray:
        """The camera centre's mean squared error about the pose sent: the solve's, plus
        p_other times the step to the other solution squared."""
        if self.step_centre_m is None or self.p_other <= 0.0:
            return self.cov_centre_m2
        d = self.step_centre_m
        return self.cov_centre_m2 + self.p_other * np.outer(d, d)

    @property
    def sent_cov_tvec_cam_m2(self) -> np.ndarray:
        """The marker centre's (tvec, camera frame) mean squared error about the pose sent;
        without the solve's tvec covariance, the camera centre's (an upper bound)."""
        cov = self.cov_tvec_cam_m2 if self.cov_tvec_cam_m2 is not None else self.cov_centre_m2
        if self.step_tvec_m is None or self.p_other <= 0.0:
            return cov
        return cov + self.p_other * np.outer(self.step_tvec_m, self.step_tvec_m)

    @property
    def sent_cov_rotation_rad2(self) -> np.ndarray:
        if self.step_rotation_rad is None or self.p_other <= 0.0:
            return self.cov_rotation_rad2
        d = self.step_rotation_rad
        return self.cov_rotation_rad2 + self.p_other * np.outer(d, d)


def other_probability(pose: Pose, corner_sigma_px: Optional[float] = None) -> float:
    """The probability that the other planar solution (``pose.alternative``) is the true one,
    from the two fits alone: their chi-square costs 4 e^2 / s^2 (s: ``_cov_sigma_px``) as
    likelihoods. 0.5 for two equal fits; above 0.5 when the pose sent is the worse fit."""
    alt = pose.alternative
    if alt is None:
        return 0.0
    e, e_alt = float(pose.reprojection_error_px), float(alt.reprojection_error_px)
    if not _finite(e, e_alt):
        r = float(pose.ambiguity_ratio)
        return 0.5 * min(max(r, 0.0), 1.0) if math.isfinite(r) else 0.5
    s = _cov_sigma_px(pose, corner_sigma_px)
    half_diff = 2.0 * (e_alt * e_alt - e * e) / (s * s)
    return 1.0 / (1.0 + math.exp(min(max(half_diff, -700.0), 700.0)))


def _disagreement(pose: Pose, attitude_std_rad: float) -> float:
    """0 (the two solutions agree within the pose's own error) .. 1 (twice the bound apart)."""
    alt = pose.alternative
    if alt is None:
        return 0.0
    if not (np.all(np.isfinite(alt.R)) and np.all(np.isfinite(pose.R))):
        return 1.0
    bound_deg = max(AGREE_DEG, 3.0 * math.degrees(attitude_std_rad))
    apart_deg = float(rotation_angle_deg_3x3(pose.R, alt.R))
    return min(max((apart_deg - bound_deg) / bound_deg, 0.0), 1.0)


def uncertainty(
    pose: Pose,
    fx_px: float,
    marker_width_m: float,
    *,
    corner_sigma_px: Optional[float] = None,
    flip_resolved: bool = False,
    down_m: Optional[np.ndarray] = None,
    down_sigma_rad: Optional[float] = None,
) -> Uncertainty:
    """The solve's covariance and the flip risk of ``pose``, for ``pose_quality`` and the
    covariance functions (pass it as ``u`` to work it out once per pose). ``corner_sigma_px``:
    the measured corner noise; ``flip_resolved``: a prior ruled the other solution out;
    ``down_m``/``down_sigma_rad``: the attitude's down the choice used (``solve_covariance``)."""
    cov_c, cov_w, cov_t = _solve(
        pose, fx_px, marker_width_m, corner_sigma_px=corner_sigma_px, down_m=down_m, down_sigma_rad=down_sigma_rad
    )
    sigma = noise_sigma_px(corner_sigma_px)
    alt = pose.alternative
    if flip_resolved or alt is None:
        return Uncertainty(cov_c, cov_w, 0.0, corner_sigma_px=sigma, cov_tvec_cam_m2=cov_t)
    p = other_probability(pose, corner_sigma_px)
    risk = _disagreement(pose, _worst_std(cov_w)) * min(1.0, 2.0 * p)
    step_c = step_w = step_t = None
    if np.all(np.isfinite(alt.R)) and np.all(np.isfinite(alt.tvec)):
        step_c = np.asarray(alt.camera_position, dtype=np.float64) - np.asarray(pose.camera_position, dtype=np.float64)
        step_w = np.asarray(rvec_from_R(np.asarray(pose.R).T @ np.asarray(alt.R)), dtype=np.float64).reshape(3)
        step_t = np.asarray(alt.tvec, dtype=np.float64).reshape(3) - np.asarray(pose.tvec, dtype=np.float64).reshape(3)
    return Uncertainty(cov_c, cov_w, risk, p, step_c, step_w, sigma, cov_tvec_cam_m2=cov_t, step_tvec_m=step_t)


def result_uncertainty(
    result: FrameResult, frames: Optional[VehicleFrames], fx_px: float, marker_width_m: float
) -> Uncertainty:
    """``uncertainty`` of a processed frame's pose with what processing learnt about it: the
    measured corner noise, whether a prior ruled the other solution out (its choice), the
    attitude's down when the frame had one (``frames``: the mount and placement that give it),
    and the pose's agreement with its track (``track_innovation``)."""
    assert result.pose is not None
    choice = result.choice
    down_m = down_sigma = None
    if frames is not None and result.attitude is not None and result.prior_down_sigma_rad is not None:
        down_m, down_sigma = frames.R_local_marker[2], result.prior_down_sigma_rad
    u = uncertainty(
        result.pose,
        fx_px,
        marker_width_m,
        corner_sigma_px=result.corner_sigma_px,
        flip_resolved=resolved_by_prior(choice.resolved_by if choice is not None else None),
        down_m=down_m,
        down_sigma_rad=down_sigma,
    )
    return dataclasses.replace(u, pending=result.corner_noise_pending, innovation=result.track_innovation)


def flip_risk(
    pose: Pose,
    fx_px: Optional[float] = None,
    marker_width_m: Optional[float] = None,
    *,
    corner_sigma_px: Optional[float] = None,
) -> float:
    """0 (the other planar solution is no threat) .. 1 (a coin flip between two different poses).

    The other solution's probability (``other_probability``, doubled: 1 for two equal fits)
    times how far its rotation lies beyond the agreement bound (max of ``AGREE_DEG`` and 3
    sigma of the pose's attitude; without ``fx_px``/``marker_width_m`` the bound is
    ``AGREE_DEG``): 0 at the bound, full weight at twice it. Without ``pose.alternative``
    there is nothing to confuse the pose with.
    """
    if fx_px is None or marker_width_m is None:
        return _disagreement(pose, 0.0) * min(1.0, 2.0 * other_probability(pose, corner_sigma_px))
    return uncertainty(pose, fx_px, marker_width_m, corner_sigma_px=corner_sigma_px).flip_risk


def position_std_m(
    pose: Pose, fx_px: float, marker_width_m: float, *, corner_sigma_px: Optional[float] = None
) -> float:
    """Expected error (1 sigma, root sum of the three axes) of the camera position, metres,
    from the solve alone (``solve_covariance``; no flip risk)."""
    cov_c, _ = solve_covariance(pose, fx_px, marker_width_m, corner_sigma_px=corner_sigma_px)
    return math.sqrt(max(float(np.trace(cov_c)), 0.0))


def pose_quality(
    pose: Pose,
    fx_px: Optional[float] = None,
    marker_width_m: Optional[float] = None,
    *,
    flip_resolved: bool = False,
    corner_sigma_px: Optional[float] = None,
    u: Optional[Uncertainty] = None,
) -> int:
    """1 (worst) .. 100 (best) for a pose; -1 (LOST_QUALITY) is kept for "no pose".

    ``fx_px``/``marker_width_m``: the focal length (pixels) and marker width (metres) behind the
    expected error; without them the precision factor is left out. ``flip_resolved``: a prior
    (the vehicle's attitude, the tilt bound) chose the planar solution, so the alternative is no
    risk. ``corner_sigma_px``: the measured corner noise (None: DEFAULT_CORNER_SIGMA_PX).
    ``u``: ``uncertainty(...)`` (or ``result_uncertainty``) when the caller has it already; it
    then carries the corner noise and the flip risk.
    """
    e = float(pose.reprojection_error_px)
    if not _finite(e) or not (np.all(np.isfinite(pose.tvec)) and np.all(np.isfinite(pose.R))):
        return 1
    if u is None and fx_px is not None and marker_width_m is not None:
        u = uncertainty(pose, fx_px, marker_width_m, corner_sigma_px=corner_sigma_px, flip_resolved=flip_resolved)
    sigma = u.corner_sigma_px if u is not None else noise_sigma_px(corner_sigma_px)
    if u is not None and u.pending:
        # Unmeasured noise: the fit the least noisy camera would have (a lower bound).
        sigma = MIN_CORNER_SIGMA_PX
    f_fit = 1.0 / (1.0 + (max(e, 0.0) / (FIT_HALF_Z * sigma)) ** 4)
    f_precision = 1.0
    if u is not None:
        f_precision = 1.0 / (1.0 + (u.position_std_m / NEED_POSITION_M) ** 2)
        risk = u.flip_risk
    else:
        risk = 0.0 if flip_resolved else flip_risk(pose, corner_sigma_px=corner_sigma_px)
    f_track = 1.0
    if u is not None and u.innovation is not None:
        f_track = track_factor(u.innovation, math.degrees(u.attitude_std_rad))
    return int(min(100, max(1, round(100.0 * f_fit * f_precision * (1.0 - risk) * f_track))))


def track_factor(innovation: Innovation, attitude_std_deg: float = 0.0) -> float:
    """The track factor of the quality (module docstring): 1 within the turn allowance, 1/2 at
    TRACK_HALF allowances off the prediction."""
    if not math.isfinite(innovation.angle_deg):
        return 0.0
    allowance = turn_allowance_deg(innovation, attitude_std_deg)
    if allowance <= 0.0:
        return 1.0 if innovation.angle_deg <= 0.0 else 0.0
    return 1.0 / (1.0 + (innovation.angle_deg / (TRACK_HALF * allowance)) ** 4)


def position_covariance_cam(
    pose: Pose, fx_px: float, marker_width_m: float, u: Optional[Uncertainty] = None
) -> np.ndarray:
    """3x3 covariance of the camera position (m^2), in the camera frame, about the pose sent
    (the other solution's share included)."""
    u = u if u is not None else uncertainty(pose, fx_px, marker_width_m)
    return rotate_covariance(np.asarray(pose.R, dtype=np.float64), u.sent_cov_centre_m2)


def attitude_std_rad(pose: Pose, fx_px: float, marker_width_m: float, u: Optional[Uncertainty] = None) -> float:
    """Standard deviation of the worst attitude angle (rad) about the pose sent."""
    u = u if u is not None else uncertainty(pose, fx_px, marker_width_m)
    return _worst_std(u.sent_cov_rotation_rad2)


def pose_covariance_local(
    pose: Pose, frames: VehicleFrames, fx_px: float, marker_width_m: float, u: Optional[Uncertainty] = None
) -> List[float]:
    """MAVLink's 21-element upper-right triangle (row-major) of the 6x6 covariance of
    (x, y, z, roll, pitch, yaw) in the local frame: m^2 and rad^2 (``Uncertainty``'s
    covariance about the pose sent, rotated into the local frame)."""
    u = u if u is not None else uncertainty(pose, fx_px, marker_width_m)
    R = frames.R_local_marker
    full = np.zeros((6, 6))
    full[:3, :3] = R @ u.sent_cov_centre_m2 @ R.T
    full[3:, 3:] = R @ u.sent_cov_rotation_rad2 @ R.T
    return full[_TRIU6].tolist()
