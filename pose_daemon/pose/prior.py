"""Which planar solution to send, if any: the quality gate and the gravity prior.

A square's four corners fit two poses (the estimator's ``pose`` and its ``alternative``);
on small markers the wrong one often fits best. The vehicle knows which way is down: with
the camera mount and the marker placement, roll and pitch give the direction of gravity in
the camera frame, and each solution implies one too (from where the marker says down is).
The solution that agrees is chosen; when neither does the frame is ``inconsistent`` (not
sent). Without attitude, ``max_tilt_deg`` (the vehicle is near level) plays the same part,
and the track's continuity decides what is left. Before any of this, a pose whose
reprojection error is more than corner noise explains is not sent (``gated``): marker-free
rectangles fit a square's model worse than a marker does.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from dataclasses import dataclass
from typing import Callable, Deque, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from ..attitude import Attitude
from ..camera import Camera, Marker
from ..geometry import (
    VehicleFrames,
    angle_between_deg,
    paper_angles_deg_from_R_cam_marker,
    rotation_angle_deg_3x3,
)
from .heading_track import HeadingTrack
from .types import Pose

__all__ = [
    "AttitudeAccuracy",
    "PriorSettings",
    "Choice",
    "CornerNoise",
    "HeadingReference",
    "HeadingTerm",
    "RESOLVED_BY",
    "choose_solution",
    "down_variance_rad2",
    "gate_bound_px",
    "heading_sample",
    "heading_sigma_deg",
    "heading_unseen_by_down",
    "polish_toward",
    "polish_toward_down",
]

# flip_resolved_by: what picked the solution that was sent.
#   "attitude":   the autopilot's roll/pitch ruled one solution out (or clearly favoured it)
#   "tilt":       the vehicle-near-level prior ruled one out
#   "continuity": both were possible; the track's previous poses chose (at a track's first
#                 frame, the better fit)
#   "clear":      only one solution fits the corners (or both are the same pose)
# Choice.withheld: "gated" (the corners fit no marker), "inconsistent" (no solution agrees with
# the attitude or the tilt bound), "unresolved" (a wall marker with attitude before its heading
# reference is known: roll and pitch cannot tell its solutions apart, see HeadingReference).
RESOLVED_BY = ("attitude", "tilt", "continuity", "clear")
# Two solutions closer than this are one pose: nothing to choose (a face-on view).
SAME_POSE_DEG = 5.0
# A heading this far off the learnt reference in 5 frames in a row: the reference moved.
HEADING_RESET_DEG = 30.0
# Both candidates are polished unless the cheaper's unpolished cost is this much lower (sigma^2).
POLISH_BOTH_BELOW = 25.0
# No attitude is trusted to better than this in the polish, degrees.
MIN_PRIOR_SIGMA_DEG = 0.25
# The vision side's own share of the error in the down direction (small markers), degrees.
VISION_DOWN_SIGMA_DEG = 1.0
# A marker whose normal is further than this from the vertical (a wall marker): a turn about the
# vertical, which roll and pitch cannot see, is one of the directions its image shows worst.
HEADING_UNSEEN_FROM_VERTICAL_DEG = 45.0
# ... unless its own corners give the heading to this (1 sigma, degrees): the bound the heading
# reference was once held to before it was used at all.
HEADING_KNOWN_SIGMA_DEG = 2.0
# The tilt prior's polish takes max_tilt_deg as this many sigma of the vehicle's tilt (a bound
# is 3 sigma, as the attitude's bound is at least 3 of its sigma).
TILT_BOUND_SIGMAS = 3.0
# The attitude's accuracy is measured on frames whose image gives the down to this share of it.
ACCURACY_FROM_IMAGE_SHARE = 0.5


@dataclass(frozen=True)
class PriorSettings:
    """The choice's bounds (config: [attitude] and [estimator] keys)."""

    max_tilt_deg: float = 0.0  # 0: no tilt prior
    attitude_bound_deg: float = 15.0  # a solution whose down is further from the attitude's disagrees
    gate_rms_px: float = 1.0  # reprojection RMS bound for small markers, pixels
    gate_rms_frac: float = 0.01  # ... and as a fraction of the marker's side for large ones
    max_view_deg: float = 55.0  # a marker seen further off its face than this is not believed (0 = any)
    gate: bool = True
    attitude_sigma_deg: float = 1.0  # an attitude's accuracy when it does not state one
    polish: bool = True  # re-fit the chosen pose with the attitude's down as a prior term
    corner_sigma_px: float = 0.3  # corner noise the priors are weighed against when none is given
    heading_window_s: float = 1.5  # the tilt prior's heading track at a wall marker (0 = none)

    @classmethod
    def from_config(cls, cfg) -> PriorSettings:
        """From a Config's [attitude] and [gate] sections."""
        return cls(
            max_tilt_deg=cfg.attitude.max_tilt_deg,
            attitude_bound_deg=cfg.attitude.max_error_deg,
            gate_rms_px=cfg.gate.max_rms_px,
            gate_rms_frac=cfg.gate.max_rms_frac,
            max_view_deg=cfg.gate.max_view_deg,
            gate=cfg.gate.max_rms_px > 0,
            attitude_sigma_deg=cfg.attitude.sigma_deg,
            polish=cfg.attitude.polish,
            heading_window_s=cfg.attitude.heading_window_s,
        )


@dataclass(frozen=True)
class Choice:
    """The outcome for one frame: ``pose`` to send with ``resolved_by``, or ``withheld``
    ("inconsistent", "gated" or "unresolved") with ``reason``. ``down_error_deg``: the chosen pose's
    angle to the attitude's down (with attitude) or its tilt (tilt prior), else None."""

    pose: Optional[Pose]
    resolved_by: Optional[str] = None
    withheld: Optional[str] = None
    reason: str = ""
    down_error_deg: Optional[float] = None
    flipped: bool = False  # the estimator's alternative was chosen over its better fit
    attitude_sigma_deg: Optional[float] = None  # the accuracy the attitude was weighed at; None without one


