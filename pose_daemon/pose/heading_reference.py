"""The heading the marker gives, against the autopilot's: the reference between the two
(HeadingReference), whether the down direction can see a marker's heading at all, how well its
corners give it, and the pose that teaches the reference."""

from __future__ import annotations

import collections
import math
from typing import Deque, Optional, Tuple

import cv2
import numpy as np

from ..camera import Camera, Marker
from ..geometry import VehicleFrames
from .prior_polish import polish_toward_down
from .types import Pose

# A heading this far off the learnt reference in 5 frames in a row: the reference moved.
HEADING_RESET_DEG = 30.0
# A marker whose normal is further than this from the vertical (a wall marker): a turn about the
# vertical, which roll and pitch cannot see, is one of the directions its image shows worst.
HEADING_UNSEEN_FROM_VERTICAL_DEG = 45.0


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