def gate_bound_px(settings: PriorSettings, side_px: float) -> float:
    """The reprojection RMS a real marker of ``side_px`` (mean side, pixels) stays under.

    Corner noise is about the same number of pixels whatever the marker's size (a floor of
    ``gate_rms_px``, which also keeps small markers, whose corners are the noisiest, from
    being held to a fraction of a pixel they cannot meet); lens-model and blur errors grow
    with the image of the marker (``gate_rms_frac`` of its side)."""
    return max(settings.gate_rms_px, settings.gate_rms_frac * float(side_px))


def view_angle_deg(pose: Pose) -> float:
    """How far off its face the camera sees the marker: the angle between the marker's normal
    and the direction from its centre to the camera, degrees (0 = face-on)."""
    return angle_between_deg(pose.R[:, 2], -np.asarray(pose.tvec, dtype=np.float64))


def _swap(pose: Pose) -> Pose:
    """The alternative of ``pose`` as the pose sent, carrying ``pose`` as its alternative."""
    alt = pose.alternative
    assert alt is not None
    return dataclasses.replace(
        alt, alternative=dataclasses.replace(pose, alternative=None), ambiguity_ratio=pose.ambiguity_ratio
    )


@dataclass(frozen=True)
class HeadingTerm:
    """A prior term on the vehicle's heading for ``polish_toward``: the body's x axis in the
    local frame (``R_local_marker R^T forward_cam``, ``forward_cam`` the body's x axis in the
    camera frame) turned about the vertical to ``yaw_rad``, weighed ``weight_px`` per radian."""

    R_local_marker: np.ndarray
    forward_cam: np.ndarray
    yaw_rad: float
    weight_px: float


def polish_toward_down(
    pose: Pose,
    corners_px: np.ndarray,
    camera: Camera,
    marker: Marker,
    down_m: np.ndarray,
    down_cam: np.ndarray,
    weight_px: float,
    iterations: int = 3,
) -> Tuple[Pose, float]:
    """``pose`` re-fitted to its corners with a prior term pulling the down direction it
    implies (``R @ down_m``, ``down_m`` = down in the marker frame) towards ``down_cam``.

    Minimises sum |reprojection|^2 + weight_px^2 |R down_m - down_cam|^2 (Gauss-Newton on
    rvec, tvec; OpenCV's projection Jacobian through the distortion). ``weight_px`` = corner
    noise / the down direction's accuracy (radians): the two terms in the same units.
    Like PhotonVision's constrained solver and Limelight's MegaTag2, only the poorly seen
    part of the pose (the marker's tilt) moves. Returns the pose (its reprojection RMS
    recomputed) and the final cost in px^2."""
    return polish_toward(pose, corners_px, camera, marker, [(down_m, down_cam, weight_px)], iterations)


def polish_toward(
    pose: Pose,
    corners_px: np.ndarray,
    camera: Camera,
    marker: Marker,
    terms: Sequence[Tuple[np.ndarray, np.ndarray, float]],
    iterations: int = 3,
    heading: Optional[HeadingTerm] = None,
) -> Tuple[Pose, float]:
    """``polish_toward_down`` with any number of direction terms (dir in the marker frame,
    wanted dir in the camera frame, weight px): down, and the heading once it is known;
    ``heading`` adds a term on the vehicle's heading itself (``HeadingTerm``)."""
    obj = marker.object_points.astype(np.float64)
    uv = np.asarray(corners_px, dtype=np.float64).reshape(-1)
    rvec = np.asarray(pose.rvec, dtype=np.float64).reshape(3).copy()
    tvec = np.asarray(pose.tvec, dtype=np.float64).reshape(3).copy()
    terms = [(np.asarray(d_m, dtype=np.float64), np.asarray(d_c, dtype=np.float64), float(w)) for d_m, d_c, w in terms]

    def residual(rv: np.ndarray, tv: np.ndarray):
        img, J = cv2.projectPoints(obj, rv, tv, camera.K, camera.dist_coeffs)
        R, dR = cv2.Rodrigues(rv)
        rs, Js = [img.reshape(-1) - uv], [J[:, :6]]
        for d_m, d_c, w in terms:
            rs.append(w * (R @ d_m - d_c))
            J_dir = np.zeros((3, 6))
            # dR is (3, 9): d R.flat / d rvec_k, row-major R.
            J_dir[:, :3] = w * (dR.reshape(3, 3, 3) @ d_m).T
            Js.append(J_dir)
        if heading is not None:
            # yaw = atan2(v_y, v_x) of v = R_local_marker R^T forward_cam (the body's x axis in
            # the local frame); d v / d rvec_k = R_local_marker dR_k^T forward_cam.
            v = heading.R_local_marker @ (R.T @ heading.forward_cam)
            dv = heading.R_local_marker @ np.einsum("kij,i->jk", dR.reshape(3, 3, 3), heading.forward_cam)
            h2 = max(float(v[0] ** 2 + v[1] ** 2), 1e-12)
            turn = math.remainder(math.atan2(v[1], v[0]) - heading.yaw_rad, math.tau)
            rs.append(np.array([heading.weight_px * turn]))
            J_head = np.zeros((1, 6))
            J_head[0, :3] = heading.weight_px * (v[0] * dv[1] - v[1] * dv[0]) / h2
            Js.append(J_head)
        return np.concatenate(rs), np.vstack(Js)

    r, J = residual(rvec, tvec)
    cost = float(r @ r)
    lam = 1e-4
    eye = np.eye(6)
    for _ in range(iterations):
        H = J.T @ J
        g = J.T @ r
        ok, step = cv2.solve(H + lam * (eye * np.diag(H) + 1e-12 * eye), -g.reshape(6, 1))
        if not ok:
            break
        step = step.reshape(6)
        rv_new, tv_new = rvec + step[:3], tvec + step[3:]
        if tv_new[2] <= 0:
            lam *= 10.0
            continue
        r_new, J_new = residual(rv_new, tv_new)
        cost_new = float(r_new @ r_new)
        if cost_new < cost:
            converged = cost - cost_new < 1e-6 * cost + 1e-9
            rvec, tvec, r, J, cost = rv_new, tv_new, r_new, J_new, cost_new
            lam = max(lam / 10.0, 1e-9)
            if converged:
                break
        else:
            lam *= 10.0
    R = cv2.Rodrigues(rvec)[0]
    rms = float(np.sqrt(np.mean(np.sum(r[:8].reshape(4, 2) ** 2, axis=1))))
    a, b, c = paper_angles_deg_from_R_cam_marker(R)
    polished = dataclasses.replace(
        pose, rvec=rvec, tvec=tvec, R=R, alpha_deg=a, beta_deg=b, gamma_deg=c, reprojection_error_px=rms
    )
    return polished, cost


# Corner noise is believed within these bounds, pixels.
CORNER_SIGMA_MIN_PX, CORNER_SIGMA_MAX_PX = 0.01, 2.0


def _corner_sigma_from_rms(rms_px: Sequence[float]) -> float:
    """The corner noise the best fits' reprojection RMS values imply (their median / 0.589,
    see ``CornerNoise``), within the believed bounds."""
    median = sorted(rms_px)[len(rms_px) // 2]
    return min(max(median / 0.589, CORNER_SIGMA_MIN_PX), CORNER_SIGMA_MAX_PX)


class CornerNoise:
    """The corner noise of this camera and detector, from the best fits' reprojection RMS.

    Four corners fit a 6-DoF pose with 2 degrees of freedom to spare, so RMS^2 = sigma^2
    chi2_2 / 4 and the median RMS is 0.589 sigma. The polish weighs the attitude against it:
    a sharp camera's corners (the renderer's: hundredths of a pixel) are barely pulled, a
    webcam's small markers (0.3-0.4 px) are pulled as much as they need."""

    def __init__(self, window: int = 31, min_samples: int = 5) -> None:
        self._rms: Deque[float] = collections.deque(maxlen=window)
        self.min_samples = int(min_samples)
        self._sigma_px: Optional[float] = None  # worked out once per observed frame

    def observe(self, rms_px: float) -> None:
        if math.isfinite(rms_px) and rms_px >= 0:
            self._rms.append(float(rms_px))
            if len(self._rms) >= self.min_samples:
                self._sigma_px = _corner_sigma_from_rms(self._rms)

    @property
    def sigma_px(self) -> Optional[float]:
        return self._sigma_px

    def estimate_px(self, rms_px: float) -> float:
        """``sigma_px`` once measured; until then the same from the frames seen so far and
        this one (reprojection RMS ``rms_px``). A fixed guess would weigh the priors many times
        off: 0.3 px against a sharp camera's 0.02."""
        measured = self.sigma_px
        if measured is not None:
            return measured
        rms = list(self._rms)
        if math.isfinite(rms_px) and rms_px >= 0:
            rms.append(float(rms_px))
        if not rms:
            return PriorSettings.corner_sigma_px
        return _corner_sigma_from_rms(rms)


class AttitudeAccuracy:
    """How well the attitude's down really agrees with the image's: the attitude's accuracy as
    measured, where the one it states is too kind.

    The polish weighs the attitude at its stated accuracy, but what reaches the camera frame is
    worse by whatever the statement leaves out: a capture timestamp a few tens of milliseconds
    off (a webcam's, a USB transfer's) turns every turn rate into an attitude error, a camera
    mount a degree off adds its own tilt. Weighed as if it were exact, that error pulls poses the
    image already gives well off the truth (bench ambiguity: 40 ms of lag at 0.5 deg stated
    made the floor's sharp-corner median 0.34 against the estimator's 0.31 deg).

    Measured from the frames whose image gives the down to under half the attitude's sigma (its
    own down variance from the corners' information, ``down_variance_rad2``). The two downs
    differ by sigma^2 + s^2 per axis (s^2 the image's, half its ``down_variance_rad2``), so the
    angle between them, squared, is that times a chi-squared of 2 degrees, whose median is
    2 ln 2: a frame's angle is below its median exactly when angle^2 / (2 ln 2) - s^2 is below
    sigma^2, so the median of that over the frames is sigma^2 whatever each frame's s (and a
    frame with mislabelled corners does not move a median). ``sigma_deg`` is the larger of the
    stated and the measured: a too modest statement is kept (the image leaning on itself costs
    little), a too proud one is corrected.
    """

    def __init__(self, window: int = 100, min_samples: int = 10) -> None:
        self._excess: Deque[float] = collections.deque(maxlen=window)
        self.min_samples = int(min_samples)
        self._measured_deg: Optional[float] = None  # worked out once per observed frame

    def observe(self, angle_rad: float, image_variance_rad2: float, sigma_deg: float) -> None:
        """One frame: ``angle_rad`` between the attitude's down and the image's (the chosen
        solution's, unpolished), ``image_variance_rad2`` the image's down variance (both axes),
        ``sigma_deg`` the attitude's accuracy in use (the frame counts only when the image is
        twice as sure)."""
        if not (math.isfinite(angle_rad) and math.isfinite(image_variance_rad2)):
            return
        if (
            image_variance_rad2 / 2.0
            <= (ACCURACY_FROM_IMAGE_SHARE * math.radians(max(sigma_deg, MIN_PRIOR_SIGMA_DEG))) ** 2
        ):
            self._excess.append(angle_rad * angle_rad / (2.0 * math.log(2.0)) - image_variance_rad2 / 2.0)
            if len(self._excess) >= self.min_samples:
                median = sorted(self._excess)[len(self._excess) // 2]
                self._measured_deg = math.degrees(math.sqrt(max(median, 0.0)))

    @property
    def measured_deg(self) -> Optional[float]:
        """The attitude's down error per axis (1 sigma, degrees) the image measures, or None
        before ``min_samples`` frames."""
        return self._measured_deg

    def sigma_deg(self, stated_deg: float) -> float:
        """The accuracy to weigh the attitude at: the stated, or the measured where worse."""
        measured = self.measured_deg
        return stated_deg if measured is None else max(stated_deg, measured)


def down_variance_rad2(pose: Pose, camera: Camera, marker: Marker, down_m: np.ndarray, corner_sigma_px: float) -> float:
    """The variance (rad^2, both axes together) of the down direction ``R @ down_m`` that
    ``pose``'s four corners give at corner noise ``corner_sigma_px``: the rotation block of
    the inverse of the corners' information (OpenCV's projection Jacobian), through the
    down's own Jacobian."""
    obj = marker.object_points.astype(np.float64)
    rvec = np.asarray(pose.rvec, dtype=np.float64).reshape(3)
    tvec = np.asarray(pose.tvec, dtype=np.float64).reshape(3)
    _, J = cv2.projectPoints(obj, rvec, tvec, camera.K, camera.dist_coeffs)
    ok, cov = cv2.invert(J[:, :6].T @ J[:, :6], flags=cv2.DECOMP_CHOLESKY)
    if not ok:
        return math.inf
    dR = cv2.Rodrigues(rvec)[1]  # (3, 9): d R.flat / d rvec_k, row-major R
    D = (dR.reshape(3, 3, 3) @ np.asarray(down_m, dtype=np.float64)).T  # d (R down_m) / d rvec
    var = float(np.trace(D @ cov[:3, :3] @ D.T)) * corner_sigma_px**2
    return var if math.isfinite(var) and var >= 0 else math.inf


class HeadingReference:
    """The constant turn between the autopilot's heading and the marker's local frame.

    The autopilot's yaw is on its own reference (compass, EKF origin), the marker's local
    frame on the marker's; the difference stays put while the marker does. Learnt from the
    frames whose heading the marker gives without doubt (one solution, or two that agree on
    the heading, or two the down direction told apart with a wide margin; a wall marker's
    heading taken given the attitude's down, ``heading_sample``), it lets the yaw decide too: a
    wall marker's left/right ambiguity turns about the vertical, which roll and pitch cannot
    see. ``offset_rad`` is None until ``min_samples`` give it to ``max_sigma_deg``.

    It is used from its fourth sample on, with its own sigma (the samples' spread over the root
    of their number) as the heading term's weight: on 20-40 px markers with 0.3 px of corner
    noise a wall marker's heading from the image alone is 5-7 deg (1 sigma) off, so every frame
    that waited for a reference known to 2 deg (8+ samples) was a coin toss; a reference from 4
    samples already halves that error, and each later frame sharpens it (with 3 the spread of
    so few samples was sometimes too small, and the pull too strong, in the bench's flights).
    """

    def __init__(self, *, window: int = 60, min_samples: int = 4, max_sigma_deg: float = 10.0) -> None:
        self._samples: Deque[float] = collections.deque(maxlen=window)
        self.min_samples, self.max_sigma_deg = int(min_samples), float(max_sigma_deg)
        self._cached: Optional[Tuple[float, float]] = None
        self._misses = 0

    def reset(self) -> None:
        self._samples.clear()
        self._cached = None
        self._misses = 0

    def check(self, heading_error_deg: float) -> None:
        """The best solution's heading is ``heading_error_deg`` off the prediction: several
        frames in a row far off mean the autopilot's heading reference moved (an EKF yaw
        reset, a reboot); the reference is learnt again."""
        self._misses = self._misses + 1 if heading_error_deg > HEADING_RESET_DEG else 0
        if self._misses >= 5:
            self.reset()

    def observe(self, yaw_marker_rad: float, yaw_autopilot_rad: float) -> None:
        self._samples.append(
            math.atan2(math.sin(yaw_marker_rad - yaw_autopilot_rad), math.cos(yaw_marker_rad - yaw_autopilot_rad))
        )
        self._cached = None

    def _estimate(self) -> Optional[Tuple[float, float]]:
        """(circular mean of the samples near the median, robust spread in degrees)."""
        if self._cached is None and len(self._samples) >= self.min_samples:
            # Plain floats: 60 samples, once a frame; numpy's per-call cost would dominate.
            a = list(self._samples)
            mean = math.atan2(sum(math.sin(v) for v in a), sum(math.cos(v) for v in a))
            dev = [abs(math.remainder(v - mean, math.tau)) for v in a]
            spread = math.degrees(sorted(dev)[len(dev) // 2]) * 1.4826  # MAD -> sigma
            limit = max(3.0 * math.radians(spread), math.radians(2.0))
            keep = [v for v, d in zip(a, dev) if d <= limit]
            if keep:
                mean = math.atan2(sum(math.sin(v) for v in keep), sum(math.cos(v) for v in keep))
            self._cached = (mean, spread)
        return self._cached

    def _ready(self) -> Optional[Tuple[float, float]]:
        """(offset rad, its sigma deg) once the offset is known to ``max_sigma_deg``."""
        est = self._estimate()
        if est is None:
            return None
        sigma = max(est[1] / math.sqrt(len(self._samples)), 0.25)
        return (est[0], sigma) if sigma <= self.max_sigma_deg else None

    def reference(self) -> Optional[Tuple[float, float]]:
        """(offset rad, its sigma deg), or None while the offset is not known well enough."""
        return self._ready()

    @property
    def offset_rad(self) -> Optional[float]:
        ready = self._ready()
        return ready[0] if ready is not None else None

    @property
    def sigma_deg(self) -> Optional[float]:
        """The offset's own uncertainty: the samples' spread over the root of their number."""
        ready = self._ready()
        return ready[1] if ready is not None else None


def heading_unseen_by_down(frames: VehicleFrames) -> bool:
    """Whether the marker's normal is more than HEADING_UNSEEN_FROM_VERTICAL_DEG from the
    vertical (a wall marker): then a turn about the vertical tilts its normal, the direction a
    small marker's image shows worst, and roll and pitch cannot see it."""
    cos_normal_vertical = abs(float(frames.R_local_marker[2][2]))
    return cos_normal_vertical < math.cos(math.radians(HEADING_UNSEEN_FROM_VERTICAL_DEG))


def heading_sigma_deg(
    pose: Pose,
    corners_px: np.ndarray,
    camera: Camera,
    marker: Marker,
    frames: VehicleFrames,
    down_cam: np.ndarray,
    sigma_down_deg: float,
    corner_sigma_px: float,
) -> float:
    """How well ``pose``'s corners (noise ``corner_sigma_px``) and a down direction known to
    ``sigma_down_deg`` give its turn about the vertical (``down_cam``): 1 sigma, degrees, from
    the linearised least squares (the turn is a rotation in the camera frame left of R)."""
    obj = marker.object_points.astype(np.float64)
    R0 = np.asarray(pose.R, dtype=np.float64)
    t0 = np.asarray(pose.tvec, dtype=np.float64).reshape(3)
    d_m = frames.R_local_marker[2]
    w = max(corner_sigma_px, 1e-6) / math.radians(sigma_down_deg)

    def residual(x: np.ndarray) -> np.ndarray:
        R = cv2.Rodrigues(x[:3])[0] @ R0
        img, _ = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t0 + x[3:], camera.K, camera.dist_coeffs)
        return np.concatenate([img.reshape(-1), w * (R @ d_m)])

    r0 = residual(np.zeros(6))
    J = np.empty((r0.size, 6))
    h = 1e-6
    for k in range(6):
        x = np.zeros(6)
        x[k] = h
        J[:, k] = (residual(x) - r0) / h
    info = J.T @ J
    ok, cov = cv2.invert(info, flags=cv2.DECOMP_SVD)
    d = np.asarray(down_cam, dtype=np.float64)
    d = d / np.linalg.norm(d)
    var = float(d @ cov[:3, :3] @ d) * corner_sigma_px**2
    return math.degrees(math.sqrt(var)) if var > 0 and math.isfinite(var) else 180.0


def heading_sample(
    pose: Pose,
    corners_px: Optional[np.ndarray],
    camera: Optional[Camera],
    marker: Optional[Marker],
    frames: VehicleFrames,
    down_cam: np.ndarray,
    weight_px: float,
) -> Pose:
    """The pose whose heading teaches the heading reference: ``pose`` re-fitted towards the
    attitude's down (``polish_toward_down``, weight ``weight_px``) where the down does not see
    the heading (a wall marker, ``heading_unseen_by_down``), else ``pose`` itself.

    A wall marker's image gives its tilt about the horizontal and its turn about the vertical
    (the heading) with correlated errors, and the frames that teach are chosen by the first
    (their down told the two solutions apart): a raw solution's heading then carries the
    part of that tilt's error the choice selected. On 20-40 px markers with 0.3 px of corner
    noise that bias was 3-10 deg for seconds at a time, of one sign (the bench's wall flight,
    seed 0), and the reference learnt it at a stated sigma of 1-3 deg; the heading term then
    pulled poses more than 10 deg off. Given the down, the heading is freed of that part:
    the same frames teach a reference within 1-3 deg of the truth."""
    if corners_px is None or camera is None or marker is None or not heading_unseen_by_down(frames):
        return pose
    return polish_toward_down(pose, corners_px, camera, marker, frames.R_local_marker[2], down_cam, weight_px)[0]


def decisive_polish(cost: List[float], best: int, other: int) -> bool:
    """Whether the unpolished costs (in sigmas squared) already rule ``other`` out."""
    return cost[other] - cost[best] > POLISH_BOTH_BELOW


def _body_yaw(frames: VehicleFrames, pose: Pose) -> float:
    R = frames.vehicle_pose(pose.R, pose.tvec).R_local_body
    return math.atan2(R[1, 0], R[0, 0])


def choose_solution(
    pose: Pose,
    frames: VehicleFrames,
    *,
    attitude: Optional[Attitude],
    settings: PriorSettings,
    side_px: float,
    by_continuity: Callable[[Pose], Pose],
    corners_px: Optional[np.ndarray] = None,
    camera: Optional[Camera] = None,
    marker: Optional[Marker] = None,
    heading: Optional[HeadingReference] = None,
    corner_sigma_px: Optional[float] = None,
    heading_track: Optional[HeadingTrack] = None,
    t_capture_s: Optional[float] = None,
    attitude_accuracy: Optional[AttitudeAccuracy] = None,
) -> Choice:
    """The solution to send for the estimator's ``pose`` (the better fit, its other planar
    solution in ``pose.alternative``), or why none is sent.

    ``attitude``: the vehicle's at the frame's capture time, or None; ``side_px``: the
    marker's mean side in the image; ``by_continuity(pose)``: the track's choice between
    ``pose`` and its alternative (returns one of the two). ``heading``: the track of the
    autopilot's heading reference (learnt and used here), or None for roll and pitch only;
    ``corner_sigma_px`` the corner noise (``CornerNoise.estimate_px``; else ``settings``').
    With ``corners_px``, ``camera`` and ``marker`` and ``settings.polish``, an attitude also
    polishes the candidates (``polish_toward``) and the one with the lower cost is chosen.
    ``heading_track`` (with ``t_capture_s``): the tilt prior's track of a wall marker's recent
    headings, which then chooses and polishes the heading too (``_level_wall``)."""
    bound_px = gate_bound_px(settings, side_px)
    if settings.gate and pose.reprojection_error_px > bound_px:
        return Choice(
            None, withheld="gated", reason=f"reprojection RMS {pose.reprojection_error_px:.2f} px > {bound_px:.2f} px"
        )
    alt = pose.alternative
    max_view = settings.max_view_deg if settings.gate and settings.max_view_deg > 0 else 180.0
    view = view_angle_deg(pose)
    alt_ok = (
        alt is not None
        and (not settings.gate or alt.reprojection_error_px <= bound_px)
        and view_angle_deg(alt) <= max_view
    )
    if view > max_view and not alt_ok:
        # Long rectangles pass for squares seen very obliquely (measured on clutter: 58-71 deg);
        # a real marker that oblique is rarely found and its pose is poor anyway.
        return Choice(None, withheld="gated", reason=f"marker seen {view:.0f} deg off its face (> {max_view:g})")
    # Only the alternative is believable when the pose is seen too far off its face: it is the one.
    swapped = view > max_view
    two = bool(not swapped and alt_ok and alt is not None and rotation_angle_deg_3x3(pose.R, alt.R) >= SAME_POSE_DEG)
    choice = _choose(
        _swap(pose) if swapped else pose,
        two,
        frames,
        attitude,
        settings,
        bound_px,
        by_continuity,
        corners_px,
        camera,
        marker,
        heading,
        corner_sigma_px,
        heading_track=heading_track if t_capture_s is not None else None,
        t_capture_s=t_capture_s,
        attitude_accuracy=attitude_accuracy,
    )
    return dataclasses.replace(choice, flipped=choice.pose is not None) if swapped else choice


def _choose(
    pose: Pose,
    two: bool,
    frames: VehicleFrames,
    attitude: Optional[Attitude],
    settings: PriorSettings,
    bound_px: float,
    by_continuity: Callable[[Pose], Pose],
    corners_px: Optional[np.ndarray],
    camera: Optional[Camera],
    marker: Optional[Marker],
    heading: Optional[HeadingReference],
    corner_sigma_px: Optional[float],
    *,
    heading_track: Optional[HeadingTrack] = None,
    t_capture_s: Optional[float] = None,
    attitude_accuracy: Optional[AttitudeAccuracy] = None,
) -> Choice:
    """choose_solution past the gate: ``two`` = the alternative is still a contender."""
    candidates: List[Pose] = [pose, _swap(pose)] if two else [pose]
    down_meas = [frames.down_cam_from_marker(c.R) for c in candidates]
    noise_px = settings.corner_sigma_px if corner_sigma_px is None else corner_sigma_px

    if attitude is not None:
        stated_deg = math.degrees(attitude.sigma_rad) if attitude.sigma_rad is not None else settings.attitude_sigma_deg
        # Weighed at what the image has measured of it where that is worse than stated (a late
        # timestamp, a mount a degree off), learnt from the frames before this one.
        sigma_att_deg = attitude_accuracy.sigma_deg(stated_deg) if attitude_accuracy is not None else stated_deg
        choice = _choose_by_attitude(
            pose,
            candidates,
            down_meas,
            frames,
            attitude,
            settings,
            bound_px,
            by_continuity,
            corners_px,
            camera,
            marker,
            heading,
            noise_px,
            sigma_att_deg,
            attitude_accuracy,
        )
        return dataclasses.replace(choice, attitude_sigma_deg=sigma_att_deg)

    if settings.max_tilt_deg > 0:
        level = frames.down_cam_level
        tilt = [angle_between_deg(d, level) for d in down_meas]
        agree = [i for i in range(len(candidates)) if tilt[i] <= settings.max_tilt_deg]
        if not agree:
            return Choice(
                None,
                withheld="inconsistent",
                reason=f"the vehicle would be tilted {min(tilt):.1f} deg (max_tilt_deg {settings.max_tilt_deg:g})",
            )
        if settings.polish and corners_px is not None and camera is not None and marker is not None:
            if not heading_unseen_by_down(frames):  # the down sees the mirror: the polished costs choose
                return _polish_level(
                    candidates, agree, frames, settings, bound_px, corners_px, camera, marker, noise_px
                )
            return _level_wall(
                pose,
                candidates,
                agree,
                frames,
                settings,
                bound_px,
                by_continuity,
                corners_px,
                camera,
                marker,
                noise_px,
                heading_track,
                t_capture_s,
            )
        if len(candidates) == 1:
            return Choice(pose, "clear", down_error_deg=tilt[0])
        best = _tilt_or_continuity(pose, agree, by_continuity)
        return Choice(
            candidates[best],
            "tilt" if len(agree) == 1 else "continuity",
            down_error_deg=tilt[best],
            flipped=best == 1,
        )

    if len(candidates) == 1:
        return Choice(pose, "clear")
    chosen = by_continuity(pose)
    return Choice(chosen, "continuity", flipped=chosen is not pose)


def _tilt_or_continuity(pose: Pose, agree: List[int], by_continuity: Callable[[Pose], Pose]) -> int:
    """Which candidate (0: ``pose``, 1: its alternative) the tilt bound leaves, or where it
    leaves both, the track's continuity picks."""
    if len(agree) == 1:
        return agree[0]
    return 0 if by_continuity(pose) is pose else 1


def _level_wall(
    pose: Pose,
    candidates: List[Pose],
    agree: List[int],
    frames: VehicleFrames,
    settings: PriorSettings,
    bound_px: float,
    by_continuity: Callable[[Pose], Pose],
    corners_px: np.ndarray,
    camera: Camera,
    marker: Marker,
    corner_sigma_px: float,
    track: Optional[HeadingTrack],
    t_capture_s: Optional[float],
) -> Choice:
    """The tilt prior's polish at a wall marker, whose mirror turns about the vertical, which
    the down does not see.

    Without a heading ``track`` (or before it predicts), the tilt bound and the track's
    continuity choose as without the polish (choosing by the polished costs flipped more:
    24.8 against 22.8 % on bench ambiguity's wall flight at 20-40 px with 0.3 px of noise),
    and the chosen pose is pulled towards a level vehicle's down (``_level_terms``): that takes
    out the part of its heading error that comes with its tilt error (22.8 -> 14.1 % flips
    there). With a track, every candidate within the bound is pulled towards level and teaches
    it (as the image gives it, never as pulled towards the track); once it predicts, the
    candidate whose fit and heading together cost least is chosen and pulled towards the
    prediction too (weight: corner noise over the prediction's own sigma): 14.1 -> 2.0 %.
    Withheld as ``_polish_level`` withholds. The pose sent keeps its own alternative."""
    terms = _level_terms(frames, settings, corner_sigma_px)
    if track is None or t_capture_s is None:
        best = _tilt_or_continuity(pose, agree, by_continuity)
        polished = polish_toward(candidates[best], corners_px, camera, marker, terms)[0]
    else:
        level = {i: polish_toward(candidates[i], corners_px, camera, marker, terms) for i in agree}
        yaw = {i: _body_yaw(frames, level[i][0]) for i in agree}
        lowest = min(level[i][1] for i in agree)
        noise2 = max(corner_sigma_px, 1e-3) ** 2
        fit_cost = {i: (level[i][1] - lowest) / noise2 for i in agree}
        prediction = track.predict(t_capture_s)
        track.add(t_capture_s, [yaw[i] for i in agree], [fit_cost[i] for i in agree])
        if prediction is None:
            best = _tilt_or_continuity(pose, agree, by_continuity)
            polished = level[best][0]
        else:
            spread = math.hypot(prediction.sigma_rad, prediction.sample_sigma_rad)
            best = min(
                agree,
                key=lambda i: fit_cost[i] + (math.remainder(yaw[i] - prediction.yaw_rad, math.tau) / spread) ** 2,
            )
            term = HeadingTerm(
                frames.R_local_marker,
                frames.R_cam_body[:, 0],
                prediction.yaw_rad,
                corner_sigma_px / max(prediction.sigma_rad, math.radians(MIN_PRIOR_SIGMA_DEG)),
            )
            polished = polish_toward(level[best][0], corners_px, camera, marker, terms, heading=term)[0]
    tilt_deg = angle_between_deg(frames.down_cam_from_marker(polished.R), frames.down_cam_level)
    withheld = _leaves_level(polished, tilt_deg, settings, bound_px)
    if withheld is not None:
        return withheld
    if len(candidates) == 1:
        return Choice(polished, "clear", down_error_deg=tilt_deg)
    return Choice(polished, "tilt" if len(agree) == 1 else "continuity", down_error_deg=tilt_deg, flipped=best == 1)


def _polish_level(
    candidates: List[Pose],
    agree: List[int],
    frames: VehicleFrames,
    settings: PriorSettings,
    bound_px: float,
    corners_px: np.ndarray,
    camera: Camera,
    marker: Marker,
    corner_sigma_px: float,
) -> Choice:
    """The tilt prior's polish: each candidate within ``max_tilt_deg`` re-fitted with its down
    pulled towards a level vehicle's (``_level_terms``), the lower cost chosen; withheld as the
    attitude's polish is when the polished pose leaves the tilt bound or the gate."""
    terms = _level_terms(frames, settings, corner_sigma_px)
    results = {i: polish_toward(candidates[i], corners_px, camera, marker, terms) for i in agree}
    best = min(results, key=lambda i: results[i][1])
    polished = results[best][0]
    tilt = angle_between_deg(frames.down_cam_from_marker(polished.R), frames.down_cam_level)
    withheld = _leaves_level(polished, tilt, settings, bound_px)
    if withheld is not None:
        return withheld
    if len(candidates) == 1:
        return Choice(polished, "clear", down_error_deg=tilt)
    other = dataclasses.replace(results[1 - best][0] if 1 - best in results else candidates[1 - best], alternative=None)
    return Choice(dataclasses.replace(polished, alternative=other), "tilt", down_error_deg=tilt, flipped=best == 1)


def _level_terms(
    frames: VehicleFrames, settings: PriorSettings, corner_sigma_px: float
) -> List[Tuple[np.ndarray, np.ndarray, float]]:
    """The tilt prior's term for ``polish_toward``: the marker's down pulled towards a level
    vehicle's, ``max_tilt_deg`` taken as TILT_BOUND_SIGMAS sigma of the vehicle's tilt."""
    sigma_deg = max(settings.max_tilt_deg / TILT_BOUND_SIGMAS, MIN_PRIOR_SIGMA_DEG)
    return [(frames.R_local_marker[2], frames.down_cam_level, corner_sigma_px / math.radians(sigma_deg))]


def _leaves_level(polished: Pose, tilt_deg: float, settings: PriorSettings, bound_px: float) -> Optional[Choice]:
    """The "inconsistent" Choice when a pose polished towards level is tilted past
    ``max_tilt_deg`` or fails the gate; else None."""
    if tilt_deg <= settings.max_tilt_deg and not (settings.gate and polished.reprojection_error_px > bound_px):
        return None
    return Choice(
        None,
        withheld="inconsistent",
        reason=(
            f"the vehicle would be tilted {tilt_deg:.1f} deg (max_tilt_deg {settings.max_tilt_deg:g}), "
            f"reprojection RMS {polished.reprojection_error_px:.2f} px (bound {bound_px:.2f})"
        ),
    )


def _choose_by_attitude(
    pose: Pose,
    candidates: List[Pose],
    down_meas: List[np.ndarray],
    frames: VehicleFrames,
    attitude: Attitude,
    settings: PriorSettings,
    bound_px: float,
    by_continuity: Callable[[Pose], Pose],
    corners_px: Optional[np.ndarray],
    camera: Optional[Camera],
    marker: Optional[Marker],
    heading: Optional[HeadingReference],
    corner_sigma_px: float,
    sigma_att_deg: float,
    accuracy: Optional[AttitudeAccuracy],
) -> Choice:
    """The attitude's choice (and polish), the attitude weighed at ``sigma_att_deg``;
    ``accuracy`` learns from this frame how well the attitude agrees with the image."""
    roll, pitch, yaw = attitude.rpy_rad
    down_att = frames.down_cam_from_attitude(roll, pitch)
    err = [angle_between_deg(d, down_att) for d in down_meas]
    bound_deg = max(settings.attitude_bound_deg, 3.0 * sigma_att_deg)
    sigma_down_deg = math.hypot(sigma_att_deg, VISION_DOWN_SIGMA_DEG)
    # Each candidate's cost in sigmas squared: its down, and its heading once that is known.
    cost = [(e / sigma_down_deg) ** 2 for e in err]
    reference = heading.reference() if heading is not None else None
    yaw_local: Optional[float] = None  # the attitude's heading on the marker's local frame
    head: List[float] = []
    if reference is not None:
        assert heading is not None
        offset, sigma_reference_deg = reference
        sigma_head_deg = math.hypot(sigma_down_deg, sigma_reference_deg)
        # The heading alone (the body's yaw), not a direction: a direction's tilt would count
        # the attitude's pitch a second time beside the down.
        yaw_local = yaw + offset
        head = [abs(math.degrees(math.remainder(_body_yaw(frames, c) - yaw_local, math.tau))) for c in candidates]
        heading.check(min(head))
        cost = [c + (h / sigma_head_deg) ** 2 for c, h in zip(cost, head)]
    best = min(range(len(candidates)), key=lambda i: cost[i])
    decisive = len(candidates) == 1 or cost[1 - best] - cost[best] > 4.0  # 2 sigma
    if accuracy is not None and decisive and err[best] <= bound_deg and camera is not None and marker is not None:
        accuracy.observe(
            math.radians(err[best]),
            down_variance_rad2(candidates[best], camera, marker, frames.R_local_marker[2], corner_sigma_px),
            sigma_att_deg,
        )

    # The down term's weight in a polish: corner noise against the attitude's accuracy (radians).
    w_down = corner_sigma_px / math.radians(max(sigma_att_deg, MIN_PRIOR_SIGMA_DEG))
    if (
        heading is not None
        and err[best] <= bound_deg
        and (
            len(candidates) == 1
            or err[1 - best] - err[best] > 4.0 * sigma_down_deg
            or abs(math.remainder(_body_yaw(frames, candidates[0]) - _body_yaw(frames, candidates[1]), math.tau))
            < math.radians(2.0)
        )
    ):
        # The heading of this frame is known without the heading prior: learn from it (not
        # from a frame whose down is off: it is withheld, and its corners may be mislabelled).
        heading.observe(
            _body_yaw(frames, heading_sample(candidates[best], corners_px, camera, marker, frames, down_att, w_down)),
            yaw,
        )

    if (
        heading is not None
        and reference is None
        and heading_unseen_by_down(frames)
        and corners_px is not None
        and camera is not None
        and marker is not None
    ):
        # A wall marker's mirror solution (and its noise) turns about the vertical: until the
        # heading reference is known, roll and pitch cannot say which is right, and only sharp
        # corners give the heading well enough alone. The frame still taught the reference
        # (above); otherwise it is not sent.
        sigma_heading = heading_sigma_deg(
            candidates[best],
            corners_px,
            camera,
            marker,
            frames,
            down_att,
            max(sigma_att_deg, MIN_PRIOR_SIGMA_DEG),
            corner_sigma_px,
        )
        if sigma_heading > HEADING_KNOWN_SIGMA_DEG:
            return Choice(
                None,
                withheld="unresolved",
                reason=(
                    f"the heading reference is not known yet and the image gives the heading to "
                    f"{sigma_heading:.1f} deg (1 sigma): roll and pitch cannot choose for a wall marker"
                ),
            )

    # Where the vision already agrees with the attitude to within the attitude's own noise,
    # the prior could move it by a fraction of that noise: not worth a re-fit per frame.
    agrees = err[best] <= max(sigma_att_deg, MIN_PRIOR_SIGMA_DEG) and (
        reference is None or head[best] <= math.hypot(sigma_att_deg, reference[1])
    )
    if (
        settings.polish
        and corners_px is not None
        and camera is not None
        and marker is not None
        and not (agrees and decisive)
    ):
        # The image term carries the vision's own uncertainty: the prior's weight is the
        # attitude's alone (and the heading reference's).
        sigma_prior_deg = max(sigma_att_deg, MIN_PRIOR_SIGMA_DEG)
        terms = [(frames.R_local_marker[2], down_att, w_down)]
        head_term: Optional[HeadingTerm] = None
        if yaw_local is not None and reference is not None:
            sigma_yaw_deg = math.hypot(sigma_prior_deg, reference[1])
            head_term = HeadingTerm(
                frames.R_local_marker,
                frames.R_cam_body[:, 0],
                yaw_local,
                corner_sigma_px / math.radians(sigma_yaw_deg),
            )
        # The cheap costs' favourite first; the other too only when it could still win.
        order = [best] + [i for i in range(len(candidates)) if i != best]
        results = {best: polish_toward(candidates[best], corners_px, camera, marker, terms, heading=head_term)}
        for i in order[1:]:
            if not decisive_polish(cost, best, i):
                results[i] = polish_toward(candidates[i], corners_px, camera, marker, terms, heading=head_term)
        best = min(results, key=lambda i: results[i][1])
        polished = results[best][0]
        e = angle_between_deg(frames.down_cam_from_marker(polished.R), down_att)
        if e > bound_deg or (settings.gate and polished.reprojection_error_px > bound_px):
            return Choice(
                None,
                withheld="inconsistent",
                reason=(
                    f"no solution agrees with the attitude: down {e:.1f} deg off (bound "
                    f"{bound_deg:.1f}), reprojection RMS {polished.reprojection_error_px:.2f} px "
                    f"(bound {bound_px:.2f})"
                ),
            )
        if len(candidates) == 1:
            return Choice(polished, "clear", down_error_deg=e)
        other = dataclasses.replace(
            results[1 - best][0] if 1 - best in results else candidates[1 - best], alternative=None
        )
        return Choice(dataclasses.replace(polished, alternative=other), "attitude", down_error_deg=e, flipped=best == 1)

    if err[best] > bound_deg:
        return Choice(
            None,
            withheld="inconsistent",
            reason=f"the marker's down is {err[best]:.1f} deg from the attitude's (bound {bound_deg:.1f})",
        )
    if len(candidates) == 1:
        return Choice(pose, "clear", down_error_deg=err[0])
    if decisive:
        return Choice(candidates[best], "attitude", down_error_deg=err[best], flipped=best == 1)
    chosen = 0 if by_continuity(pose) is pose else 1
    if err[chosen] > bound_deg:
        chosen = best
    return Choice(candidates[chosen], "continuity", down_error_deg=err[chosen], flipped=chosen == 1)
